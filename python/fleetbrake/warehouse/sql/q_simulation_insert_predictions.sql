-- Store the event windows of one wagon and revision. `prediction_batch` holds them, one row
-- per event and second (fleetbrake.simulation.predictions); the staging only recasts.
INSERT INTO predictions (
    event_id, wagon_id, time_utc, model_revision, phase, measured_sensor_c, predicted_sensor_c,
    predicted_contact_mean_c, predicted_contact_max_c, speed_kmh, brake_pressure_bar, ambient_c,
    flux_w_m2
)
WITH staged AS (
    SELECT
        CAST(event_id AS VARCHAR)                AS event_id,
        CAST(wagon_id AS VARCHAR)                AS wagon_id,
        CAST(time_utc AS TIMESTAMP)              AS time_utc,
        CAST(model_revision AS VARCHAR)          AS model_revision,
        CAST(phase AS VARCHAR)                   AS phase,
        CAST(measured_sensor_c AS DOUBLE)        AS measured_sensor_c,
        CAST(predicted_sensor_c AS DOUBLE)       AS predicted_sensor_c,
        CAST(predicted_contact_mean_c AS DOUBLE) AS predicted_contact_mean_c,
        CAST(predicted_contact_max_c AS DOUBLE)  AS predicted_contact_max_c,
        CAST(speed_kmh AS DOUBLE)                AS speed_kmh,
        CAST(brake_pressure_bar AS DOUBLE)       AS brake_pressure_bar,
        CAST(ambient_c AS DOUBLE)                AS ambient_c,
        CAST(flux_w_m2 AS DOUBLE)                AS flux_w_m2
    FROM prediction_batch
)
SELECT
    event_id, wagon_id, time_utc, model_revision, phase, measured_sensor_c, predicted_sensor_c,
    predicted_contact_mean_c, predicted_contact_max_c, speed_kmh, brake_pressure_bar, ambient_c,
    flux_w_m2
FROM staged;
