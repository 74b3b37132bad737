-- One wagon's registry entry as the last `run` stored it, and the fleet.toml it came from (the
-- block and sensor seat of an event's temperature field). Parameters: $wagon_id.
SELECT config_json, source
FROM wagon_registry
WHERE wagon_id = $wagon_id;
