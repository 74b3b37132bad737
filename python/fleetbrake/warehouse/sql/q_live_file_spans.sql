-- The time range of the samples each of the given files holds (fleetbrake.viz.live: the new
-- timeline a unit of `watch` streams to a live viewer). Parameters: $paths (VARCHAR[], the
-- files' paths as v_files.path).
WITH wanted AS (
    SELECT file_id, path
    FROM files
    WHERE list_contains(CAST($paths AS VARCHAR[]), path)
      AND status = 'ingested'
),
spans AS (
    SELECT w.path, min(s.time_utc) AS from_utc, max(s.time_utc) AS to_utc
    FROM wanted AS w
    JOIN samples AS s ON s.file_id = w.file_id
    GROUP BY w.path
)
SELECT path, from_utc, to_utc
FROM spans
ORDER BY path;
