-- How many model revisions the warehouse holds (none yet: the declared model is recorded).
SELECT count(*) AS revisions
FROM model_revisions;
