-- Forget what revision $revision stored in predictions for the wagons $wagon_ids (replaced next, in
-- the same transaction). Parameters: $wagon_ids (a list), $revision.
DELETE FROM predictions
WHERE model_revision = $revision AND list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id);
