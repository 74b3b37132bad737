-- Wagons' events are up to date: forget their dirty time ranges, in the transaction that
-- updated their events (fleetbrake.ingest.events). Parameters: $wagon_ids (a list).
DELETE FROM event_dirty
WHERE list_contains($wagon_ids, wagon_id);
