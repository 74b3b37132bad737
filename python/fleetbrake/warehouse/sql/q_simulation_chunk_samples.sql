-- The samples of several wagons at once (a chunk of partitions), as
-- q_simulation_wagon_samples.sql reads one wagon's, with file_id and, for the wagon, wagon_ix:
-- its 1-based position in $wagon_ids, not its name (4 bytes a row instead of the name's
-- string: the strings cost the writer about a third of reading a chunk, and their bytes
-- crossed to the worker, which cuts on the positions: fleetbrake.simulation.store.wagon_parts). In stored
-- order: the reader splits them by wagon and sorts each by time_utc, file_id
-- (fleetbrake.simulation.store.sample_parts). One query for a chunk reads each stored row
-- group once, where one query per wagon decompressed the row groups it shares with its
-- neighbours again for each. Parameters: $wagon_ids (a list).
SELECT
    CAST(list_position($wagon_ids, wagon_id) AS INTEGER) AS wagon_ix,
    CAST(file_id AS BIGINT)            AS file_id,
    CAST(time_utc AS TIMESTAMP)        AS time_utc,
    CAST(speed_kmh AS DOUBLE)          AS speed_kmh,
    CAST(brake_pressure_bar AS DOUBLE) AS brake_pressure_bar,
    CAST(block_temp_c AS DOUBLE)       AS block_temp_c,
    CAST(block_temp_fault AS BOOLEAN)  AS block_temp_fault,
    CAST(block_temp_raw_c AS DOUBLE)   AS block_temp_raw_c,
    CAST(ambient_temp_c AS DOUBLE)     AS ambient_temp_c
FROM samples
WHERE list_contains($wagon_ids, wagon_id);
