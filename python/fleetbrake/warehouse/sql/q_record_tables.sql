-- The tables of the database (fleetbrake.viz.data): a database written by an older `run`, or
-- by `ingest` alone, lacks some of the tables a recording reads.
SELECT table_name
FROM duckdb_tables()
ORDER BY table_name;
