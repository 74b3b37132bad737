-- Record the time ranges whose events must be detected again: one row per file stored or
-- replaced. `dirty_batch` holds them (fleetbrake.ingest.files), written in the files'
-- transaction; the staging only recasts.
INSERT INTO event_dirty (wagon_id, from_utc, to_utc, file_id)
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)   AS wagon_id,
        CAST(from_utc AS TIMESTAMP) AS from_utc,
        CAST(to_utc AS TIMESTAMP)   AS to_utc,
        CAST(file_id AS BIGINT)     AS file_id
    FROM dirty_batch
)
SELECT wagon_id, from_utc, to_utc, file_id
FROM staged;
