-- The time ranges whose events must be detected again, per wagon, in time order
-- (fleetbrake.ingest.events). No parameters.
WITH dirty AS (
    SELECT wagon_id, from_utc, to_utc
    FROM event_dirty
)
SELECT wagon_id, from_utc, to_utc
FROM dirty
ORDER BY wagon_id, from_utc;
