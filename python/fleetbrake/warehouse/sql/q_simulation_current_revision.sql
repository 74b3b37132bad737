-- The current model revision (the one `run` simulates new data with): the newest marked so.
WITH current_revisions AS (
    SELECT model_revision, created_utc
    FROM model_revisions
    WHERE is_current
)
SELECT model_revision
FROM current_revisions
ORDER BY created_utc DESC
LIMIT 1;
