-- Remove events that changed or vanished, in the transaction that stores their replacements
-- (fleetbrake.ingest.events). Parameters: $ids, the event_ids (a list).
DELETE FROM events
WHERE list_contains($ids, event_id);
