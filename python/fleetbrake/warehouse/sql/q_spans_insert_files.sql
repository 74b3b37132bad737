-- Record the ingested files $file_ids (a list) as the spans were cut from them.
WITH current AS (
    SELECT file_id, wagon_id, sha256, rows, first_utc, last_utc
    FROM files
    WHERE list_contains(CAST($file_ids AS BIGINT[]), file_id)
      AND status = 'ingested' AND wagon_id IS NOT NULL AND rows > 0
)
INSERT INTO spanned_files (file_id, wagon_id, sha256, rows, first_utc, last_utc)
SELECT file_id, wagon_id, sha256, rows, first_utc, last_utc
FROM current;
