-- v_files: one row per log file seen (interface.md). rows_rejected: rows read but not stored,
-- each named in reason (and, one run of lines per row, in v_file_rejections).
CREATE OR REPLACE VIEW v_files AS
WITH staged AS (
    SELECT
        CAST(path AS VARCHAR)           AS path,
        CAST(wagon_id AS VARCHAR)       AS wagon_id,
        CAST(status AS VARCHAR)         AS status,
        CAST(rows AS BIGINT)            AS rows,
        CAST(rows_rejected AS BIGINT)   AS rows_rejected,
        CAST(reason AS VARCHAR)         AS reason,
        CAST(ingested_utc AS TIMESTAMP) AS ingested_utc
    FROM files
)
SELECT path, wagon_id, status, rows, rows_rejected, reason, ingested_utc
FROM staged;
