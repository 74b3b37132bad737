-- Every detected event (the closed loop re-simulates them all with a new revision).
WITH staged AS (
    SELECT
        CAST(event_id AS VARCHAR)    AS event_id,
        CAST(wagon_id AS VARCHAR)    AS wagon_id,
        CAST(start_utc AS TIMESTAMP) AS start_utc,
        CAST(end_utc AS TIMESTAMP)   AS end_utc
    FROM events
)
SELECT event_id, wagon_id, start_utc, end_utc
FROM staged
ORDER BY wagon_id, start_utc;
