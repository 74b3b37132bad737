-- Several wagons' event windows as revision $revision predicted them (a chunk), as
-- q_flags_predictions.sql reads one wagon's, with wagon_id; the reader splits them by wagon
-- and sorts each by event_id, time_utc. Parameters: $wagon_ids (a list), $revision.
SELECT wagon_id, event_id, time_utc, phase, measured_sensor_c, predicted_sensor_c,
       predicted_contact_max_c, speed_kmh, brake_pressure_bar
FROM predictions
WHERE list_contains($wagon_ids, wagon_id) AND model_revision = $revision;
