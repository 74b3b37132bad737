-- One wagon's samples as a recording draws them, in time order: all of them (the timeline) or
-- those inside an event's window. Parameters: $wagon_id; $from_utc, $to_utc (NULL: unbounded).
WITH window_bounds AS (
    SELECT
        coalesce(CAST($from_utc AS TIMESTAMP), TIMESTAMP '-infinity') AS from_utc,
        coalesce(CAST($to_utc AS TIMESTAMP), TIMESTAMP 'infinity')    AS to_utc
),
wagon_samples AS (
    SELECT
        time_utc, speed_kmh, brake_pressure_bar, block_temp_c, block_temp_raw_c,
        block_temp_fault
    FROM samples
    WHERE wagon_id = $wagon_id
)
SELECT s.time_utc, s.speed_kmh, s.brake_pressure_bar, s.block_temp_c, s.block_temp_raw_c,
       s.block_temp_fault
FROM wagon_samples AS s, window_bounds AS w
WHERE s.time_utc BETWEEN w.from_utc AND w.to_utc
ORDER BY s.time_utc;
