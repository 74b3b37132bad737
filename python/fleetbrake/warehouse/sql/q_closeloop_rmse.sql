-- RMSE of measured - predicted sensor temperature over every second with a valid
-- measurement of the events $event_ids, as revision $revision predicted them (the close-loop
-- report's figures, computed from v_predictions as an analyst would).
-- Parameters: $revision, $event_ids (a list of event ids).
WITH wanted AS (
    SELECT DISTINCT unnest(CAST($event_ids AS VARCHAR[])) AS event_id
),
residuals AS (
    SELECT p.measured_sensor_c - p.predicted_sensor_c AS residual_k
    FROM v_predictions AS p
    JOIN wanted AS w USING (event_id)
    WHERE p.model_revision = $revision
      AND p.measured_sensor_c IS NOT NULL
)
SELECT sqrt(avg(residual_k * residual_k)) AS rmse_k
FROM residuals;
