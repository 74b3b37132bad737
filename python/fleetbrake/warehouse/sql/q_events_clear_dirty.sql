-- A wagon's events are up to date: forget its dirty time ranges, in the transaction that
-- updated its events (fleetbrake.ingest.events). Parameters: $wagon_id.
DELETE FROM event_dirty
WHERE wagon_id = $wagon_id;
