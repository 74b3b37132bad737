-- One wagon's timeline as revision $revision simulated it, by time: the column the flags
-- judge against (q_simulation_timeline.sql has the contact temperatures too, which the flags
-- never read: a third of the rows' width, read and shipped to a worker for nothing).
-- Parameters: $wagon_id, $revision.
SELECT time_utc, predicted_sensor_c
FROM timeline
WHERE wagon_id = $wagon_id AND model_revision = $revision
ORDER BY time_utc;
