-- What the warehouse already holds about each log file path, so that the ingestion reads only
-- new or changed files (fleetbrake.ingest.files). No parameters.
WITH recorded AS (
    SELECT
        path, file_id, sha256, size_bytes, mtime_ns, status, quarantine_code, reason,
        wagon_id, first_utc, last_utc
    FROM files
)
SELECT
    path, file_id, sha256, size_bytes, mtime_ns, status, quarantine_code, reason,
    wagon_id, first_utc, last_utc
FROM recorded;
