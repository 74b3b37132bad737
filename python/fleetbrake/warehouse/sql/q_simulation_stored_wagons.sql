-- The registry entries the last `run` stored, one per wagon.
SELECT wagon_id, config_json
FROM wagon_registry
ORDER BY wagon_id;
