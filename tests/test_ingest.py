"""Ingestion of a fleet directory: every imperfection of fleet-data.md, idempotence, late files."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import os
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import duckdb
import numpy as np
import polars as pl
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from fleetbrake.app.run import run_fleet
from fleetbrake.cli.main import app
from fleetbrake.fleet import logfile as lf
from fleetbrake.fleet.registry import RegistryError
from fleetbrake.ingest import files as ingest_module
from fleetbrake.ingest import prepare as prepare_module
from fleetbrake.ingest import scan as scan_module
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import IngestReport, ingest_fleet, run_ingest
from fleetbrake.ingest.quarantine import Quarantine
from fleetbrake.ingest.reading import read_log
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.synth import corrupt
from fleetbrake.warehouse.connection import open_warehouse
from fleetgen import (
    T0_UTC,
    make_session,
    relpath_of,
    simple_session,
    snapshot,
    write_registry,
    write_session,
)

WAGON = "SGG-0001"
ROWS = 900


def ingest(fleet: Path, db: Path, **config: object) -> IngestReport:
    """One ingestion run (events included), no progress bar."""
    return run_ingest(fleet, db, config=IngestConfig(**config), progress=False)  # type: ignore[arg-type]


def query(db: Path, sql: str, params: dict[str, object] | None = None) -> list[tuple]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.execute(sql, params or {}).fetchall()
    finally:
        con.close()


def file_row(db: Path, path: str) -> dict[str, object]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        frame = con.sql("SELECT * FROM files WHERE path = $p", params={"p": path}).pl()
    finally:
        con.close()
    assert frame.height == 1, f"{path} not recorded"
    return frame.row(0, named=True)


def stored(db: Path, path: str) -> pl.DataFrame:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.sql(
            "SELECT s.* FROM samples s JOIN files f USING (file_id) WHERE f.path = $p "
            "ORDER BY time_utc",
            params={"p": path},
        ).pl()
    finally:
        con.close()


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    root = tmp_path / "fleet"
    write_registry(root, [WAGON, "SGG-0002", "SGG_0003"])
    return root


@pytest.fixture
def db(tmp_path: Path) -> Path:
    return tmp_path / "wh" / "fleet.duckdb"


# --------------------------------------------------------------------------------------------
# Contract of the views


def test_views_have_exactly_the_interface_columns(fleet: Path, db: Path) -> None:
    ingest(fleet, db)
    con = duckdb.connect(str(db), read_only=True)
    try:
        files = con.execute("DESCRIBE v_files").fetchall()
        events = con.execute("DESCRIBE v_events").fetchall()
    finally:
        con.close()
    assert [(r[0], r[1]) for r in files] == [
        ("path", "VARCHAR"),
        ("wagon_id", "VARCHAR"),
        ("status", "VARCHAR"),
        ("rows", "BIGINT"),
        ("rows_rejected", "BIGINT"),
        ("reason", "VARCHAR"),
        ("ingested_utc", "TIMESTAMP"),
    ]
    assert [(r[0], r[1]) for r in events] == [
        ("event_id", "VARCHAR"),
        ("wagon_id", "VARCHAR"),
        ("start_utc", "TIMESTAMP"),
        ("end_utc", "TIMESTAMP"),
        ("duration_s", "DOUBLE"),
        ("distance_m", "DOUBLE"),
        ("v_start_kmh", "DOUBLE"),
        ("v_end_kmh", "DOUBLE"),
        ("p_mean_bar", "DOUBLE"),
        ("t_block_start_c", "DOUBLE"),
    ]


def test_clean_file_is_stored_exactly(fleet: Path, db: Path) -> None:
    frame = simple_session(rows=ROWS)
    write_session(fleet, WAGON, frame, T0_UTC)
    report = ingest(fleet, db)
    path = relpath_of(WAGON, T0_UTC)
    assert [(r.path, r.status, r.rows) for r in report.results] == [(path, "ingested", ROWS)]
    assert query(db, "SELECT * EXCLUDE (ingested_utc) FROM v_files") == [
        (path, WAGON, "ingested", ROWS, 0, None)
    ]
    samples = stored(db, path)
    assert samples.select(frame.columns).equals(frame)
    assert samples["wagon_id"].unique().to_list() == [WAGON]
    assert not samples["block_temp_fault"].any()
    assert samples["block_temp_raw_c"].null_count() == ROWS
    row = file_row(db, path)
    assert row["repairs"] is None and row["reason"] is None
    assert (row["first_utc"], row["last_utc"]) == (
        T0_UTC,
        T0_UTC + dt.timedelta(seconds=ROWS - 1),
    )
    assert row["sha256"] == __import__("hashlib").sha256((fleet / path).read_bytes()).hexdigest()


# --------------------------------------------------------------------------------------------
# Repairable imperfections, one by one


@dataclasses.dataclass
class Case:
    """An imperfect file: how to make it, and what the ingestion must record."""

    make: Callable[[pl.DataFrame, np.random.Generator], pl.DataFrame | bytes]
    counters: dict[str, object] = dataclasses.field(default_factory=dict)
    gzip: bool = True
    """The name ends in .gz (and the content is compressed, unless ``compress``)."""
    note: str | None = None
    compress: bool | None = None


def _expected_rows(written: pl.DataFrame | bytes, original: pl.DataFrame) -> int:
    """Rows with a usable, distinct time in what was written."""
    if isinstance(written, bytes):
        return lf.complete_rows(written)
    times = written["time_utc"]
    if times.dtype == pl.String:
        times = times.str.to_datetime(lf.TIME_FORMAT, strict=False)
    return times.drop_nulls().n_unique()


def _crlf(frame: pl.DataFrame, rng: np.random.Generator) -> bytes:
    return lf.to_csv_bytes(frame).replace(b"\n", b"\r\n")


def _extra_cells(frame: pl.DataFrame, rng: np.random.Generator) -> bytes:
    lines = lf.to_csv_bytes(frame).split(b"\n")
    lines[10] += b",surplus,cells"
    return b"\n".join(lines)


def _not_finite(frame: pl.DataFrame, rng: np.random.Generator) -> pl.DataFrame:
    speed = frame["speed_kmh"].to_numpy().copy()
    speed[[5, 6]] = [np.inf, np.nan]
    return frame.with_columns(pl.Series("speed_kmh", speed))


def _impossible(frame: pl.DataFrame, rng: np.random.Generator) -> pl.DataFrame:
    """Finite numbers no channel can take: a speed of 1e308 km/h, a pressure of -5 bar, ..."""
    changes = {
        "speed_kmh": {5: 1e308, 6: -3.0},
        "brake_pressure_bar": {7: -5.0},
        "lat_deg": {8: 91.0},
        "ambient_temp_c": {9: 1000.0},
    }
    columns = []
    for name, rows in changes.items():
        values = frame[name].to_numpy().copy()
        for row, value in rows.items():
            values[row] = value
        columns.append(pl.Series(name, values))
    return frame.with_columns(columns)


def _bom(frame: pl.DataFrame, rng: np.random.Generator) -> bytes:
    return b"\xef\xbb\xbf" + lf.to_csv_bytes(frame)


def _rows_outside_session(frame: pl.DataFrame, rng: np.random.Generator) -> pl.DataFrame:
    times = frame["time_utc"].to_list()
    times[100] = T0_UTC - dt.timedelta(hours=1)
    times[200] = T0_UTC + dt.timedelta(days=5)
    return frame.with_columns(pl.Series("time_utc", times, dtype=pl.Datetime("us")))


CASES: dict[str, Case] = {
    "drop rows": Case(lambda f, r: corrupt.drop_rows(f, r, 0.05)),
    "gap": Case(lambda f, r: corrupt.drop_gap(f, r, 240)),
    "duplicates": Case(lambda f, r: corrupt.duplicate_rows(f, r, 0.03), {"rows_duplicate": 27}),
    "out of order": Case(
        lambda f, r: corrupt.swap_neighbours(f, r, 0.03), {"rows_out_of_order": (10, 27)}
    ),
    "blank cells": Case(lambda f, r: corrupt.blank_cells(f, r, 0.02), {"rows_no_time": 18}),
    "garbled numbers": Case(
        lambda f, r: corrupt.garble_cells(f, r, 0.01, ("speed_kmh", "block_temp_c"), text="ERR"),
        {"cells_unparsable": 18},
        note="not a finite number",
    ),
    "garbled times": Case(
        lambda f, r: corrupt.garble_cells(f, r, 0.01, ("time_utc",), text="2024-13-45T99:00:00Z"),
        {"rows_no_time": 9},
        note="not a time",
    ),
    "not finite numbers": Case(_not_finite, {"cells_unparsable": 2}),
    "physically impossible numbers": Case(
        _impossible, {"cells_unparsable": 5}, note="outside the range the channel can take"
    ),
    "gps speed frozen": Case(lambda f, r: corrupt.freeze_speed(f, r, 200)),
    "gps speed jumps": Case(lambda f, r: corrupt.jump_speed(f, r, 6)),
    "pt1000 frozen": Case(lambda f, r: corrupt.pt1000_frozen(f, r, 300)),
    "pt1000 drifting": Case(lambda f, r: corrupt.pt1000_drift_to_ambient(f, r)),
    "pt1000 open circuit": Case(
        lambda f, r: corrupt.pt1000_open_circuit(f, r, 60), {"block_temp_faults": 60}
    ),
    "truncated mid-row": Case(
        lambda f, r: corrupt.truncate_mid_row(lf.to_csv_bytes(f), r),
        {"partial_row_dropped": True},
        gzip=False,
        note="cut short",
    ),
    "truncated mid-row, then gzipped": Case(
        lambda f, r: corrupt.truncate_mid_row(lf.to_csv_bytes(f), r),
        {"partial_row_dropped": True},
        gzip=True,
    ),
    "crlf": Case(_crlf, gzip=False),
    "byte order mark": Case(_bom, gzip=False),
    "more cells than the header": Case(
        _extra_cells, {"rows_rejected": 1}, gzip=False, note="line 11 has 11"
    ),
    "rows outside the session": Case(_rows_outside_session, {"rows_outside_session": 2}),
    "columns shuffled, extra, no ambient": Case(
        lambda f, r: (
            f.drop("ambient_temp_c")
            .with_columns(pl.lit("x").alias("firmware"))
            .select([*r.permutation(f.columns[:-1]).tolist(), "firmware"])
        )
    ),
    "gzip named .csv": Case(lambda f, r: lf.gzip_bytes(lf.to_csv_bytes(f)), gzip=False),
    "plain named .csv.gz": Case(lambda f, r: lf.to_csv_bytes(f), gzip=True, compress=False),
}


@pytest.mark.parametrize("name", list(CASES))
def test_repairable_file_keeps_every_good_row(name: str, fleet: Path, db: Path) -> None:
    case = CASES[name]
    original = simple_session(rows=ROWS, seed=7)
    written = case.make(original, np.random.default_rng(11))
    write_session(fleet, WAGON, written, T0_UTC, gzip=case.gzip, compress=case.compress)
    path = relpath_of(WAGON, T0_UTC, gzip=case.gzip)
    report = ingest(fleet, db)

    assert [r.status for r in report.results] == ["ingested"]
    if isinstance(written, pl.DataFrame):
        expected = _expected_rows(written, original)
        if name == "rows outside the session":
            expected -= 2
    elif name.startswith("truncated"):
        expected = lf.complete_rows(written)
    elif name == "more cells than the header":
        expected = ROWS - 1
    else:
        expected = ROWS
    assert 0 < expected
    row = file_row(db, path)
    assert row["rows"] == expected == report.rows
    samples = stored(db, path)
    assert samples.height == expected
    assert samples["time_utc"].is_sorted() and samples["time_utc"].n_unique() == expected
    for counter, value in case.counters.items():
        if isinstance(value, tuple):
            assert value[0] <= row[counter] <= value[1], counter
        else:
            assert row[counter] == value, counter
    if case.counters or case.note:
        assert row["repairs"], "a repair must be described"
        assert case.note is None or case.note in row["repairs"]
    # Samples that were written clean are stored unchanged.
    columns = [c for c in lf.COLUMNS if c in samples.columns and c != "ambient_temp_c"]
    clean_written = original.join(samples.select("time_utc"), on="time_utc").sort("time_utc")
    if name in ("drop rows", "gap", "duplicates", "out of order", "crlf", "byte order mark"):
        assert samples.select(columns).equals(clean_written.select(columns))


def test_open_circuit_readings_are_faults_not_temperatures(fleet: Path, db: Path) -> None:
    original = simple_session(rows=ROWS)
    broken = corrupt.pt1000_open_circuit(original, np.random.default_rng(0), 50, start=100)
    broken = corrupt.pt1000_open_circuit(
        broken, np.random.default_rng(1), 5, start=400, reading_c=-61
    )
    write_session(fleet, WAGON, broken, T0_UTC)
    ingest(fleet, db)
    samples = stored(db, relpath_of(WAGON, T0_UTC))
    faulty = samples.filter(pl.col("block_temp_fault"))
    assert faulty.height == 55
    assert faulty["block_temp_c"].null_count() == 55
    assert (
        faulty["block_temp_raw_c"].to_list()
        == broken["block_temp_c"].slice(100, 50).to_list() + [-61.0] * 5
    )
    good = samples.filter(~pl.col("block_temp_fault"))
    assert good["block_temp_raw_c"].null_count() == good.height
    assert good["block_temp_c"].null_count() == 0
    row = file_row(db, relpath_of(WAGON, T0_UTC))
    assert "55 block_temp_c readings outside [-60, 600] degC" in row["repairs"]
    assert "lines 102, 103, 104, 105, 106 and 50 more" in row["repairs"]


def test_impossible_readings_are_counted_emptied_and_warn_nowhere(
    fleet: Path,
    db: Path,
    monkeypatch: pytest.MonkeyPatch,
    rom_refinement: float,
    rom_cache_dir: Path,
    default_rom: object,  # the session's reduced model, built once under the conftest's lock
) -> None:
    """A speed of 1e308 km/h and a pressure of -5 bar inside a braking: the file is ingested,
    the cells are recorded as unparsable ones are (counted, noted with their lines, stored
    empty), and the whole run (events, simulation, flags) raises no warning (numpy's overflow
    warning, for one, would reach the console from the simulation)."""
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    session = make_session(np.random.default_rng(3), n_events=4, kinds=("slowdown", "stop"))
    onset = int((session.events[1].onset_utc - T0_UTC).total_seconds())
    speed = session.frame["speed_kmh"].to_numpy().copy()
    pressure = session.frame["brake_pressure_bar"].to_numpy().copy()
    speed[onset + 5 : onset + 8] = 1e308
    pressure[onset + 10 : onset + 12] = -5.0
    frame = session.frame.with_columns(
        pl.Series("speed_kmh", speed), pl.Series("brake_pressure_bar", pressure)
    )
    write_session(fleet, WAGON, frame, T0_UTC)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        report = run_fleet(
            fleet, db, simulation=SimulationConfig(refinement=rom_refinement), progress=False
        )
    assert [r.status for r in report.ingest.results] == ["ingested"]  # type: ignore[attr-defined]
    assert report.simulation.events_simulated == len(session.events)
    path = relpath_of(WAGON, T0_UTC)
    row = file_row(db, path)
    assert row["rows"] == frame.height
    assert row["cells_unparsable"] == 5
    lines = ", ".join(str(onset + 2 + k) for k in (5, 6, 7))
    assert f"speed_kmh outside [0, 350] lines {lines} (1e+308, 1e+308, ...)" in row["repairs"]
    lines = ", ".join(str(onset + 2 + k) for k in (10, 11))
    assert f"brake_pressure_bar outside [-1, 12] lines {lines} (-5, -5)" in row["repairs"]
    samples = stored(db, path)
    assert samples["speed_kmh"].slice(onset + 5, 3).null_count() == 3
    assert samples["brake_pressure_bar"].slice(onset + 10, 2).null_count() == 2
    assert samples["speed_kmh"].null_count() == 3
    assert samples["brake_pressure_bar"].null_count() == 2


def test_repair_notes_name_lines(fleet: Path, db: Path) -> None:
    frame = simple_session(rows=50)
    data = lf.to_csv_bytes(frame).split(b"\n")
    data[4] = b"," + data[4].split(b",", 1)[1]  # line 5: empty time
    data[7] = data[6]  # line 8 repeats line 7
    data[12] = data[12].replace(b",", b",abc,", 1).rsplit(b",", 1)[0]  # line 13: 'abc' speed
    write_session(fleet, WAGON, b"\n".join(data), T0_UTC, gzip=False)
    ingest(fleet, db)
    row = file_row(db, relpath_of(WAGON, T0_UTC, gzip=False))
    assert row["rows"] == 48
    assert "1 row without a time dropped (1 empty): line 5" in row["repairs"]
    assert "repeating an earlier row's time dropped (the first kept): line 8" in row["repairs"]
    assert "speed_kmh line 13 ('abc')" in row["repairs"]


def test_header_only_file_is_ingested_empty(fleet: Path, db: Path) -> None:
    write_session(fleet, WAGON, simple_session(rows=0), T0_UTC)
    report = ingest(fleet, db)
    assert [(r.status, r.rows) for r in report.results] == [("ingested", 0)]


# --------------------------------------------------------------------------------------------
# Files that cannot be ingested


def _registry_extra(fleet: Path) -> None:
    write_registry(
        fleet,
        [WAGON, "SGG-0002", "SGG_0003"],
        extra='[[wagon]]\nid = "BAD-0001"\ncylinder_diameter_m = -0.3\n',
    )


QUARANTINE: dict[str, tuple[str, Callable[[Path], None], str]] = {
    # name: (relative path, how to write it, words the reason must hold)
    "truncated gzip": (
        relpath_of(WAGON, T0_UTC),
        lambda p: p.write_bytes(
            corrupt.truncate_gzip(
                lf.gzip_bytes(lf.to_csv_bytes(simple_session(rows=ROWS))),
                np.random.default_rng(0),
            )
        ),
        "gzip stream truncated",
    ),
    "corrupt gzip": (
        relpath_of(WAGON, T0_UTC),
        lambda p: p.write_bytes(b"\x1f\x8b\x08\x00" + bytes(range(256)) * 4),
        "corrupt gzip",
    ),
    "garbage binary": (
        relpath_of(WAGON, T0_UTC),
        lambda p: p.write_bytes(corrupt.garbage_bytes(np.random.default_rng(3), 5000)),
        "not a CSV log",
    ),
    "garbage text": (
        relpath_of(WAGON, T0_UTC, gzip=False),
        lambda p: p.write_bytes(corrupt.garbage_bytes(np.random.default_rng(3), 5000, kind="text")),
        "is not a log header",
    ),
    "zeros": (
        relpath_of(WAGON, T0_UTC, gzip=False),
        lambda p: p.write_bytes(
            corrupt.garbage_bytes(np.random.default_rng(3), 5000, kind="zeros")
        ),
        "no complete first line",
    ),
    "empty": (relpath_of(WAGON, T0_UTC), lambda p: p.write_bytes(b""), "empty file"),
    "wrong header": (
        relpath_of(WAGON, T0_UTC),
        lambda p: p.write_bytes(
            lf.gzip_bytes(
                lf.to_csv_bytes(simple_session(rows=10).rename({"brake_pressure_bar": "pressure"}))
            )
        ),
        "lacks brake_pressure_bar",
    ),
    "column twice": (
        relpath_of(WAGON, T0_UTC, gzip=False),
        lambda p: p.write_bytes(
            lf.to_csv_bytes(simple_session(rows=10)).replace(b"ambient_temp_c", b"speed_kmh")
        ),
        "names speed_kmh more than once",
    ),
    "unknown wagon": (
        relpath_of("SGG-9999", T0_UTC),
        lambda p: lf.write_log(p, simple_session(rows=10)),
        "SGG-9999 has no entry in the registry",
    ),
    "invalid registry entry": (
        relpath_of("BAD-0001", T0_UTC),
        lambda p: (_registry_extra(p.parents[2]), lf.write_log(p, simple_session(rows=10))),
        "key cylinder_diameter_m",
    ),
    "bad file name": (
        f"logs/{WAGON}/{WAGON}_2024-03-01.csv",
        lambda p: lf.write_log(p, simple_session(rows=10)),
        "does not follow",
    ),
    "wagon directory not the file's": (
        f"logs/SGG-0002/{WAGON}_20240301T060000Z.csv.gz",
        lambda p: lf.write_log(p, simple_session(rows=10)),
        "file of wagon SGG-0001 in the directory of wagon SGG-0002",
    ),
    "file directly in logs": (
        f"logs/{WAGON}_20240301T060000Z.csv.gz",
        lambda p: lf.write_log(p, simple_session(rows=10)),
        "must be at logs/<wagon_id>/<file name>",
    ),
}


@pytest.mark.parametrize("name", list(QUARANTINE))
def test_bad_file_is_quarantined_with_a_reason_naming_it(name: str, fleet: Path, db: Path) -> None:
    relpath, make, words = QUARANTINE[name]
    (fleet / relpath).parent.mkdir(parents=True, exist_ok=True)
    make(fleet / relpath)
    good = write_session(fleet, "SGG-0002", simple_session(rows=100), T0_UTC)
    report = ingest(fleet, db)
    assert {r.path: r.status for r in report.results} == {
        relpath: "quarantined",
        good.relative_to(fleet).as_posix(): "ingested",
    }
    ((path, status, rows, reason),) = query(
        db, "SELECT path, status, rows, reason FROM v_files WHERE status = 'quarantined'"
    )
    assert (path, status, rows) == (relpath, "quarantined", 0)
    assert reason.startswith(relpath + ": ")
    assert words in reason
    assert query(db, "SELECT count(*) FROM samples")[0][0] == 100


def test_hidden_files_are_ignored(fleet: Path, db: Path) -> None:
    write_session(fleet, WAGON, simple_session(rows=10), T0_UTC)
    (fleet / "logs" / WAGON / f".{WAGON}_20240301T070000Z.csv.gz.Xa81Ks").write_bytes(b"partial")
    (fleet / "logs" / ".trash").mkdir()
    (fleet / "logs" / ".trash" / "x.csv").write_bytes(b"x")
    report = ingest(fleet, db)
    assert report.files_seen == 1
    assert query(db, "SELECT count(*) FROM files")[0][0] == 1


# --------------------------------------------------------------------------------------------
# Everything at once


SAFE_TO_COMBINE = [
    "drop rows",
    "gap",
    "duplicates",
    "out of order",
    "blank cells",
    "not finite numbers",
    "physically impossible numbers",
    "gps speed frozen",
    "gps speed jumps",
    "pt1000 frozen",
    "pt1000 drifting",
    "pt1000 open circuit",
    "rows outside the session",
]
"""Frame-level cases that can be applied one after the other."""


def _messy_fleet(fleet: Path, rng: np.random.Generator) -> tuple[int, set[str]]:
    """Many files with random imperfections, and every kind of bad file; returns the rows that
    must be stored and the paths that must be quarantined."""
    expected_rows = 0
    for w, wagon in enumerate([WAGON, "SGG-0002", "SGG_0003"]):
        for k in range(8):
            start = T0_UTC + dt.timedelta(hours=2 * k, minutes=w)
            frame = simple_session(start, rows=int(rng.integers(300, 1500)), seed=w * 10 + k)
            for name in rng.choice(SAFE_TO_COMBINE, size=3, replace=False):
                frame = CASES[str(name)].make(frame, rng)
            if rng.random() < 0.3:  # non-parsable cells last: they make the columns text
                frame = CASES[str(rng.choice(["garbled numbers", "garbled times"]))].make(
                    frame, rng
                )
            gz = bool(rng.integers(0, 2))
            if k == 7:  # a unit that lost power: plain CSV cut mid-row
                data = corrupt.truncate_mid_row(lf.to_csv_bytes(frame), rng)
                write_session(fleet, wagon, data, start, gzip=False)
                expected_rows += _rows_of_bytes(data, start)
            else:
                write_session(fleet, wagon, frame, start, gzip=gz)
                expected_rows += _rows_of_frame(frame, start)
    quarantined = set()
    for relpath, make, _ in QUARANTINE.values():
        target = fleet / relpath.replace("20240301T060000Z", "20240302T060000Z")
        target.parent.mkdir(parents=True, exist_ok=True)
        make(target)
        quarantined.add(target.relative_to(fleet).as_posix())
    return expected_rows, quarantined


def _usable_times(times: pl.Series, start: dt.datetime) -> int:
    if times.dtype == pl.String:
        times = times.str.to_datetime(lf.TIME_FORMAT, strict=False)
    times = times.drop_nulls()
    late = start + dt.timedelta(hours=48)
    return times.filter((times >= start) & (times <= late)).n_unique()


def _rows_of_frame(frame: pl.DataFrame, start: dt.datetime) -> int:
    return _usable_times(frame["time_utc"], start)


def _rows_of_bytes(data: bytes, start: dt.datetime) -> int:
    complete = data[: data.rfind(b"\n") + 1]
    frame = pl.read_csv(complete, infer_schema=False, quote_char=None)
    return _usable_times(frame["time_utc"], start)


def test_everything_at_once_loses_nothing_good(fleet: Path, db: Path) -> None:
    rng = np.random.default_rng(2024)
    expected_rows, quarantined = _messy_fleet(fleet, rng)
    result = CliRunner().invoke(app, ["ingest", str(fleet), "--db", str(db)])
    assert result.exit_code == 0, result.output
    assert query(db, "SELECT count(*) FROM samples")[0][0] == expected_rows
    assert query(db, "SELECT sum(rows) FROM v_files")[0][0] == expected_rows
    rows = query(db, "SELECT path, reason FROM v_files WHERE status = 'quarantined'")
    assert {p for p, _ in rows} == quarantined
    for path, reason in rows:
        assert reason.startswith(path + ": ")
        assert path in result.output
    assert query(db, "SELECT count(*) FROM v_files WHERE status = 'ingested'")[0][0] == 24
    assert "quarantined" in result.output
    # per wagon, samples never repeat a time
    assert query(
        db,
        "SELECT count(*) FROM (SELECT wagon_id, time_utc FROM samples GROUP BY ALL HAVING count(*) > 1)",
    ) == [(0,)]


# --------------------------------------------------------------------------------------------
# Idempotence, new and late files, changed files, a fixed registry


def _three_wagons(fleet: Path) -> list[str]:
    paths = []
    for w, wagon in enumerate([WAGON, "SGG-0002", "SGG_0003"]):
        for k in range(3):
            start = T0_UTC + dt.timedelta(days=1, hours=3 * k)
            frame = corrupt.duplicate_rows(
                simple_session(start, rows=700, seed=w + k), np.random.default_rng(k), 0.01
            )
            paths.append(write_session(fleet, wagon, frame, start).relative_to(fleet).as_posix())
    (fleet / "logs" / WAGON / "junk.csv").write_bytes(b"junk")
    return paths


def test_second_run_changes_nothing(fleet: Path, db: Path) -> None:
    _three_wagons(fleet)
    first = ingest(fleet, db)
    assert len(first.ingested) == 9 and len(first.quarantined) == 1
    before = snapshot(db)
    assert before["events"], "the sessions have brakings"
    second = ingest(fleet, db)
    assert second.results == [] and second.files_unchanged == 10
    assert second.events is not None and second.events.added == second.events.removed == 0
    assert snapshot(db) == before
    third = ingest(fleet, db, verify_hashes=True)  # every file read and hashed again
    assert third.results == [] and third.files_unchanged == 10
    assert snapshot(db) == before


def test_new_and_late_files_are_taken_and_nothing_else(fleet: Path, db: Path) -> None:
    _three_wagons(fleet)
    ingest(fleet, db)
    before = snapshot(db, ignore=())
    new = write_session(
        fleet,
        WAGON,
        simple_session(T0_UTC + dt.timedelta(days=2), rows=500),
        T0_UTC + dt.timedelta(days=2),
    )
    late = write_session(fleet, "SGG-0002", simple_session(T0_UTC, rows=400), T0_UTC)
    report = ingest(fleet, db)
    assert sorted(r.path for r in report.results) == sorted(
        p.relative_to(fleet).as_posix() for p in (new, late)
    )
    assert all(r.status == "ingested" and not r.replaced for r in report.results)
    after = snapshot(db)
    for table in ("files", "samples"):
        assert set(before[table]) <= set(after[table])
    assert len(after["samples"]) == len(before["samples"]) + 900
    assert len(after["files"]) == len(before["files"]) + 2
    # events: the old ones untouched (same rows, same detected_utc), two new ones
    assert set(before["events"]) <= set(after["events"])
    assert len(after["events"]) == len(before["events"]) + 2
    assert report.events is not None and report.events.added == 2 and report.events.removed == 0


def test_a_path_with_other_bytes_replaces_its_samples(fleet: Path, db: Path) -> None:
    start = T0_UTC
    path = write_session(fleet, WAGON, simple_session(start, rows=300), start)
    ingest(fleet, db)
    (old_id,) = query(db, "SELECT file_id FROM files")[0]
    write_session(fleet, WAGON, simple_session(start, rows=500, seed=9), start)
    report = ingest(fleet, db)
    assert [(r.status, r.rows, r.replaced) for r in report.results] == [("ingested", 500, True)]
    assert query(db, "SELECT count(*), count(DISTINCT file_id), min(file_id) FROM samples") == [
        (500, 1, old_id + 1)
    ]
    assert query(
        db, "SELECT count(*) FROM files WHERE path = $p", {"p": path.relative_to(fleet).as_posix()}
    ) == [(1,)]


def test_same_size_and_mtime_is_trusted_unless_verify_hashes(fleet: Path, db: Path) -> None:
    path = write_session(fleet, WAGON, simple_session(rows=300), T0_UTC, gzip=False)
    ingest(fleet, db)
    stat = path.stat()
    data = path.read_bytes()
    last_digit = data[-2:-1]
    path.write_bytes(data[:-2] + (b"1" if last_digit != b"1" else b"2") + b"\n")
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size
    assert ingest(fleet, db).results == []
    report = ingest(fleet, db, verify_hashes=True)
    assert [(r.status, r.replaced) for r in report.results] == [("ingested", True)]


def test_quarantined_for_the_registry_is_taken_once_the_registry_is_fixed(
    fleet: Path, db: Path
) -> None:
    path = write_session(fleet, "SGG-0009", simple_session(rows=200), T0_UTC)
    first = ingest(fleet, db)
    assert [r.status for r in first.results] == ["quarantined"]
    assert ingest(fleet, db).results == []  # same registry: same verdict, nothing written
    write_registry(fleet, [WAGON, "SGG-0009"])
    report = ingest(fleet, db)
    assert [(r.status, r.rows, r.replaced) for r in report.results] == [("ingested", 200, True)]
    assert query(
        db,
        "SELECT status, rows FROM v_files WHERE path = $p",
        {"p": path.relative_to(fleet).as_posix()},
    ) == [("ingested", 200)]


# --------------------------------------------------------------------------------------------
# Command line and failures to do the job


def test_cli_reports_and_exits_zero_with_bad_files(fleet: Path, db: Path) -> None:
    write_session(fleet, WAGON, simple_session(rows=600), T0_UTC)
    (fleet / "logs" / WAGON / f"{WAGON}_20240302T000000Z.csv").write_bytes(b"\x00\x01garbage")
    result = CliRunner().invoke(app, ["ingest", str(fleet), "--db", str(db)])
    assert result.exit_code == 0, result.output
    assert "1 ingested (600 rows, 0 rejected), 1 quarantined" in result.output
    assert f"logs/{WAGON}/{WAGON}_20240302T000000Z.csv: " in result.output
    assert "events: 1 new or changed" in result.output


def test_cli_fails_without_a_registry_and_leaves_no_database(tmp_path: Path, db: Path) -> None:
    (tmp_path / "fleet" / "logs").mkdir(parents=True)
    result = CliRunner().invoke(app, ["ingest", str(tmp_path / "fleet"), "--db", str(db)])
    assert result.exit_code == 1
    assert "fleet.toml: registry file not found" in result.output
    assert not db.exists()
    with pytest.raises(RegistryError):
        ingest(tmp_path / "fleet", db)


def test_cli_fails_without_a_fleet_directory(tmp_path: Path, db: Path) -> None:
    result = CliRunner().invoke(app, ["ingest", str(tmp_path / "nowhere"), "--db", str(db)])
    assert result.exit_code == 1
    assert "nowhere: no such fleet directory" in result.output


def test_cli_fails_on_a_file_that_is_not_a_database(fleet: Path, tmp_path: Path) -> None:
    not_db = tmp_path / "x.duckdb"
    not_db.write_bytes(b"this is no database" * 100)
    result = CliRunner().invoke(app, ["ingest", str(fleet), "--db", str(not_db)])
    assert result.exit_code == 1
    assert str(not_db) in result.output


def test_ingest_fleet_on_an_open_warehouse(fleet: Path, db: Path) -> None:
    write_session(fleet, WAGON, simple_session(rows=100), T0_UTC)
    with open_warehouse(db) as wh:
        report = ingest_fleet(fleet, wh, progress=False)
        assert report.rows == 100
        assert report.events is None
        assert wh.con.execute("SELECT count(*) FROM event_dirty").fetchone() == (1,)


# --------------------------------------------------------------------------------------------
# Whatever the bytes, the reader repairs or quarantines, and the fleet goes on


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    cut=st.integers(min_value=0, max_value=4000),
    flips=st.lists(
        st.tuples(st.integers(min_value=0, max_value=4000), st.integers(0, 255)), max_size=12
    ),
    tail=st.binary(max_size=64),
)
def test_reader_never_fails_on_damaged_bytes(
    cut: int, flips: list[tuple[int, int]], tail: bytes
) -> None:
    data = bytearray(lf.to_csv_bytes(simple_session(rows=40))[: 200 + cut])
    for position, value in flips:
        if position < len(data):
            data[position] = value
    try:
        parsed = read_log(bytes(data) + tail, "logs/W/W_20240301T060000Z.csv", T0_UTC)
    except Quarantine as problem:
        assert problem.reason.startswith("logs/W/W_20240301T060000Z.csv: ")
        return
    frame = parsed.frame
    assert frame.columns == ["time_utc", *lf.FLOAT_COLUMNS, "block_temp_raw_c", "block_temp_fault"]
    assert frame["time_utc"].null_count() == 0
    assert frame["time_utc"].is_sorted() and frame["time_utc"].n_unique() == frame.height
    assert frame.height <= parsed.repairs.rows_in_file


def test_unreadable_file_and_reader_failure_are_quarantined_then_retried(
    fleet: Path, db: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    locked = write_session(fleet, WAGON, simple_session(rows=100), T0_UTC)
    odd_start = T0_UTC + dt.timedelta(hours=1)
    odd = write_session(fleet, WAGON, simple_session(odd_start, rows=100), odd_start)
    fine_start = T0_UTC + dt.timedelta(hours=2)
    write_session(fleet, WAGON, simple_session(fine_start, rows=100), fine_start)
    read_bytes = Path.read_bytes
    read_log_ = prepare_module.read_log

    def refuse(path: Path) -> bytes:
        if path == locked:
            raise PermissionError(13, "Permission denied")
        return read_bytes(path)

    def fail(data: bytes, relpath: str, *args: object) -> object:
        if relpath.endswith(odd.name):
            raise RuntimeError("reader bug")
        return read_log_(data, relpath, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(Path, "read_bytes", refuse)
    monkeypatch.setattr(prepare_module, "read_log", fail)
    first = ingest(fleet, db)
    reasons = {r.path: r.reason for r in first.quarantined}
    assert reasons == {
        locked.relative_to(fleet).as_posix(): f"{locked.relative_to(fleet).as_posix()}: "
        "cannot be read (Permission denied)",
        odd.relative_to(fleet).as_posix(): f"{odd.relative_to(fleet).as_posix()}: "
        "could not be read (RuntimeError: reader bug)",
    }
    assert first.rows == 100
    assert ingest(fleet, db).results == []  # same causes, same verdicts: nothing written
    monkeypatch.undo()
    second = ingest(fleet, db)
    assert sorted((r.status, r.rows, r.replaced) for r in second.results) == [
        ("ingested", 100, True),
        ("ingested", 100, True),
    ]


def test_a_file_removed_after_the_scan_is_skipped(
    fleet: Path, db: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    write_session(fleet, WAGON, simple_session(rows=100), T0_UTC)
    scan = ingest_module.scan_logs

    def with_ghost(fleet_dir: Path) -> list[scan_module.LogEntry]:
        ghost = fleet_dir / relpath_of(WAGON, T0_UTC + dt.timedelta(hours=1))
        return [
            *scan(fleet_dir),
            scan_module.LogEntry(ghost.relative_to(fleet_dir).as_posix(), ghost, 10, 1),
        ]

    monkeypatch.setattr(ingest_module, "scan_logs", with_ghost)
    report = ingest(fleet, db)
    assert report.files_seen == 1 and [r.status for r in report.results] == ["ingested"]


def _child_env() -> dict[str, str]:
    """The environment for a child python that imports this fleetbrake."""
    package_root = str(Path(ingest_module.__file__).resolve().parents[2])
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([package_root, os.environ.get("PYTHONPATH", "")]),
    }


def test_bench_ingest_prints_its_figures_as_json_last(tmp_path: Path) -> None:
    fleet = tmp_path / "bench-fleet"
    command = [sys.executable, "-m", "fleetbrake.cli.main", "bench", "ingest", "--json"]
    command += ["--rows", "200000", "--fleet", str(fleet), "--workdir", str(tmp_path)]
    for _ in range(2):  # made, then reused
        result = subprocess.run(
            command, capture_output=True, text=True, timeout=300, check=True, env=_child_env()
        )
        figures = json.loads(result.stdout.strip().splitlines()[-1])
        assert figures["rows"] == 200_000 and figures["files"] == 10
        assert figures["rows_per_s"] == pytest.approx(200_000 / figures["seconds"], rel=0.01)
        assert 50 < figures["peak_rss_mb"] < 4000
        assert len(figures["rss_mb_quarter_peaks"]) == 4
    assert len(list(fleet.rglob("*.csv.gz"))) == 10
    assert [p.name for p in tmp_path.iterdir()] == ["bench-fleet"]  # the rest cleaned up
