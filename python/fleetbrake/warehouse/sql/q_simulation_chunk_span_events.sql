-- The braking events of several spans (a chunk), as q_simulation_span_events.sql reads one
-- span's, with part_ix (the span's 1-based position in the lists): span i holds the events of
-- wagon $wagon_ids[i] whose activation is in [$from_utc[i], $to_utc[i]]. The reader splits
-- them by span and sorts each by start_utc.
-- Parameters: $wagon_ids, $from_utc, $to_utc (lists of the same length).
WITH ranges AS (
    SELECT
        unnest(CAST($wagon_ids AS VARCHAR[]))                      AS wagon_id,
        unnest(CAST($from_utc AS TIMESTAMP[]))                     AS from_utc,
        unnest(CAST($to_utc AS TIMESTAMP[]))                       AS to_utc,
        unnest(CAST(range(1, len($wagon_ids) + 1) AS INTEGER[]))   AS part_ix
)
SELECT r.part_ix AS part_ix, e.event_id, e.start_utc, e.end_utc, e.complete
FROM events AS e
JOIN ranges AS r
  ON e.wagon_id = r.wagon_id
 AND e.start_utc BETWEEN r.from_utc AND r.to_utc;
