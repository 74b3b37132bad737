-- The model revisions that predicted some of one wagon's events, by name.
-- Parameters: $wagon_id.
SELECT DISTINCT model_revision
FROM predictions
WHERE wagon_id = $wagon_id
ORDER BY model_revision;
