-- Forget what revision $revision stored in simulated_wagons for the wagons $wagon_ids (replaced next, in
-- the same transaction). Parameters: $wagon_ids (a list), $revision.
DELETE FROM simulated_wagons
WHERE model_revision = $revision AND list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id);
