-- Forget what revision $revision stored in simulated_wagons for wagon $wagon_id (replaced next, in the
-- same transaction). Parameters: $wagon_id, $revision.
DELETE FROM simulated_wagons
WHERE wagon_id = $wagon_id AND model_revision = $revision;
