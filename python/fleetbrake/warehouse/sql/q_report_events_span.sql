-- The fleet report (fleetbrake.app.report): from the first event's start to the last event's
-- end (nulls without events). No parameters.
SELECT min(start_utc) AS first_utc, max(end_utc) AS last_utc
FROM v_events;
