"""Every row read is stored or rejected, and every rejected row is named: in ``v_files``
(``rows_rejected``, ``reason``), in ``v_file_rejections`` (each run of lines and why), on stderr
and in the run's report; a file whose rows are all rejected is quarantined."""

from __future__ import annotations

import datetime as dt
import gzip
import logging
from collections.abc import Callable
from pathlib import Path

import duckdb
import polars as pl
import pytest
from rich.console import Console

from fleetbrake.fleet import logfile as lf
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import IngestReport, print_report, run_ingest
from fleetbrake.warehouse.connection import SCHEMA_VERSION, open_warehouse
from fleetgen import T0_UTC, relpath_of, simple_session, write_registry, write_session

WAGON = "SGG-0001"
ROWS = 600
FIELDS = len(simple_session(rows=2).columns)


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    root = tmp_path / "fleet"
    write_registry(root, [WAGON])
    return root


@pytest.fixture
def db(tmp_path: Path) -> Path:
    return tmp_path / "wh" / "fleet.duckdb"


def _ingest(fleet: Path, db: Path) -> IngestReport:
    return run_ingest(fleet, db, config=IngestConfig(), progress=False)


def _query(db: Path, sql: str, params: dict[str, object] | None = None) -> list[tuple]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.execute(sql, params or {}).fetchall()
    finally:
        con.close()


def _file(db: Path, path: str) -> dict[str, object]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        frame = con.sql(
            "SELECT v.*, f.rows_in_file, f.quarantine_code FROM v_files v JOIN files f "
            "USING (path) WHERE path = $p",
            params={"p": path},
        ).pl()
    finally:
        con.close()
    assert frame.height == 1, path
    return frame.row(0, named=True)


def _rejections(db: Path, path: str) -> list[tuple]:
    return _query(
        db,
        "SELECT first_line, last_line, rows, reason FROM v_file_rejections WHERE path = $p "
        "ORDER BY first_line",
        {"p": path},
    )


def _write_lines(fleet: Path, start: dt.datetime, edit: Callable[[list[bytes]], None]) -> str:
    """A plain CSV session of ``ROWS`` rows at ``start``, its lines (header = index 0) edited."""
    path = write_session(fleet, WAGON, simple_session(start, rows=ROWS), start, gzip=False)
    lines = path.read_bytes().split(b"\n")
    edit(lines)
    path.write_bytes(b"\n".join(lines))
    return relpath_of(WAGON, start, gzip=False)


def test_a_row_with_an_extra_field_of_a_megabyte_is_rejected_and_named(
    fleet: Path, db: Path, caplog: pytest.LogCaptureFixture
) -> None:
    def extra_field(lines: list[bytes]) -> None:
        time_cell, rest = lines[1].split(b",", 1)
        lines[1] = time_cell + b"," + b"x" * (1 << 20) + b"," + rest

    path = _write_lines(fleet, T0_UTC, extra_field)
    with caplog.at_level(logging.WARNING, logger="fleetbrake.ingest.files"):
        report = _ingest(fleet, db)

    row = _file(db, path)
    assert (row["status"], row["rows"], row["rows_rejected"]) == ("ingested", ROWS - 1, 1)
    assert row["rows_in_file"] == row["rows"] + row["rows_rejected"]
    assert row["reason"].startswith(f"{path}: 1 row rejected: ")
    assert f"line 2 has {FIELDS + 1}" in row["reason"]
    assert len(row["reason"]) < 500  # the megabyte is not copied into the ledger
    assert _rejections(db, path) == [(2, 2, 1, f"{FIELDS + 1} fields ({FIELDS} expected)")]
    assert report.rows_rejected == 1
    assert [r.message for r in caplog.records] == [
        f"{path}: 1 of {ROWS} rows read rejected (see v_file_rejections)"
    ]
    console = Console(record=True, width=200, soft_wrap=True)
    print_report(report, console)
    assert f"1 ingested ({ROWS - 1:,} rows, 1 rejected)" in console.export_text()


def test_a_file_repeating_another_files_times_is_quarantined_with_its_reason(
    fleet: Path, db: Path
) -> None:
    original = write_session(fleet, WAGON, simple_session(rows=ROWS), T0_UTC, gzip=False)
    later = T0_UTC + dt.timedelta(hours=1)
    copy = fleet / relpath_of(WAGON, later, gzip=True)
    copy.write_bytes(gzip.compress(original.read_bytes()))
    report = _ingest(fleet, db)

    path = relpath_of(WAGON, later)
    row = _file(db, path)
    assert (row["status"], row["quarantine_code"], row["rows"]) == ("quarantined", "rows", 0)
    assert (row["rows_in_file"], row["rows_rejected"]) == (ROWS, ROWS)
    assert row["reason"].startswith(f"{path}: no row kept, {ROWS} rows rejected: ")
    assert "before the file name's time 2024-03-01T07:00:00Z" in row["reason"]
    [(first, last, rows, why)] = _rejections(db, path)
    assert (first, last, rows) == (2, ROWS + 1, ROWS)
    assert "before the file name's time" in why
    assert [r.status for r in report.results] == ["ingested", "quarantined"]
    assert report.rows_rejected == ROWS
    assert _ingest(fleet, db).results == []  # judged by its bytes alone: not read again


