-- The wagons and activations of the events $event_ids (a list of event ids): the spans
-- holding them are simulated again when a caller forces them.
WITH wanted AS (
    SELECT DISTINCT unnest(CAST($event_ids AS VARCHAR[])) AS event_id
)
SELECT e.wagon_id, e.start_utc
FROM events AS e
JOIN wanted AS w USING (event_id)
ORDER BY e.wagon_id, e.start_utc;
