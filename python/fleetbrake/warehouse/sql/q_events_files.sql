-- The time ranges of the ingested files that hold samples of the wagons $wagon_ids (a list),
-- by wagon and in time order: the event detection joins each wagon's into chains
-- (fleetbrake.ingest.events). One query for every wagon whose events are detected again.
WITH ingested AS (
    SELECT wagon_id, file_id, first_utc, last_utc, rows
    FROM files
    WHERE list_contains($wagon_ids, wagon_id)
      AND status = 'ingested'
      AND rows > 0
)
SELECT wagon_id, first_utc, last_utc, rows
FROM ingested
ORDER BY wagon_id, first_utc, file_id;
