-- Store the timeline of one wagon and revision. `timeline_batch` holds one row per logged
-- second (fleetbrake.simulation.predictions); the staging only recasts.
INSERT INTO timeline (
    wagon_id, model_revision, time_utc, predicted_sensor_c, predicted_contact_mean_c,
    predicted_contact_max_c
)
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)                AS wagon_id,
        CAST(model_revision AS VARCHAR)          AS model_revision,
        CAST(time_utc AS TIMESTAMP)              AS time_utc,
        CAST(predicted_sensor_c AS DOUBLE)       AS predicted_sensor_c,
        CAST(predicted_contact_mean_c AS DOUBLE) AS predicted_contact_mean_c,
        CAST(predicted_contact_max_c AS DOUBLE)  AS predicted_contact_max_c
    FROM timeline_batch
)
SELECT
    wagon_id, model_revision, time_utc, predicted_sensor_c, predicted_contact_mean_c,
    predicted_contact_max_c
FROM staged;
