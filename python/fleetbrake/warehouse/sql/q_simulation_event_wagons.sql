-- The wagons holding the events $event_ids (a list of event ids).
WITH wanted AS (
    SELECT DISTINCT unnest(CAST($event_ids AS VARCHAR[])) AS event_id
)
SELECT DISTINCT e.wagon_id
FROM events AS e
JOIN wanted AS w USING (event_id)
ORDER BY e.wagon_id;
