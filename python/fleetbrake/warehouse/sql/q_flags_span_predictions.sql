-- One span's event windows as revision $revision predicted them, for the brakings' figures
-- (rises, contact maximum). Parameters: $wagon_id, $revision, $from_utc, $to_utc.
SELECT event_id, time_utc, phase, measured_sensor_c, predicted_sensor_c,
       predicted_contact_max_c, speed_kmh, brake_pressure_bar
FROM predictions
WHERE wagon_id = $wagon_id AND model_revision = $revision
  AND time_utc BETWEEN $from_utc AND $to_utc
ORDER BY event_id, time_utc;
