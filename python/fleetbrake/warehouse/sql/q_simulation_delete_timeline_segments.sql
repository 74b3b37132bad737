-- Forget what revision $revision stored in timeline_segments for wagon $wagon_id (replaced next, in the
-- same transaction). Parameters: $wagon_id, $revision.
DELETE FROM timeline_segments
WHERE wagon_id = $wagon_id AND model_revision = $revision;
