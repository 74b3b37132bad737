-- What the warehouse holds about one log file, and its wagon's flags by kind: the outcome
-- line of a file that `fleetbrake watch` took again (fleetbrake.app.watch.service). $path.
WITH stored AS (
    SELECT path, wagon_id, status, rows, reason
    FROM v_files
    WHERE path = $path
),
wagon_flags AS (
    SELECT kind, count(*) AS n
    FROM v_flags
    WHERE wagon_id = (SELECT wagon_id FROM stored)
    GROUP BY kind
)
SELECT
    stored.wagon_id,
    stored.status,
    stored.rows,
    stored.reason,
    (SELECT coalesce(list(struct_pack(kind := kind, n := n) ORDER BY kind), []) FROM wagon_flags)
        AS flags
FROM stored;
