-- The spans of one wagon's samples that overlap a time range, as the estimator runs through
-- them (a span ends where two samples are more than $gap_s apart: ChainParams.bridge_max_s),
-- for a recording to recompute per-second estimates where the stored rows are per minute.
-- Parameters: $wagon_id, $gap_s; $from_utc, $to_utc (NULL: unbounded).
WITH window_bounds AS (
    SELECT
        coalesce(CAST($from_utc AS TIMESTAMP), TIMESTAMP '-infinity') AS from_utc,
        coalesce(CAST($to_utc AS TIMESTAMP), TIMESTAMP 'infinity')    AS to_utc
),
wagon_samples AS (
    SELECT time_utc, lag(time_utc) OVER (ORDER BY time_utc) AS previous_utc
    FROM samples
    WHERE wagon_id = $wagon_id
),
numbered AS (
    SELECT
        time_utc,
        sum(CASE
                WHEN previous_utc IS NULL
                  OR time_utc - previous_utc > to_seconds(CAST($gap_s AS DOUBLE)) THEN 1
                ELSE 0
            END) OVER (ORDER BY time_utc) AS span
    FROM wagon_samples
),
spans AS (
    SELECT min(time_utc) AS start_utc, max(time_utc) AS end_utc
    FROM numbered
    GROUP BY span
)
SELECT s.start_utc, s.end_utc
FROM spans AS s, window_bounds AS w
WHERE s.end_utc >= w.from_utc AND s.start_utc <= w.to_utc
ORDER BY s.start_utc;
