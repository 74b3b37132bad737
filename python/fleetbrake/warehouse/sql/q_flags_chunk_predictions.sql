-- Several wagons' event windows as revision $revision predicted them (a chunk), as
-- q_flags_predictions.sql reads one wagon's, with wagon_ix (the wagon's 1-based position in
-- $wagon_ids: q_simulation_chunk_samples.sql says why not its name); the reader splits them by
-- wagon and sorts each by event_id, time_utc. Parameters: $wagon_ids (a list), $revision.
SELECT CAST(list_position($wagon_ids, wagon_id) AS INTEGER) AS wagon_ix,
       event_id, time_utc, phase, measured_sensor_c, predicted_sensor_c,
       predicted_contact_max_c, speed_kmh, brake_pressure_bar
FROM predictions
WHERE list_contains($wagon_ids, wagon_id) AND model_revision = $revision;
