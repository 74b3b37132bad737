-- Several spans' timelines as revision $revision simulated them (a chunk), as
-- q_flags_span_timeline.sql reads one span's, with part_ix (the span's 1-based position in
-- the lists: q_simulation_chunk_span_samples.sql says why not the wagon's name): span i is
-- wagon $wagon_ids[i] in [$from_utc[i], $to_utc[i]]. The reader splits them by span and
-- sorts each by time_utc. Parameters: $wagon_ids, $from_utc, $to_utc (lists of the same
-- length), $revision.
WITH ranges AS (
    SELECT
        unnest(CAST($wagon_ids AS VARCHAR[]))                      AS wagon_id,
        unnest(CAST($from_utc AS TIMESTAMP[]))                     AS from_utc,
        unnest(CAST($to_utc AS TIMESTAMP[]))                       AS to_utc,
        unnest(CAST(range(1, len($wagon_ids) + 1) AS INTEGER[]))   AS part_ix
)
SELECT r.part_ix AS part_ix, t.time_utc, t.predicted_sensor_c
FROM timeline AS t
JOIN ranges AS r
  ON t.wagon_id = r.wagon_id
 AND t.time_utc BETWEEN r.from_utc AND r.to_utc
WHERE t.model_revision = $revision
  AND list_contains(CAST($wagon_ids AS VARCHAR[]), t.wagon_id);
