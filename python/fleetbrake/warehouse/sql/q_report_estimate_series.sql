-- The fleet report (fleetbrake.app.report): one wagon's contact estimates of one model
-- revision in a time window, beside the open-loop prediction of the contact mean and the
-- measured sensor temperature (v_predictions, where it holds the second); resolution_s says
-- whether a row is a second's or a minute's (outside the estimate windows).
-- Parameters: $wagon_id, $model_revision, $from_utc, $to_utc.
WITH estimates AS (
    SELECT
        time_utc, resolution_s, contact_mean_c, contact_mean_lo_c, contact_mean_hi_c,
        unexplained_power_w, unexplained_power_lo_w, unexplained_power_hi_w
    FROM v_contact_estimates
    WHERE wagon_id = $wagon_id
      AND model_revision = $model_revision
      AND time_utc BETWEEN CAST($from_utc AS TIMESTAMP) AND CAST($to_utc AS TIMESTAMP)
),
open_loop AS (
    SELECT
        time_utc,
        max(predicted_contact_mean_c) AS predicted_contact_mean_c,
        max(measured_sensor_c)        AS measured_sensor_c
    FROM v_predictions
    WHERE wagon_id = $wagon_id
      AND model_revision = $model_revision
      AND time_utc BETWEEN CAST($from_utc AS TIMESTAMP) AND CAST($to_utc AS TIMESTAMP)
    GROUP BY time_utc
)
SELECT e.*, o.predicted_contact_mean_c, o.measured_sensor_c
FROM estimates AS e
LEFT JOIN open_loop AS o USING (time_utc)
ORDER BY e.time_utc;
