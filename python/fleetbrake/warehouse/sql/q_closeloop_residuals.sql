-- Measured - predicted sensor temperature per second of revision $revision's predictions with a
-- valid measurement (the close-loop report's plots: only the columns they read).
-- Parameters: $revision.
WITH valid AS (
    SELECT wagon_id, model_revision, phase, measured_sensor_c, predicted_sensor_c
    FROM predictions
    WHERE model_revision = $revision
      AND measured_sensor_c IS NOT NULL
)
SELECT
    wagon_id, model_revision, phase,
    measured_sensor_c - predicted_sensor_c AS residual_k
FROM valid;
