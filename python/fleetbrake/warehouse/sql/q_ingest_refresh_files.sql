-- The ledger takes the size and modification time a file has now when its bytes are the ones
-- recorded (copied or touched: same sha256), so that it is not read again at every run or
-- rescan. `refresh_batch` holds them (fleetbrake.ingest.files), in the files' transaction;
-- the staging only recasts.
UPDATE files
SET size_bytes = staged.size_bytes, mtime_ns = staged.mtime_ns
FROM (
    WITH staged AS (
        SELECT
            CAST(file_id AS BIGINT)    AS file_id,
            CAST(size_bytes AS BIGINT) AS size_bytes,
            CAST(mtime_ns AS BIGINT)   AS mtime_ns
        FROM refresh_batch
    )
    SELECT file_id, size_bytes, mtime_ns FROM staged
) AS staged
WHERE files.file_id = staged.file_id;
