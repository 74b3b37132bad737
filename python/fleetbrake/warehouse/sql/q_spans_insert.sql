-- Store spans cut again: `span_batch` holds them (fleetbrake.ingest.spans); the staging
-- only recasts.
INSERT INTO spans (wagon_id, span_start_utc, span_end_utc, sample_rows, data_key)
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)          AS wagon_id,
        CAST(span_start_utc AS TIMESTAMP)  AS span_start_utc,
        CAST(span_end_utc AS TIMESTAMP)    AS span_end_utc,
        CAST(sample_rows AS BIGINT)        AS sample_rows,
        CAST(data_key AS VARCHAR)          AS data_key
    FROM span_batch
)
SELECT wagon_id, span_start_utc, span_end_utc, sample_rows, data_key
FROM staged;
