-- The stored spans of the wagons $wagon_ids (a list), by wagon and start.
WITH stored AS (
    SELECT wagon_id, span_start_utc, span_end_utc, sample_rows, data_key
    FROM spans
    WHERE list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id)
)
SELECT wagon_id, span_start_utc, span_end_utc, sample_rows, data_key
FROM stored
ORDER BY wagon_id, span_start_utc;
