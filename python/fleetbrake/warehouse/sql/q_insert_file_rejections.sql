-- Record the rejected runs of lines of a batch of log files. `rejection_batch` holds one row per
-- run (fleetbrake.ingest.ledger); the staging only recasts.
INSERT INTO file_rejections (file_id, first_line, last_line, rows, reason)
WITH staged AS (
    SELECT
        CAST(file_id AS BIGINT)     AS file_id,
        CAST(first_line AS BIGINT)  AS first_line,
        CAST(last_line AS BIGINT)   AS last_line,
        CAST(rows AS BIGINT)        AS rows,
        CAST(reason AS VARCHAR)     AS reason
    FROM rejection_batch
)
SELECT file_id, first_line, last_line, rows, reason
FROM staged
ORDER BY file_id, first_line;