def test_each_kind_of_bad_row_is_named_with_its_lines(fleet: Path, db: Path) -> None:
    def damage(lines: list[bytes]) -> None:
        lines[2] = lines[2].rsplit(b",", 1)[0]  # line 3: a field short
        lines[4] = b"2024-03-01 06:00:03," + lines[4].split(b",", 1)[1]  # line 5: not a time
        lines[40] = b"2024-03-01T05:00:00Z," + lines[40].split(b",", 1)[1]  # line 41, 42:
        lines[41] = b"2024-03-01T05:00:01Z," + lines[41].split(b",", 1)[1]  # before the name
        lines[60] = lines[59]  # line 61 repeats line 60's time
        lines[-1] = b"2024-03-01T06:10"  # the file ends inside its last line

    path = _write_lines(fleet, T0_UTC, damage)
    _ingest(fleet, db)

    row = _file(db, path)
    assert (row["status"], row["rows_rejected"]) == ("ingested", 6)
    assert row["rows_in_file"] == ROWS + 1 == row["rows"] + row["rows_rejected"]
    reasons = dict(((first, last), (rows, why)) for first, last, rows, why in _rejections(db, path))
    assert reasons[(3, 3)] == (1, f"{FIELDS - 1} fields ({FIELDS} expected)")
    assert reasons[(5, 5)][1].startswith("no time")
    assert reasons[(41, 42)][0] == 2 and "before the file name's time" in reasons[(41, 42)][1]
    assert "repeats the time of an earlier row" in reasons[(61, 61)][1]
    assert reasons[(ROWS + 2, ROWS + 2)][1].startswith("cut short")
    assert sum(rows for rows, _ in reasons.values()) == 6
    for named in (
        f"line 3 has {FIELDS - 1}",
        "line 5",
        "lines 41, 42",
        "line 61",
        "inside line 602",
    ):
        assert named in row["reason"], named


def test_every_row_of_a_generated_fleet_is_stored_or_rejected(
    tmp_path: Path, reduced_model_for: Callable[..., object], rom_cache_dir: Path
) -> None:
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        config = SynthConfig(wagons=2, days=1, seed=8, anomalies=False, duplicate_fraction=0.01)
        generate_fleet(tmp_path / "fleet", config, rom=reduced_model_for)
    db = tmp_path / "fleet.duckdb"
    report = run_ingest(tmp_path / "fleet", db, progress=False)
    con = duckdb.connect(str(db), read_only=True)
    try:
        files = con.sql(
            "SELECT f.path, f.status, f.rows, f.rows_in_file, f.rows_rejected, f.reason, "
            "(SELECT coalesce(sum(r.rows), 0) FROM file_rejections r WHERE r.file_id = f.file_id)"
            " AS named, (SELECT count(*) FROM samples s WHERE s.file_id = f.file_id) AS samples "
            "FROM files f"
        ).pl()
    finally:
        con.close()
    read = files.filter(pl.col("rows_in_file").is_not_null())
    assert read.height > 0 and files.filter(pl.col("status") == "quarantined").height > 0
    assert read.filter(pl.col("rows_rejected") > 0).height > 0, "the fleet has bad rows"
    for row in read.iter_rows(named=True):
        assert row["rows"] == row["samples"], row["path"]
        assert row["rows_in_file"] == row["rows"] + row["rows_rejected"], row["path"]
        assert row["named"] == row["rows_rejected"], row["path"]
        assert (row["reason"] is None) == (row["rows_rejected"] == 0), row["path"]
        data = (tmp_path / "fleet" / row["path"]).read_bytes()
        text = gzip.decompress(data) if data[:2] == b"\x1f\x8b" else data
        lines = text.count(b"\n") - 1 + (0 if text.endswith(b"\n") else 1)
        assert row["rows_in_file"] == lines, row["path"]
    assert report.rows_rejected == int(read["rows_rejected"].sum())


def test_a_warehouse_without_the_column_gains_it_and_keeps_its_rows(fleet: Path, db: Path) -> None:
    write_session(fleet, WAGON, simple_session(rows=ROWS), T0_UTC)
    _ingest(fleet, db)
    con = duckdb.connect(str(db))
    try:  # the schema of version 1: no rows_rejected, no file_rejections
        con.execute("DROP VIEW v_files")
        con.execute("DROP VIEW v_file_rejections")
        con.execute("DROP TABLE file_rejections")
        con.execute("ALTER TABLE files DROP COLUMN rows_rejected")
        con.execute("DELETE FROM schema_version")
        con.execute("INSERT INTO schema_version VALUES (1, now())")
        samples = con.execute("SELECT count(*) FROM samples").fetchone()
    finally:
        con.close()

    with open_warehouse(db) as wh:
        assert wh.con.execute("SELECT max(version) FROM schema_version").fetchone() == (
            SCHEMA_VERSION,
        )
        assert wh.con.execute("SELECT path, rows, rows_rejected FROM v_files").fetchall() == [
            (relpath_of(WAGON, T0_UTC), ROWS, None)
        ]
        assert wh.con.execute("SELECT count(*) FROM samples").fetchone() == samples
        assert wh.con.execute("SELECT count(*) FROM v_file_rejections").fetchone() == (0,)
    assert _ingest(fleet, db).results == []  # nothing read again
    later = T0_UTC + dt.timedelta(hours=2)
    write_session(fleet, WAGON, lf.to_csv_bytes(simple_session(later, rows=10)) + b"x", later)
    report = _ingest(fleet, db)
    assert [(r.rows, r.rows_rejected) for r in report.results] == [(10, 1)]
