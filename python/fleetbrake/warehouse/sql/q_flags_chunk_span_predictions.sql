-- Several spans' event windows as revision $revision predicted them (a chunk), as
-- q_flags_span_predictions.sql reads one span's, with part_ix (the span's 1-based position in
-- the lists): span i is wagon $wagon_ids[i] in [$from_utc[i], $to_utc[i]] (an event window
-- ends at a data gap, so inside its span). The reader splits them by span and sorts each by
-- event_id, time_utc. Parameters: $wagon_ids, $from_utc, $to_utc (lists of the same
-- length), $revision.
WITH ranges AS (
    SELECT
        unnest(CAST($wagon_ids AS VARCHAR[]))                      AS wagon_id,
        unnest(CAST($from_utc AS TIMESTAMP[]))                     AS from_utc,
        unnest(CAST($to_utc AS TIMESTAMP[]))                       AS to_utc,
        unnest(CAST(range(1, len($wagon_ids) + 1) AS INTEGER[]))   AS part_ix
)
SELECT r.part_ix AS part_ix, p.event_id, p.time_utc, p.phase, p.measured_sensor_c,
       p.predicted_sensor_c, p.predicted_contact_max_c, p.speed_kmh, p.brake_pressure_bar
FROM predictions AS p
JOIN ranges AS r
  ON p.wagon_id = r.wagon_id
 AND p.time_utc BETWEEN r.from_utc AND r.to_utc
WHERE p.model_revision = $revision
  AND list_contains(CAST($wagon_ids AS VARCHAR[]), p.wagon_id);
