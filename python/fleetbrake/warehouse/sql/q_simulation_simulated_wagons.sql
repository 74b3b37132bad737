-- The wagons simulated with revision $revision, and from what. Parameters: $revision.
SELECT wagon_id, data_key, model_key, events, simulated_utc
FROM simulated_wagons
WHERE model_revision = $revision
ORDER BY wagon_id;
