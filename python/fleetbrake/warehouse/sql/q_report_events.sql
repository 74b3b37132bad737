-- The fleet report (fleetbrake.app.report): every braking event. No parameters.
SELECT *
FROM v_events
ORDER BY wagon_id, start_utc;
