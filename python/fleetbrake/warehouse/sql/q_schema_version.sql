-- The newest schema version a fleetbrake has applied to this database (null when new)
-- (fleetbrake.warehouse.connection). No parameters.
SELECT max(version) AS version
FROM schema_version;
