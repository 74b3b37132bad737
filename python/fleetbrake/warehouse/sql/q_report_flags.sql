-- The fleet report (fleetbrake.app.report): every flag. No parameters.
SELECT *
FROM v_flags
ORDER BY wagon_id, start_utc;
