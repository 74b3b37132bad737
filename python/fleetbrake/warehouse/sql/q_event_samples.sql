-- The samples of one wagon in a time window, sorted, as the event detection reads a window
-- (fleetbrake.ingest.events reads several windows with one q_events_chunk_samples.sql and
-- sorts each so; tests/test_events.py compares each window's rows with this query's).
-- Parameters: $wagon_id, $from_utc, $to_utc.
WITH staged AS (
    SELECT
        CAST(time_utc AS TIMESTAMP)        AS time_utc,
        CAST(file_id AS BIGINT)            AS file_id,
        CAST(speed_kmh AS DOUBLE)          AS speed_kmh,
        CAST(distance_m AS DOUBLE)         AS distance_m,
        CAST(brake_pressure_bar AS DOUBLE) AS brake_pressure_bar,
        CAST(block_temp_c AS DOUBLE)       AS block_temp_c,
        CAST(block_temp_fault AS BOOLEAN)  AS block_temp_fault
    FROM samples
    WHERE wagon_id = $wagon_id
      AND time_utc BETWEEN $from_utc AND $to_utc
)
SELECT
    time_utc, file_id, speed_kmh, distance_m, brake_pressure_bar, block_temp_c, block_temp_fault
FROM staged
ORDER BY time_utc, file_id;
