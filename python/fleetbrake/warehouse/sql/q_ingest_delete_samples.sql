-- Remove the samples of files whose path is being replaced (other bytes, or a quarantine
-- judged again), in the transaction that stores what replaces them (fleetbrake.ingest.files).
-- Parameters: $ids, the file_ids replaced (a list).
DELETE FROM samples
WHERE list_contains($ids, file_id);
