-- Forget what revision $revision stored in timeline for the wagons $wagon_ids (replaced next, in
-- the same transaction). Parameters: $wagon_ids (a list), $revision.
DELETE FROM timeline
WHERE model_revision = $revision AND list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id);
