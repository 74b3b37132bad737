-- Which of the wagons whose events are detected again hold stored events: the others have
-- none to compare the new detection with (fleetbrake.ingest.events). Parameters: $wagon_ids
-- (a list).
WITH holding AS (
    SELECT DISTINCT wagon_id
    FROM events
    WHERE list_contains($wagon_ids, wagon_id)
)
SELECT wagon_id
FROM holding;
