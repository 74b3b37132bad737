-- Several wagons' timeline segments of revision $revision (a chunk), as
-- q_simulation_timeline_segments.sql reads one wagon's, with wagon_id; the reader splits them
-- by wagon and sorts each by start_utc. Parameters: $wagon_ids (a list), $revision.
SELECT wagon_id, span_start_utc, span_end_utc, start_utc, stop_utc, kind, event_id, anchor,
       shift_k, reference_c
FROM timeline_segments
WHERE list_contains($wagon_ids, wagon_id) AND model_revision = $revision;
