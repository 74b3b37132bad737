-- The fleet report (fleetbrake.app.report): per event and model revision, the peaks of the
-- measured and predicted sensor and of the predicted contact mean and maximum, the RMSE of
-- measured minus predicted sensor temperature (K) and the seconds with a valid reading.
-- No parameters.
WITH per_event AS (
    SELECT
        event_id,
        wagon_id,
        model_revision,
        min(time_utc)                                               AS first_utc,
        max(measured_sensor_c)                                      AS measured_max_c,
        max(predicted_sensor_c)                                     AS predicted_max_c,
        max(predicted_contact_mean_c)                               AS contact_mean_max_c,
        max(predicted_contact_max_c)                                AS contact_max_c,
        sqrt(avg(power(measured_sensor_c - predicted_sensor_c, 2))) AS rmse_k,
        count(measured_sensor_c)                                    AS valid_s
    FROM v_predictions
    GROUP BY event_id, wagon_id, model_revision
)
SELECT *
FROM per_event
ORDER BY wagon_id, first_utc, model_revision;
