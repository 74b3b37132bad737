-- Record what several spans were estimated from (a batch of the stage, with their rows of
-- contact_estimates, in one transaction). `estimated_batch` holds one row per span
-- (fleetbrake.simulation.estimates.spans.replace_span_estimates); the staging only recasts.
INSERT INTO estimated_spans (
    wagon_id, model_revision, span_start_utc, span_end_utc, data_key, model_key, seconds,
    measurement_k, power_w_per_sqrt_s, created_utc
)
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)             AS wagon_id,
        CAST(model_revision AS VARCHAR)       AS model_revision,
        CAST(span_start_utc AS TIMESTAMP)     AS span_start_utc,
        CAST(span_end_utc AS TIMESTAMP)       AS span_end_utc,
        CAST(data_key AS VARCHAR)             AS data_key,
        CAST(model_key AS VARCHAR)            AS model_key,
        CAST(seconds AS BIGINT)               AS seconds,
        CAST(measurement_k AS DOUBLE)         AS measurement_k,
        CAST(power_w_per_sqrt_s AS DOUBLE)    AS power_w_per_sqrt_s,
        CAST(created_utc AS TIMESTAMP)        AS created_utc
    FROM estimated_batch
)
SELECT
    wagon_id, model_revision, span_start_utc, span_end_utc, data_key, model_key, seconds,
    measurement_k, power_w_per_sqrt_s, created_utc
FROM staged;
