-- The time ranges of one wagon's ingested files that hold samples, in time order: the event
-- detection joins them into chains (fleetbrake.ingest.events). Parameters: $wagon_id.
WITH ingested AS (
    SELECT file_id, first_utc, last_utc, rows
    FROM files
    WHERE wagon_id = $wagon_id
      AND status = 'ingested'
      AND rows > 0
)
SELECT first_utc, last_utc, rows
FROM ingested
ORDER BY first_utc, file_id;
