-- Store the registry entries `run` used. `registry_batch` holds one row per wagon.
INSERT INTO wagon_registry (wagon_id, config_json, source, updated_utc)
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)      AS wagon_id,
        CAST(config_json AS VARCHAR)   AS config_json,
        CAST(source AS VARCHAR)        AS source,
        CAST(updated_utc AS TIMESTAMP) AS updated_utc
    FROM registry_batch
)
SELECT wagon_id, config_json, source, updated_utc
FROM staged;
