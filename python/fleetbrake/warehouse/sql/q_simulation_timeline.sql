-- One wagon's timeline as revision $revision simulated it, by time.
-- Parameters: $wagon_id, $revision.
SELECT time_utc, predicted_sensor_c, predicted_contact_mean_c, predicted_contact_max_c
FROM timeline
WHERE wagon_id = $wagon_id AND model_revision = $revision
ORDER BY time_utc;
