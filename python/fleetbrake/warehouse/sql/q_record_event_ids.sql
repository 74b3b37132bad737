-- The ids of one wagon's events in time order (named when an event asked for is unknown).
-- Parameters: $wagon_id.
SELECT event_id
FROM events
WHERE wagon_id = $wagon_id
ORDER BY start_utc;
