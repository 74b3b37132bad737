"""The warehouse's packaged SQL (:mod:`fleetbrake.warehouse.sql`, read with
``importlib.resources`` so an installed wheel has it) and the warehouse's error.
:mod:`fleetbrake.warehouse.connection` re-exports both; the modules the connection itself
runs (the schema migration, :mod:`fleetbrake.warehouse.estimate_windows`) import them from
here."""

from __future__ import annotations

import functools
from importlib import resources

from fleetbrake.errors import FleetbrakeError

__all__ = ["SQL_PACKAGE", "WarehouseError", "sql", "sql_files"]

SQL_PACKAGE = "fleetbrake.warehouse.sql"
"""The package whose ``*.sql`` resources are the schema, views and queries (shipped in the wheel)."""


class WarehouseError(FleetbrakeError):
    """The warehouse cannot be opened or used; the message names the database file."""


def sql_files() -> list[str]:
    """Names of the packaged ``*.sql`` files, sorted."""
    return sorted(
        entry.name
        for entry in resources.files(SQL_PACKAGE).iterdir()
        if entry.name.endswith(".sql")
    )


@functools.cache
def sql(name: str) -> str:
    """Text of the packaged ``fleetbrake/warehouse/sql/<name>.sql``."""
    try:
        return resources.files(SQL_PACKAGE).joinpath(f"{name}.sql").read_text(encoding="utf-8")
    except FileNotFoundError:
        raise WarehouseError(
            f"{name}.sql: SQL file not found in {SQL_PACKAGE} (is the installation complete?)"
        ) from None
