-- Record that spans were judged (after their flags are stored, in the same transaction).
-- `flagged_batch` holds one row per span (fleetbrake.flags.storage.store_flags); the staging
-- only recasts.
INSERT INTO flagged_spans (
    wagon_id, model_revision, span_start_utc, span_end_utc, data_key, config_key, flag_count,
    updated_utc
)
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)          AS wagon_id,
        CAST(model_revision AS VARCHAR)    AS model_revision,
        CAST(span_start_utc AS TIMESTAMP)  AS span_start_utc,
        CAST(span_end_utc AS TIMESTAMP)    AS span_end_utc,
        CAST(data_key AS VARCHAR)          AS data_key,
        CAST(config_key AS VARCHAR)        AS config_key,
        CAST(flag_count AS BIGINT)         AS flag_count,
        CAST(updated_utc AS TIMESTAMP)     AS updated_utc
    FROM flagged_batch
)
SELECT
    wagon_id, model_revision, span_start_utc, span_end_utc, data_key, config_key, flag_count,
    updated_utc
FROM staged;
