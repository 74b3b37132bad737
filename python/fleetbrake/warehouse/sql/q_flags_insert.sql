-- Store flags. `flag_batch` holds them (fleetbrake.flags.judge), one row each; the staging
-- only recasts.
INSERT INTO flags (
    flag_id, wagon_id, event_id, kind, severity, start_utc, end_utc, evidence, detected_utc
)
WITH staged AS (
    SELECT
        CAST(flag_id AS VARCHAR)        AS flag_id,
        CAST(wagon_id AS VARCHAR)       AS wagon_id,
        CAST(event_id AS VARCHAR)       AS event_id,
        CAST(kind AS VARCHAR)           AS kind,
        CAST(severity AS VARCHAR)       AS severity,
        CAST(start_utc AS TIMESTAMP)    AS start_utc,
        CAST(end_utc AS TIMESTAMP)      AS end_utc,
        CAST(evidence AS VARCHAR)       AS evidence,
        CAST(detected_utc AS TIMESTAMP) AS detected_utc
    FROM flag_batch
)
SELECT flag_id, wagon_id, event_id, kind, severity, start_utc, end_utc, evidence, detected_utc
FROM staged;
