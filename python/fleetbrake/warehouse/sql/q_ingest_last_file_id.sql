-- The highest file_id given so far (0 in an empty warehouse): the ingestion numbers new files
-- on from it (fleetbrake.ingest.files). No parameters.
WITH recorded AS (
    SELECT file_id FROM files
)
SELECT coalesce(max(file_id), 0) AS last_file_id
FROM recorded;
