-- Remove the files rows of paths being replaced, after their samples (q_ingest_delete_samples),
-- in the transaction that stores what replaces them (fleetbrake.ingest.files).
-- Parameters: $ids, the file_ids replaced (a list).
DELETE FROM files
WHERE list_contains($ids, file_id);
