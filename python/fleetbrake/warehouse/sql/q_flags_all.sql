-- Every stored flag, in a stable order (the fleet's flags after a whole `run`: those it judged
-- and those that stood).
WITH stored AS (
    SELECT flag_id, wagon_id, event_id, kind, severity, start_utc, end_utc, evidence
    FROM flags
)
SELECT *
FROM stored
ORDER BY wagon_id, start_utc, kind, flag_id;
