-- Record what spans were simulated from (a batch of the stage, with their rows, in one
-- transaction). `simulated_batch` holds one row per span
-- (fleetbrake.simulation.store.replace_spans); the staging only recasts.
INSERT INTO simulated_spans (
    wagon_id, model_revision, span_start_utc, span_end_utc, data_key, model_key, events,
    simulated_utc
)
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)          AS wagon_id,
        CAST(model_revision AS VARCHAR)    AS model_revision,
        CAST(span_start_utc AS TIMESTAMP)  AS span_start_utc,
        CAST(span_end_utc AS TIMESTAMP)    AS span_end_utc,
        CAST(data_key AS VARCHAR)          AS data_key,
        CAST(model_key AS VARCHAR)         AS model_key,
        CAST(events AS BIGINT)             AS events,
        CAST(simulated_utc AS TIMESTAMP)   AS simulated_utc
    FROM simulated_batch
)
SELECT
    wagon_id, model_revision, span_start_utc, span_end_utc, data_key, model_key, events,
    simulated_utc
FROM staged;
