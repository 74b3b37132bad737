-- The samples of several spans at once (a chunk of partitions of the simulation, the estimate
-- and the flags), as q_simulation_span_samples.sql reads one span's, with file_id and part_ix:
-- the span's 1-based position in the lists (4 bytes a row instead of the wagon's name: the
-- strings cost the writer about a third of reading a chunk, and their bytes crossed to the
-- worker, which cuts on the positions: fleetbrake.simulation.store.wagon_parts). Span i is
-- the samples of wagon $wagon_ids[i] in [$from_utc[i], $to_utc[i]]; only those are read. In
-- stored order: the reader splits them by span and sorts each by time_utc, file_id
-- (fleetbrake.simulation.store.sample_parts). One query for a chunk reads each stored row
-- group once, where one query per span decompressed the row groups it shares with its
-- neighbours again for each. Parameters: $wagon_ids, $from_utc, $to_utc (lists of the same
-- length).
WITH ranges AS (
    SELECT
        unnest(CAST($wagon_ids AS VARCHAR[]))                      AS wagon_id,
        unnest(CAST($from_utc AS TIMESTAMP[]))                     AS from_utc,
        unnest(CAST($to_utc AS TIMESTAMP[]))                       AS to_utc,
        unnest(CAST(range(1, len($wagon_ids) + 1) AS INTEGER[]))   AS part_ix
)
SELECT
    r.part_ix                            AS part_ix,
    CAST(s.file_id AS BIGINT)            AS file_id,
    CAST(s.time_utc AS TIMESTAMP)        AS time_utc,
    CAST(s.speed_kmh AS DOUBLE)          AS speed_kmh,
    CAST(s.brake_pressure_bar AS DOUBLE) AS brake_pressure_bar,
    CAST(s.block_temp_c AS DOUBLE)       AS block_temp_c,
    CAST(s.block_temp_fault AS BOOLEAN)  AS block_temp_fault,
    CAST(s.block_temp_raw_c AS DOUBLE)   AS block_temp_raw_c,
    CAST(s.ambient_temp_c AS DOUBLE)     AS ambient_temp_c
FROM samples AS s
JOIN ranges AS r
  ON s.wagon_id = r.wagon_id
 AND s.time_utc BETWEEN r.from_utc AND r.to_utc
WHERE list_contains(CAST($wagon_ids AS VARCHAR[]), s.wagon_id);
