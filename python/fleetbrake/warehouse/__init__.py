"""The DuckDB warehouse: connection, one-writer lock, schema and views (SQL files shipped in
:mod:`fleetbrake.warehouse.sql`)."""
