-- How many model revisions there are (the closed loop numbers the next one after them).
SELECT count(*) AS revisions
FROM model_revisions;
