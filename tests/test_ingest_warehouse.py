"""The warehouse: schema and views applied idempotently, versions, the writer lock, transactions."""

from __future__ import annotations

import time
from pathlib import Path

import duckdb
import pytest

from fleetbrake.warehouse.connection import (
    SCHEMA_VERSION,
    WarehouseError,
    WarehouseLockedError,
    open_warehouse,
    sql,
    sql_files,
)

TABLES = {"schema_version", "files", "samples", "event_dirty", "events"}
VIEWS = {"v_files", "v_events"}


def _objects(db: Path) -> tuple[set[str], set[str]]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        rows = con.execute(
            "SELECT table_name, table_type FROM information_schema.tables"
        ).fetchall()
    finally:
        con.close()
    return {n for n, t in rows if t == "BASE TABLE"}, {n for n, t in rows if t == "VIEW"}


def test_open_creates_everything_and_reopening_changes_nothing(tmp_path: Path) -> None:
    db = tmp_path / "deep" / "dir" / "fleet.duckdb"
    with open_warehouse(db) as wh:
        wh.con.execute(
            "INSERT INTO events VALUES ('W-1', 'W', '2024-03-01 06:00:00', "
            "'2024-03-01 06:01:00', 60, 800, 70, 40, 1.2, 1.5, 20, 'slowdown', true, now())"
        )
    tables, views = _objects(db)
    assert TABLES <= tables and VIEWS <= views
    for _ in range(2):
        with open_warehouse(db) as wh:
            assert wh.con.execute("SELECT version FROM schema_version").fetchall() == [
                (SCHEMA_VERSION,)
            ]
            assert wh.con.execute("SELECT event_id FROM v_events").fetchall() == [("W-1",)]
    assert _objects(db) == (tables, views)


def test_every_view_is_in_its_own_file_and_sql_files_exist() -> None:
    assert {name.removesuffix(".sql") for name in sql_files() if name.startswith("v_")} >= VIEWS
    for name in ("schema", "q_insert_files", "q_insert_samples", "q_insert_events"):
        assert sql(name).strip()
    with pytest.raises(WarehouseError, match=r"no_such\.sql: SQL file not found"):
        sql("no_such")


def test_a_newer_schema_is_not_touched(tmp_path: Path) -> None:
    db = tmp_path / "fleet.duckdb"
    with open_warehouse(db) as wh:
        wh.con.execute("INSERT INTO schema_version VALUES (99, now())")
    with pytest.raises(WarehouseError, match=f"{db}: schema version 99 was written by a newer"):
        open_warehouse(db)
    con = duckdb.connect(str(db), read_only=True)
    try:
        assert con.execute("SELECT max(version) FROM schema_version").fetchone() == (99,)
    finally:
        con.close()
    with open_warehouse(db.with_name("other.duckdb")):  # the lock was given back
        pass
    with pytest.raises(WarehouseError, match="schema version 99"):
        open_warehouse(db)


def test_second_writer_is_refused_or_waits(tmp_path: Path) -> None:
    db = tmp_path / "fleet.duckdb"
    first = open_warehouse(db)
    try:
        started = time.monotonic()
        with pytest.raises(WarehouseLockedError) as refused:
            open_warehouse(db, wait_s=0.5)
        assert time.monotonic() - started >= 0.5
        message = str(refused.value)
        assert message.startswith(f"{db}: another fleetbrake process (pid ")
        assert "after waiting 0.5 s; nothing was changed" in message
    finally:
        first.close()
    with open_warehouse(db, wait_s=0.0):  # the lock is released on close
        pass


def test_read_only(tmp_path: Path) -> None:
    with pytest.raises(WarehouseError, match="no such database"):
        open_warehouse(tmp_path / "none.duckdb", read_only=True)
    db = tmp_path / "fleet.duckdb"
    open_warehouse(db).close()
    with open_warehouse(db, read_only=True) as wh:
        assert wh.read_only
        assert wh.con.execute("SELECT count(*) FROM v_files").fetchone() == (0,)
        with pytest.raises(duckdb.Error):
            wh.con.execute("DELETE FROM files")


def test_settings_hold_for_the_block_only(tmp_path: Path) -> None:
    with open_warehouse(tmp_path / "fleet.duckdb", memory_limit="512MB") as wh:

        def setting(name: str) -> object:
            return wh.con.execute("SELECT current_setting($n)", {"n": name}).fetchone()[0]  # type: ignore[index]

        before = setting("memory_limit"), setting("preserve_insertion_order")
        with wh.settings(memory_limit="64MB", preserve_insertion_order=False):
            assert setting("preserve_insertion_order") is False
            assert setting("memory_limit") != before[0]
        assert (setting("memory_limit"), setting("preserve_insertion_order")) == before
        with pytest.raises(RuntimeError), wh.settings(memory_limit="64MB"):
            raise RuntimeError("the block failed")
        assert setting("memory_limit") == before[0]
        with pytest.raises(ValueError, match="not a DuckDB setting the warehouse changes: x"):
            with wh.settings(x=1):
                pass


def test_transaction_rolls_back_on_error(tmp_path: Path) -> None:
    with open_warehouse(tmp_path / "fleet.duckdb") as wh:
        with pytest.raises(RuntimeError), wh.transaction() as con:
            con.execute("INSERT INTO schema_version VALUES (0, now())")
            raise RuntimeError("boom")
        assert wh.con.execute("SELECT count(*) FROM schema_version").fetchone() == (1,)
