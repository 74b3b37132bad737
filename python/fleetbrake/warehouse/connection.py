"""The DuckDB warehouse: open or create it, keep its schema and views current, one writer at a time.

::

    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse("warehouse/fleet.duckdb") as wh:    # WarehouseLockedError if busy
        with wh.transaction():
            wh.con.execute("INSERT INTO ... VALUES ($x)", {"x": 1})
        wh.con.sql("SELECT * FROM v_files").pl()

The SQL ships inside the package, in :mod:`fleetbrake.warehouse.sql` (read with
``importlib.resources``, so an installed wheel has it): ``schema*.sql`` (tables, applied first),
``v_*.sql`` (one view per file, applied next), both at every open and idempotent, and
``q_*.sql`` (one statement each, run by the code with bound ``$name`` parameters, read with
:func:`sql`). What stays Python here is the connection: opening, the lock, transactions and
DuckDB settings (:meth:`Warehouse.settings`).

One writer at a time: DuckDB lets a single process open a file for writing. A writer first
takes an exclusive ``flock`` on ``<db>.lock`` (released by the kernel when the process ends,
even on SIGKILL), so a second writer waits up to ``wait_s`` and then raises
:class:`WarehouseLockedError` naming the database and the process holding it, before DuckDB is
touched. Every change goes through DuckDB transactions, so a killed writer leaves the last
committed state.
"""

from __future__ import annotations

import datetime as dt
import fcntl
import os
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import duckdb

from fleetbrake.errors import DatabaseLockedError
from fleetbrake.warehouse.migration import migrate_to_v3
from fleetbrake.warehouse.sqlfiles import SQL_PACKAGE, WarehouseError, sql, sql_files

__all__ = [
    "DEFAULT_DB_PATH",
    "SCHEMA_VERSION",
    "SQL_PACKAGE",
    "Warehouse",
    "WarehouseError",
    "WarehouseLockedError",
    "apply_schema",
    "open_warehouse",
    "reader",
    "sql",
    "sql_files",
]

DEFAULT_DB_PATH = Path("warehouse/fleet.duckdb")
"""Where the database is when ``--db`` is not given (relative to the working directory)."""

SCHEMA_VERSION = 3
"""Version of the tables in ``schema*.sql``. A database of an older version is brought up to
date when opened for writing, its rows kept: the statements add what is missing (version 2:
``files.rows_rejected``, null for the files recorded before it, and the ``file_rejections``
table; version 3: ``contact_estimates.resolution_s``, 1 on the rows of before), then
:func:`~fleetbrake.warehouse.migration.migrate_to_v3` compacts the contact estimates, and the
version is recorded last. A database of a newer version is not opened."""

DEFAULT_MEMORY_LIMIT = "1GB"
"""DuckDB's buffer pool bound: the ingestion's memory does not grow with the fleet."""

_LOCK_POLL_S = 0.2


class WarehouseLockedError(WarehouseError, DatabaseLockedError):
    """Another process is writing to the database."""


def _schema_files() -> list[str]:
    """Names of the schema's statements, in order: the tables, then the views."""
    names = sql_files()
    tables = [n[:-4] for n in names if n.startswith("schema")]
    views = [n[:-4] for n in names if n.startswith("v_")]
    if not tables:
        raise WarehouseError(f"{SQL_PACKAGE}: no schema*.sql found (is the installation complete?)")
    return tables + views


def apply_schema(con: duckdb.DuckDBPyConnection, db_label: str = "database") -> None:
    """Create what is missing (tables, columns, then views) and record the schema version;
    idempotent. An older database gains what its version lacks in the same transaction, its
    contact estimates are then compacted (:func:`~fleetbrake.warehouse.migration.migrate_to_v3`,
    transactions of its own) and the version recorded last, so that an interrupted migration
    is run again, and completed, at the next open.

    Raises :class:`WarehouseError` if the database was made by a newer schema version.
    """
    con.execute("BEGIN TRANSACTION")
    try:
        for name in _schema_files():
            con.execute(sql(name))
        row = con.execute(sql("q_schema_version")).fetchone()
        found = None if row is None or row[0] is None else int(row[0])
        if found is not None and found > SCHEMA_VERSION:
            raise WarehouseError(
                f"{db_label}: schema version {found} was written by a newer fleetbrake "
                f"(this one knows version {SCHEMA_VERSION}); it was left unchanged"
            )
        if found is None:
            _record_version(con)
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise
    if found is not None and found < SCHEMA_VERSION:
        migrate_to_v3(con, db_label)
        _record_version(con)


def _record_version(con: duckdb.DuckDBPyConnection) -> None:
    con.execute(sql("q_insert_schema_version"), {"version": SCHEMA_VERSION, "now": _utc_now()})


def _utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(tzinfo=None)


def _scalar(row: tuple[object, ...] | None) -> object:
    """The one value of a one-row, one-column result (None if there is no row)."""
    return None if row is None else row[0]


_SETTINGS_SQL: Mapping[str, str] = {
    "memory_limit": "SET memory_limit = $value",
    "preserve_insertion_order": "SET preserve_insertion_order = $value",
    "disabled_compression_methods": "SET disabled_compression_methods = $value",
}
"""The DuckDB settings :meth:`Warehouse.settings` may change (a setting's name cannot be a
bound parameter: each has its statement, the value bound)."""


