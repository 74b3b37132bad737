-- How many braking events the warehouse holds (fleetbrake.ingest.events). No parameters.
SELECT count(*) AS events
FROM events;
