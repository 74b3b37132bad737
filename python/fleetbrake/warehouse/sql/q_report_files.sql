-- The fleet report (fleetbrake.app.report): every log file seen. No parameters.
SELECT *
FROM v_files
ORDER BY path;
