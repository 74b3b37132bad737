-- One span's timeline as revision $revision simulated it, by time: the column the flags judge
-- against (the contact temperatures, which the flags never read, left out).
-- Parameters: $wagon_id, $revision, $from_utc, $to_utc.
SELECT time_utc, predicted_sensor_c
FROM timeline
WHERE wagon_id = $wagon_id AND model_revision = $revision
  AND time_utc BETWEEN $from_utc AND $to_utc
ORDER BY time_utc;
