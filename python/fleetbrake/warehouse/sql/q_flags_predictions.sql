-- One wagon's event windows as revision $revision predicted them, for the brakings' figures
-- (rises, contact maximum). Parameters: $wagon_id, $revision.
SELECT event_id, time_utc, phase, measured_sensor_c, predicted_sensor_c,
       predicted_contact_max_c, speed_kmh, brake_pressure_bar
FROM predictions
WHERE wagon_id = $wagon_id AND model_revision = $revision
ORDER BY event_id, time_utc;
