-- Record that this fleetbrake's schema version was applied (fleetbrake.warehouse.connection).
-- Parameters: $version, $now (UTC).
INSERT INTO schema_version (version, applied_utc)
VALUES ($version, $now);
