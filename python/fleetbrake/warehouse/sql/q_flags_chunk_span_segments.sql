-- Several spans' timeline segments of revision $revision (a chunk), as
-- q_flags_span_segments.sql reads one span's, with part_ix (the span's 1-based position in
-- the lists): span i's are wagon $wagon_ids[i]'s whose span starts in
-- [$from_utc[i], $to_utc[i]]. The reader splits them by span and sorts each by start_utc.
-- Parameters: $wagon_ids, $from_utc, $to_utc (lists of the same length), $revision.
WITH ranges AS (
    SELECT
        unnest(CAST($wagon_ids AS VARCHAR[]))                      AS wagon_id,
        unnest(CAST($from_utc AS TIMESTAMP[]))                     AS from_utc,
        unnest(CAST($to_utc AS TIMESTAMP[]))                       AS to_utc,
        unnest(CAST(range(1, len($wagon_ids) + 1) AS INTEGER[]))   AS part_ix
)
SELECT r.part_ix AS part_ix, g.span_start_utc, g.span_end_utc, g.start_utc, g.stop_utc,
       g.kind, g.event_id, g.anchor, g.shift_k, g.reference_c
FROM timeline_segments AS g
JOIN ranges AS r
  ON g.wagon_id = r.wagon_id
 AND g.span_start_utc BETWEEN r.from_utc AND r.to_utc
WHERE g.model_revision = $revision
  AND list_contains(CAST($wagon_ids AS VARCHAR[]), g.wagon_id);
