-- The braking events of several wagons (a chunk), as q_simulation_wagon_events.sql reads one
-- wagon's, with wagon_id; the reader splits them by wagon and sorts each by start_utc.
-- Parameters: $wagon_ids (a list).
SELECT wagon_id, event_id, start_utc, end_utc, complete
FROM events
WHERE list_contains($wagon_ids, wagon_id);
