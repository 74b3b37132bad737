-- v_file_rejections: every rejected row of a log file, as runs of consecutive lines rejected for
-- the same reason (line numbers in the file, the header being line 1; interface.md).
CREATE OR REPLACE VIEW v_file_rejections AS
WITH staged AS (
    SELECT
        CAST(f.path AS VARCHAR)       AS path,
        CAST(f.wagon_id AS VARCHAR)   AS wagon_id,
        CAST(r.first_line AS BIGINT)  AS first_line,
        CAST(r.last_line AS BIGINT)   AS last_line,
        CAST(r.rows AS BIGINT)        AS rows,
        CAST(r.reason AS VARCHAR)     AS reason
    FROM file_rejections AS r
    JOIN files AS f USING (file_id)
)
SELECT path, wagon_id, first_line, last_line, rows, reason
FROM staged;
