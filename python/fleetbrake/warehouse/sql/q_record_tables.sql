-- The tables and views of the database (fleetbrake.viz.data): a database written by an older
-- `run`, or by `ingest` alone, lacks some of the tables (and views) a recording reads.
WITH relations AS (
    SELECT table_name AS name FROM duckdb_tables()
    UNION
    SELECT view_name AS name FROM duckdb_views() WHERE NOT internal
)
SELECT name
FROM relations
ORDER BY name;
