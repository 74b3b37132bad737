-- One wagon's contact estimates of revision $revision, by time, every stored column.
-- Parameters: $wagon_id, $revision.
SELECT *
FROM contact_estimates
WHERE wagon_id = $wagon_id AND model_revision = $revision
ORDER BY time_utc;
