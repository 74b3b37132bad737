-- The files whose samples changed since the spans were last cut (fleetbrake.ingest.spans):
-- ingested files not yet seen, or seen with other bytes, rows or times, and seen files no
-- longer ingested (removed, replaced or quarantined). Their time ranges are cut again.
-- Reads the files table only, never the samples. No parameters.
WITH current AS (
    SELECT file_id, wagon_id, sha256, rows, first_utc, last_utc
    FROM files
    WHERE status = 'ingested' AND wagon_id IS NOT NULL AND rows > 0
),
seen AS (
    SELECT file_id, wagon_id, sha256, rows, first_utc, last_utc
    FROM spanned_files
),
added AS (
    SELECT c.file_id, c.wagon_id, c.first_utc, c.last_utc, 'added' AS change
    FROM current AS c
    LEFT JOIN seen AS s USING (file_id)
    WHERE s.file_id IS NULL
       OR (s.wagon_id, s.sha256, s.rows, s.first_utc, s.last_utc)
          IS DISTINCT FROM (c.wagon_id, c.sha256, c.rows, c.first_utc, c.last_utc)
),
removed AS (
    SELECT s.file_id, s.wagon_id, s.first_utc, s.last_utc, 'removed' AS change
    FROM seen AS s
    LEFT JOIN current AS c USING (file_id)
    WHERE c.file_id IS NULL
       OR (s.wagon_id, s.sha256, s.rows, s.first_utc, s.last_utc)
          IS DISTINCT FROM (c.wagon_id, c.sha256, c.rows, c.first_utc, c.last_utc)
),
changed AS (
    SELECT * FROM added
    UNION ALL
    SELECT * FROM removed
)
SELECT file_id, wagon_id, first_utc, last_utc, change
FROM changed
ORDER BY wagon_id, first_utc, file_id;
