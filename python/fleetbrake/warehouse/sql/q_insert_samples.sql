-- Store the samples of a batch of log files. `sample_batch` holds the parsed, repaired files
-- (fleetbrake.ingest), each row with its wagon_id and file_id; the staging only recasts.
INSERT INTO samples (
    wagon_id, file_id, time_utc, speed_kmh, distance_m, elevation_m, lat_deg, lon_deg,
    brake_pressure_bar, block_temp_c, block_temp_raw_c, block_temp_fault, ambient_temp_c
)
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)             AS wagon_id,
        CAST(file_id AS BIGINT)               AS file_id,
        CAST(time_utc AS TIMESTAMP)           AS time_utc,
        CAST(speed_kmh AS DOUBLE)             AS speed_kmh,
        CAST(distance_m AS DOUBLE)            AS distance_m,
        CAST(elevation_m AS DOUBLE)           AS elevation_m,
        CAST(lat_deg AS DOUBLE)               AS lat_deg,
        CAST(lon_deg AS DOUBLE)               AS lon_deg,
        CAST(brake_pressure_bar AS DOUBLE)    AS brake_pressure_bar,
        CAST(block_temp_c AS DOUBLE)          AS block_temp_c,
        CAST(block_temp_raw_c AS DOUBLE)      AS block_temp_raw_c,
        CAST(block_temp_fault AS BOOLEAN)     AS block_temp_fault,
        CAST(ambient_temp_c AS DOUBLE)        AS ambient_temp_c
    FROM sample_batch
)
SELECT
    wagon_id, file_id, time_utc, speed_kmh, distance_m, elevation_m, lat_deg, lon_deg,
    brake_pressure_bar, block_temp_c, block_temp_raw_c, block_temp_fault, ambient_temp_c
FROM staged;
