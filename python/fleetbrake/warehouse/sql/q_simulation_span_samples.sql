-- The samples of one span of a wagon, by time, as the simulation, the estimate and the flags
-- read them (faulty readings are null in block_temp_c, their raw value in block_temp_raw_c).
-- Parameters: $wagon_id, $from_utc, $to_utc.
WITH staged AS (
    SELECT
        CAST(time_utc AS TIMESTAMP)        AS time_utc,
        CAST(file_id AS BIGINT)            AS file_id,
        CAST(speed_kmh AS DOUBLE)          AS speed_kmh,
        CAST(brake_pressure_bar AS DOUBLE) AS brake_pressure_bar,
        CAST(block_temp_c AS DOUBLE)       AS block_temp_c,
        CAST(block_temp_fault AS BOOLEAN)  AS block_temp_fault,
        CAST(block_temp_raw_c AS DOUBLE)   AS block_temp_raw_c,
        CAST(ambient_temp_c AS DOUBLE)     AS ambient_temp_c
    FROM samples
    WHERE wagon_id = $wagon_id AND time_utc BETWEEN $from_utc AND $to_utc
)
SELECT
    time_utc, speed_kmh, brake_pressure_bar, block_temp_c, block_temp_fault, block_temp_raw_c,
    ambient_temp_c
FROM staged
ORDER BY time_utc, file_id;
