-- Forget the stored spans inside the ranges cut again (replaced next, in the same
-- transaction): range i is wagon $wagon_ids[i] in [$from_utc[i], $to_utc[i]].
-- Parameters: $wagon_ids, $from_utc, $to_utc (lists of the same length).
DELETE FROM spans AS s
WHERE EXISTS (
    SELECT 1
    FROM (
        SELECT
            unnest(CAST($wagon_ids AS VARCHAR[]))   AS wagon_id,
            unnest(CAST($from_utc AS TIMESTAMP[]))  AS from_utc,
            unnest(CAST($to_utc AS TIMESTAMP[]))    AS to_utc
    ) AS r
    WHERE r.wagon_id = s.wagon_id
      AND s.span_start_utc <= r.to_utc
      AND s.span_end_utc >= r.from_utc
);
