-- Several wagons' timelines as revision $revision simulated them (a chunk), as
-- q_flags_timeline.sql reads one wagon's, with wagon_id; the reader splits them by wagon and
-- sorts each by time_utc. Parameters: $wagon_ids (a list), $revision.
SELECT wagon_id, time_utc, predicted_sensor_c
FROM timeline
WHERE list_contains($wagon_ids, wagon_id) AND model_revision = $revision;
