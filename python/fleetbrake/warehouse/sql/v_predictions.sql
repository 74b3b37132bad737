-- v_predictions: one row per event, per second, per model revision (interface.md).
CREATE OR REPLACE VIEW v_predictions AS
WITH staged AS (
    SELECT
        CAST(event_id AS VARCHAR)                 AS event_id,
        CAST(wagon_id AS VARCHAR)                 AS wagon_id,
        CAST(time_utc AS TIMESTAMP)               AS time_utc,
        CAST(model_revision AS VARCHAR)           AS model_revision,
        CAST(measured_sensor_c AS DOUBLE)         AS measured_sensor_c,
        CAST(predicted_sensor_c AS DOUBLE)        AS predicted_sensor_c,
        CAST(predicted_contact_mean_c AS DOUBLE)  AS predicted_contact_mean_c,
        CAST(predicted_contact_max_c AS DOUBLE)   AS predicted_contact_max_c
    FROM predictions
)
SELECT
    event_id, wagon_id, time_utc, model_revision, measured_sensor_c, predicted_sensor_c,
    predicted_contact_mean_c, predicted_contact_max_c
FROM staged;
