-- Remove the rejected runs of lines of files whose path is being replaced, in the transaction
-- that stores what replaces them (fleetbrake.ingest.ledger). Parameters: $ids, the file_ids
-- replaced (a list).
DELETE FROM file_rejections
WHERE list_contains($ids, file_id);
