-- Forget what revision $revision stored in timeline_segments for the wagons $wagon_ids (replaced next, in
-- the same transaction). Parameters: $wagon_ids (a list), $revision.
DELETE FROM timeline_segments
WHERE model_revision = $revision AND list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id);
