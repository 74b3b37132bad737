-- Forget what revision $revision stored in timeline for wagon $wagon_id (replaced next, in the
-- same transaction). Parameters: $wagon_id, $revision.
DELETE FROM timeline
WHERE wagon_id = $wagon_id AND model_revision = $revision;