class _ProcessLock:
    """An exclusive ``flock`` on ``<db>.lock``, holding the owner's pid and start time."""

    def __init__(self, db_path: Path) -> None:
        self.path = db_path.with_name(db_path.name + ".lock")
        self._fd: int | None = None

    def acquire(self, db_path: Path, wait_s: float) -> None:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        deadline = time.monotonic() + max(wait_s, 0.0)
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    holder = self._holder()
                    os.close(fd)
                    waited = f" after waiting {wait_s:g} s" if wait_s > 0 else ""
                    raise WarehouseLockedError(
                        f"{db_path}: another fleetbrake process ({holder}) is writing to this "
                        f"database{waited}; nothing was changed. Run again when it has "
                        "finished, or give --wait SECONDS to wait for it."
                    ) from None
                time.sleep(_LOCK_POLL_S)
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()}, since {_utc_now():%Y-%m-%dT%H:%M:%SZ}\n".encode())
        self._fd = fd

    def _holder(self) -> str:
        try:
            text = self.path.read_text(encoding="utf-8").strip()
        except OSError:
            text = ""
        return text or "pid unknown"

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None


class Warehouse:
    """An open warehouse: a DuckDB connection (``con``) and, when writable, the process lock."""

    def __init__(
        self,
        path: Path,
        con: duckdb.DuckDBPyConnection,
        lock: _ProcessLock | None,
        opened_with: Mapping[str, object] | None = None,
    ) -> None:
        self.path = path
        self.con = con
        self._lock = lock
        self._opened_with = dict(opened_with or {})
        """The settings the connection was opened with, restored exactly by :meth:`settings`
        (DuckDB reports a memory limit rounded)."""

    @property
    def read_only(self) -> bool:
        """True when opened with ``read_only=True`` (no lock, no writes)."""
        return self._lock is None

    @contextmanager
    def transaction(self) -> Iterator[duckdb.DuckDBPyConnection]:
        """``BEGIN`` ... ``COMMIT``, or ``ROLLBACK`` if the block raises."""
        self.con.execute("BEGIN TRANSACTION")
        try:
            yield self.con
        except BaseException:
            self.con.execute("ROLLBACK")
            raise
        self.con.execute("COMMIT")

    @contextmanager
    def settings(self, **values: object) -> Iterator[None]:
        """DuckDB settings (names of :data:`_SETTINGS_SQL`) changed for the block, then
        restored to what they were."""
        unknown = sorted(set(values) - set(_SETTINGS_SQL))
        if unknown:
            raise ValueError(f"not a DuckDB setting the warehouse changes: {', '.join(unknown)}")
        before = {
            name: self._opened_with[name]
            if name in self._opened_with
            else _scalar(
                self.con.execute("SELECT current_setting($name)", {"name": name}).fetchone()
            )
            for name in values
        }
        for name, value in values.items():
            self.con.execute(_SETTINGS_SQL[name], {"value": value})
        try:
            yield
        finally:
            for name, value in before.items():
                self.con.execute(_SETTINGS_SQL[name], {"value": value})

    def close(self) -> None:
        """Close the connection, then release the lock."""
        try:
            self.con.close()
        finally:
            if self._lock is not None:
                self._lock.release()

    def __enter__(self) -> Warehouse:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextmanager
def reader(wh: Warehouse) -> Iterator[Warehouse]:
    """A second connection to ``wh``'s database (a DuckDB cursor: the same database and
    settings) for the reads of a stage whose writes run on a writer thread
    (:class:`fleetbrake.engine.writer.WriteBehind`) on ``wh``'s own connection (one
    connection is not to be used by two threads at once). It sees what was committed.
    Closed at the end of the block."""
    cursor = wh.con.cursor()
    try:
        yield Warehouse(wh.path, cursor, None)
    finally:
        cursor.close()


def open_warehouse(
    path: str | os.PathLike[str] = DEFAULT_DB_PATH,
    *,
    read_only: bool = False,
    wait_s: float = 0.0,
    memory_limit: str = DEFAULT_MEMORY_LIMIT,
    threads: int | None = None,
) -> Warehouse:
    """Open (creating it and its directory if needed) the warehouse at ``path``.

    Writable (the default): takes the process lock, waiting up to ``wait_s`` seconds for
    another writer (:class:`WarehouseLockedError` after that), then applies the schema and
    views. ``read_only=True``: no lock, no schema changes; the database must exist.
    """
    path = Path(path)
    config: dict[str, str | bool | int | float | list[str]] = {"memory_limit": memory_limit}
    if threads is not None:
        config["threads"] = threads
    if read_only:
        if not path.exists():
            raise WarehouseError(f"{path}: no such database")
        return Warehouse(path, _connect(path, read_only=True, config=config), None, config)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = _ProcessLock(path)
    lock.acquire(path, wait_s)
    try:
        con = _connect(path, read_only=False, config=config)
        try:
            apply_schema(con, str(path))
        except BaseException:
            con.close()
            raise
    except BaseException:
        lock.release()
        raise
    return Warehouse(path, con, lock, config)


def _connect(
    path: Path, *, read_only: bool, config: dict[str, str | bool | int | float | list[str]]
) -> duckdb.DuckDBPyConnection:
    try:
        return duckdb.connect(str(path), read_only=read_only, config=config)
    except duckdb.IOException as error:
        message = str(error)
        if "lock" in message.lower():
            raise WarehouseLockedError(
                f"{path}: the database is open in another process (not through fleetbrake's "
                f"lock); nothing was changed. DuckDB says: {message}"
            ) from None
        raise WarehouseError(f"{path}: cannot open the database: {message}") from None
    except duckdb.Error as error:
        raise WarehouseError(f"{path}: cannot open the database: {error}") from None
