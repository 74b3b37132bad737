-- Which of the given log files are queryable, as an analyst sees them: each one's row in
-- v_files (its status) and its wagon's flags in v_flags at that moment
-- (fleetbrake.bench.watch). $paths: the paths looked for (a list).
WITH landed AS (
    SELECT path, wagon_id, status
    FROM v_files
    WHERE list_contains($paths, path)
),
wagon_flags AS (
    SELECT wagon_id, count(*) AS n
    FROM v_flags
    WHERE wagon_id IN (SELECT wagon_id FROM landed)
    GROUP BY wagon_id
)
SELECT landed.path, landed.status, coalesce(wagon_flags.n, 0) AS flags
FROM landed
LEFT JOIN wagon_flags USING (wagon_id)
ORDER BY landed.path;
