-- The spans of the samples inside time ranges of wagons (the regions to cut again), each with
-- its key: range i is wagon $wagon_ids[i] in [$from_utc[i], $to_utc[i]]; a range begins and
-- ends at a gap longer than $gap_s (or at the wagon's first or last sample), so the spans
-- found are the wagon's spans there. Only the samples of the ranges are read.
-- data_key: the span's bounds, its sample rows, each file's identity, bytes and rows in the
-- span, and its events as the simulation reads them (those whose activation is in the span:
-- id, activation, release, complete; not when they were detected, so the same files give the
-- same keys in any warehouse).
-- Parameters: $wagon_ids, $from_utc, $to_utc (lists of the same length), $gap_s.
WITH ranges AS (
    SELECT
        unnest(CAST($wagon_ids AS VARCHAR[]))   AS wagon_id,
        unnest(CAST($from_utc AS TIMESTAMP[]))  AS from_utc,
        unnest(CAST($to_utc AS TIMESTAMP[]))    AS to_utc
),
inside AS (
    SELECT s.wagon_id, s.time_utc, s.file_id
    FROM samples AS s
    JOIN ranges AS r
      ON s.wagon_id = r.wagon_id
     AND s.time_utc BETWEEN r.from_utc AND r.to_utc
    WHERE list_contains(CAST($wagon_ids AS VARCHAR[]), s.wagon_id)
),
seconds AS (
    SELECT wagon_id, time_utc, count(*) AS sample_rows
    FROM inside
    GROUP BY wagon_id, time_utc
),
marked AS (
    SELECT
        wagon_id, time_utc, sample_rows,
        CASE
            WHEN epoch(time_utc) - lag(epoch(time_utc)) OVER w > $gap_s THEN 1
            WHEN lag(time_utc) OVER w IS NULL THEN 1
            ELSE 0
        END AS starts
    FROM seconds
    WINDOW w AS (PARTITION BY wagon_id ORDER BY time_utc)
),
numbered AS (
    SELECT
        wagon_id, time_utc, sample_rows,
        sum(starts) OVER (
            PARTITION BY wagon_id ORDER BY time_utc ROWS UNBOUNDED PRECEDING
        ) AS span_no
    FROM marked
),
cut AS (
    SELECT wagon_id, span_no, min(time_utc) AS span_start_utc, max(time_utc) AS span_end_utc,
           sum(sample_rows) AS sample_rows
    FROM numbered
    GROUP BY wagon_id, span_no
),
span_files AS (
    SELECT c.wagon_id, c.span_start_utc, i.file_id, count(*) AS rows
    FROM cut AS c
    JOIN inside AS i
      ON i.wagon_id = c.wagon_id
     AND i.time_utc BETWEEN c.span_start_utc AND c.span_end_utc
    GROUP BY c.wagon_id, c.span_start_utc, i.file_id
),
files_key AS (
    SELECT
        sf.wagon_id, sf.span_start_utc,
        md5(string_agg(
            CAST(sf.file_id AS VARCHAR) || ':' || coalesce(f.sha256, '-') || ':'
                || CAST(sf.rows AS VARCHAR),
            ',' ORDER BY sf.file_id
        )) AS files_md5
    FROM span_files AS sf
    LEFT JOIN files AS f USING (file_id)
    GROUP BY sf.wagon_id, sf.span_start_utc
),
events_key AS (
    SELECT
        c.wagon_id, c.span_start_utc,
        md5(string_agg(
            e.event_id || '@' || CAST(e.start_utc AS VARCHAR) || '/'
                || CAST(e.end_utc AS VARCHAR) || '/' || CAST(e.complete AS VARCHAR),
            ',' ORDER BY e.event_id
        )) AS events_md5
    FROM cut AS c
    JOIN events AS e
      ON e.wagon_id = c.wagon_id
     AND e.start_utc BETWEEN c.span_start_utc AND c.span_end_utc
    GROUP BY c.wagon_id, c.span_start_utc
)
SELECT
    c.wagon_id,
    c.span_start_utc,
    c.span_end_utc,
    CAST(c.sample_rows AS BIGINT) AS sample_rows,
    concat_ws(
        '|', c.span_start_utc, c.span_end_utc, c.sample_rows, coalesce(fk.files_md5, '-'),
        coalesce(ek.events_md5, '-')
    ) AS data_key
FROM cut AS c
LEFT JOIN files_key AS fk USING (wagon_id, span_start_utc)
LEFT JOIN events_key AS ek USING (wagon_id, span_start_utc)
ORDER BY c.wagon_id, c.span_start_utc;
