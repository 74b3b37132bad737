-- The samples of several time windows of wagons at once (a chunk of the event detection's
-- partitions), each window's rows as q_event_samples.sql reads one, with part_ix: the
-- window's 1-based position in the lists. Window i is the samples of wagon $wagon_ids[i] in
-- [$from_utc[i], $to_utc[i]]; a wagon's windows do not overlap. In stored order: the worker
-- splits them by window and sorts each by time_utc, file_id (fleetbrake.ingest.events), so
-- that the single writer neither sorts nor runs one query per wagon.
-- Parameters: $wagon_ids, $from_utc, $to_utc (lists of the same length).
WITH windows AS (
    SELECT
        unnest(CAST($wagon_ids AS VARCHAR[]))                        AS wagon_id,
        unnest(CAST($from_utc AS TIMESTAMP[]))                       AS from_utc,
        unnest(CAST($to_utc AS TIMESTAMP[]))                         AS to_utc,
        unnest(CAST(range(1, len($wagon_ids) + 1) AS INTEGER[]))     AS part_ix
),
staged AS (
    SELECT
        w.part_ix                            AS part_ix,
        CAST(s.time_utc AS TIMESTAMP)        AS time_utc,
        CAST(s.file_id AS BIGINT)            AS file_id,
        CAST(s.speed_kmh AS DOUBLE)          AS speed_kmh,
        CAST(s.distance_m AS DOUBLE)         AS distance_m,
        CAST(s.brake_pressure_bar AS DOUBLE) AS brake_pressure_bar,
        CAST(s.block_temp_c AS DOUBLE)       AS block_temp_c,
        CAST(s.block_temp_fault AS BOOLEAN)  AS block_temp_fault
    FROM samples AS s
    JOIN windows AS w
      ON s.wagon_id = w.wagon_id
     AND s.time_utc BETWEEN w.from_utc AND w.to_utc
    WHERE list_contains($wagon_ids, s.wagon_id)
)
SELECT
    part_ix, time_utc, file_id, speed_kmh, distance_m, brake_pressure_bar, block_temp_c,
    block_temp_fault
FROM staged;
