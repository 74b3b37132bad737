-- Forget what the wagons $wagon_ids were estimated from with revision $revision (recorded
-- again next, in the same transaction). Parameters: $wagon_ids (a list), $revision.
DELETE FROM estimated_wagons
WHERE model_revision = $revision AND list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id);
