-- The last predicted second of one event by one model revision (NULL when it has none): an
-- event's recording runs until then. Parameters: $event_id, $model_revision.
SELECT max(time_utc) AS last_utc
FROM predictions
WHERE event_id = $event_id
  AND model_revision = $model_revision;
