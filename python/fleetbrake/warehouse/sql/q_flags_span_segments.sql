-- The segments of one span's timeline as revision $revision simulated it, by time.
-- Parameters: $wagon_id, $revision, $from_utc, $to_utc.
SELECT span_start_utc, span_end_utc, start_utc, stop_utc, kind, event_id, anchor, shift_k,
       reference_c
FROM timeline_segments
WHERE wagon_id = $wagon_id AND model_revision = $revision
  AND span_start_utc BETWEEN $from_utc AND $to_utc
ORDER BY start_utc;
