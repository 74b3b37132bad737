-- v_flags: one row per anomaly raised (interface.md).
CREATE OR REPLACE VIEW v_flags AS
WITH staged AS (
    SELECT
        CAST(flag_id AS VARCHAR)     AS flag_id,
        CAST(wagon_id AS VARCHAR)    AS wagon_id,
        CAST(event_id AS VARCHAR)    AS event_id,
        CAST(kind AS VARCHAR)        AS kind,
        CAST(severity AS VARCHAR)    AS severity,
        CAST(start_utc AS TIMESTAMP) AS start_utc,
        CAST(end_utc AS TIMESTAMP)   AS end_utc,
        CAST(evidence AS VARCHAR)    AS evidence
    FROM flags
)
SELECT flag_id, wagon_id, event_id, kind, severity, start_utc, end_utc, evidence
FROM staged;
