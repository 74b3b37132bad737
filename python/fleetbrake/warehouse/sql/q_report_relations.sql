-- The fleet report (fleetbrake.app.report): the views of the database (a database written by
-- an older `run` lacks v_contact_estimates). No parameters.
SELECT view_name
FROM duckdb_views()
WHERE NOT internal
ORDER BY view_name;
