-- The wagons that hold rows of revision $revision in any table of the simulation stage
-- (those whose rows a new simulation must delete first; the others are only inserted).
-- Parameters: $revision.
WITH stored AS (
    SELECT wagon_id FROM simulated_wagons WHERE model_revision = $revision
    UNION
    SELECT DISTINCT wagon_id FROM predictions WHERE model_revision = $revision
    UNION
    SELECT DISTINCT wagon_id FROM timeline WHERE model_revision = $revision
    UNION
    SELECT DISTINCT wagon_id FROM timeline_segments WHERE model_revision = $revision
)
SELECT wagon_id
FROM stored
ORDER BY wagon_id;
