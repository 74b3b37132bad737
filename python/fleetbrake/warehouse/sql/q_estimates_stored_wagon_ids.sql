-- The wagons that hold rows of revision $revision in a table of the estimation stage (those
-- whose rows a new estimation must delete first; the others are only inserted).
-- Parameters: $revision.
WITH stored AS (
    SELECT wagon_id FROM estimated_wagons WHERE model_revision = $revision
    UNION
    SELECT DISTINCT wagon_id FROM contact_estimates WHERE model_revision = $revision
)
SELECT wagon_id
FROM stored
ORDER BY wagon_id;
