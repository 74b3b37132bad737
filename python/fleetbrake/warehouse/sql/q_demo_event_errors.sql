-- The error of every event under the current model revision (the newest one): the RMSE of
-- measured minus predicted sensor temperature over the seconds with a valid reading, for the
-- demo's choice of the event worth a recording (fleetbrake.app.demo.pick_event).
-- No parameters.
WITH current_revision AS (
    SELECT model_revision
    FROM v_model_revisions
    ORDER BY created_utc DESC
    LIMIT 1
),
valid_seconds AS (
    SELECT p.event_id, p.wagon_id, p.model_revision, p.measured_sensor_c, p.predicted_sensor_c
    FROM v_predictions AS p
    JOIN current_revision AS r ON r.model_revision = p.model_revision
    WHERE p.measured_sensor_c IS NOT NULL
)
SELECT
    event_id,
    wagon_id,
    model_revision,
    sqrt(avg(power(measured_sensor_c - predicted_sensor_c, 2))) AS rmse_k
FROM valid_seconds
GROUP BY event_id, wagon_id, model_revision;
