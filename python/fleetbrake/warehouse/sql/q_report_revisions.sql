-- The fleet report (fleetbrake.app.report): the model revisions, oldest first (the last is
-- the current one). No parameters.
SELECT *
FROM v_model_revisions
ORDER BY created_utc;
