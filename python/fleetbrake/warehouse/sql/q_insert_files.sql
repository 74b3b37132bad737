-- Record log files seen (ingested or quarantined). `file_batch` holds one row per file
-- (fleetbrake.ingest); the staging only recasts.
INSERT INTO files (
    file_id, path, wagon_id, sha256, size_bytes, mtime_ns, status, quarantine_code, reason,
    rows, rows_in_file, rows_no_time, rows_outside_session, rows_duplicate, rows_out_of_order,
    cells_unparsable, block_temp_faults, partial_row_dropped, repairs, first_utc, last_utc,
    ingested_utc, rows_rejected
)
WITH staged AS (
    SELECT
        CAST(file_id AS BIGINT)                AS file_id,
        CAST(path AS VARCHAR)                  AS path,
        CAST(wagon_id AS VARCHAR)              AS wagon_id,
        CAST(sha256 AS VARCHAR)                AS sha256,
        CAST(size_bytes AS BIGINT)             AS size_bytes,
        CAST(mtime_ns AS BIGINT)               AS mtime_ns,
        CAST(status AS VARCHAR)                AS status,
        CAST(quarantine_code AS VARCHAR)       AS quarantine_code,
        CAST(reason AS VARCHAR)                AS reason,
        CAST(rows AS BIGINT)                   AS rows,
        CAST(rows_in_file AS BIGINT)           AS rows_in_file,
        CAST(rows_no_time AS BIGINT)           AS rows_no_time,
        CAST(rows_outside_session AS BIGINT)   AS rows_outside_session,
        CAST(rows_duplicate AS BIGINT)         AS rows_duplicate,
        CAST(rows_out_of_order AS BIGINT)      AS rows_out_of_order,
        CAST(cells_unparsable AS BIGINT)       AS cells_unparsable,
        CAST(block_temp_faults AS BIGINT)      AS block_temp_faults,
        CAST(partial_row_dropped AS BOOLEAN)   AS partial_row_dropped,
        CAST(repairs AS VARCHAR)               AS repairs,
        CAST(first_utc AS TIMESTAMP)           AS first_utc,
        CAST(last_utc AS TIMESTAMP)            AS last_utc,
        CAST(ingested_utc AS TIMESTAMP)        AS ingested_utc,
        CAST(rows_rejected AS BIGINT)          AS rows_rejected
    FROM file_batch
)
SELECT
    file_id, path, wagon_id, sha256, size_bytes, mtime_ns, status, quarantine_code, reason,
    rows, rows_in_file, rows_no_time, rows_outside_session, rows_duplicate, rows_out_of_order,
    cells_unparsable, block_temp_faults, partial_row_dropped, repairs, first_utc, last_utc,
    ingested_utc, rows_rejected
FROM staged
ORDER BY file_id;
