-- The braking events of one wagon, by activation. Parameters: $wagon_id.
SELECT event_id, start_utc, end_utc, complete
FROM events
WHERE wagon_id = $wagon_id
ORDER BY start_utc;
