-- The revisions and wagons holding per-second contact estimates, to compact
-- (fleetbrake.warehouse.migration). No parameters.
SELECT DISTINCT model_revision, wagon_id
FROM contact_estimates
WHERE resolution_s = 1
ORDER BY model_revision, wagon_id;
