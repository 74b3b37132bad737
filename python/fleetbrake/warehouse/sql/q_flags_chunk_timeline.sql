-- Several wagons' timelines as revision $revision simulated them (a chunk), as
-- q_flags_timeline.sql reads one wagon's, with wagon_ix (the wagon's 1-based position in
-- $wagon_ids: q_simulation_chunk_samples.sql says why not its name); the reader splits them by
-- wagon and sorts each by time_utc. Parameters: $wagon_ids (a list), $revision.
SELECT CAST(list_position($wagon_ids, wagon_id) AS INTEGER) AS wagon_ix,
       time_utc, predicted_sensor_c
FROM timeline
WHERE list_contains($wagon_ids, wagon_id) AND model_revision = $revision;
