"""Units of ingestion: exactly the files handed over (``files=``, as ``fleetbrake watch``
hands them), and the ledger's refresh for a file whose bytes did not change."""

from __future__ import annotations

import datetime as dt
import os
from pathlib import Path

import duckdb
import pytest

from fleetbrake.app.run import run_fleet
from fleetbrake.ingest import prepare as prepare_module
from fleetbrake.ingest.files import IngestReport, ingest_fleet
from fleetbrake.ingest.scan import scan_logs, stat_logs
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.warehouse.connection import open_warehouse
from fleetgen import T0_UTC, simple_session, snapshot, write_registry, write_session

WAGONS = ["SGG-0001", "SGG-0002"]


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    root = tmp_path / "fleet"
    write_registry(root, WAGONS)
    return root


@pytest.fixture
def db(tmp_path: Path) -> Path:
    return tmp_path / "wh" / "fleet.duckdb"


def _ingest(fleet: Path, db: Path, files: list[str] | None = None) -> IngestReport:
    with open_warehouse(db) as wh:
        return ingest_fleet(fleet, wh, progress=False, files=files)


def _ledger(db: Path) -> dict[str, tuple[int, int, str]]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        rows = con.execute("SELECT path, size_bytes, mtime_ns, status FROM files").fetchall()
    finally:
        con.close()
    return {path: (size, mtime, status) for path, size, mtime, status in rows}


def _session(fleet: Path, wagon: str, hours: int, rows: int = 400) -> str:
    start = T0_UTC + dt.timedelta(hours=hours)
    path = write_session(fleet, wagon, simple_session(start, rows=rows, seed=hours), start)
    return path.relative_to(fleet).as_posix()


def test_stat_logs_lists_only_the_paths_handed_that_scan_logs_would_list(fleet: Path) -> None:
    a = _session(fleet, WAGONS[0], 0)
    b = _session(fleet, WAGONS[1], 0)
    hidden = fleet / "logs" / WAGONS[0] / ".x.csv.tmp"
    hidden.write_bytes(b"x")
    handed = [
        b,
        a,
        a,  # twice: once
        "logs/SGG-0001/gone.csv",  # not there
        "fleet.toml",  # not under logs/
        "logs/SGG-0001/.x.csv.tmp",  # hidden
        "logs/SGG-0001/../../fleet.toml",  # out of the tree
        "logs/SGG-0001",  # a directory
    ]
    assert [e.relpath for e in stat_logs(fleet, handed)] == sorted([a, b])
    scanned = {e.relpath: e for e in scan_logs(fleet)}
    for entry in stat_logs(fleet, [a, b]):
        assert entry == scanned[entry.relpath]


def test_a_unit_reads_exactly_the_files_handed_not_one_being_written(fleet: Path, db: Path) -> None:
    """``files=``: a file lying half-written in ``logs/`` when the unit starts (another
    gateway's upload in progress) is not read by it, nor is a complete one not handed; once
    handed, complete, it is read whole, and a plain run (no ``files``) still takes everything
    not yet held."""
    handed = _session(fleet, WAGONS[0], 0)
    other = _session(fleet, WAGONS[1], 0)
    start = T0_UTC + dt.timedelta(hours=6)
    whole = write_session(fleet, WAGONS[1], simple_session(start, rows=500, seed=6), start)
    data = whole.read_bytes()
    whole.write_bytes(data[: len(data) // 3])  # half-written, in place
    writing = whole.relative_to(fleet).as_posix()

    first = _ingest(fleet, db, files=[handed])
    assert [(r.path, r.status) for r in first.results] == [(handed, "ingested")]
    assert first.files_seen == 1
    assert set(_ledger(db)) == {handed}

    whole.write_bytes(data)  # finished
    second = _ingest(fleet, db, files=[writing, handed])  # the handed one again: unchanged
    assert [(r.path, r.status, r.rows) for r in second.results] == [(writing, "ingested", 500)]
    assert second.files_unchanged == 1
    assert set(_ledger(db)) == {handed, writing}

    third = _ingest(fleet, db)  # a plain run: the rest of logs/
    assert [r.path for r in third.results] == [other]


def test_run_fleet_hands_files_down_to_the_ingestion(
    fleet: Path,
    db: Path,
    monkeypatch: pytest.MonkeyPatch,
    rom_cache_dir: Path,
    rom_refinement: float,
) -> None:
    """``run_fleet(files=...)`` ingests exactly those files, and the later stages see the same
    as a plain run over the same files: the files, samples, events and simulation end up
    equal."""
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    sim = SimulationConfig(refinement=rom_refinement)
    a = _session(fleet, WAGONS[0], 0, rows=900)
    b = _session(fleet, WAGONS[1], 3, rows=900)
    report = run_fleet(
        fleet, db, simulation=sim, progress=False, engine="local", workers=1, files=[a]
    )
    assert [r.path for r in report.ingest.results] == [a]
    assert set(_ledger(db)) == {a}
    report = run_fleet(
        fleet, db, simulation=sim, progress=False, engine="local", workers=1, files=[b]
    )
    assert [r.path for r in report.ingest.results] == [b]

    reference = db.with_name("reference.duckdb")
    run_fleet(fleet, reference, simulation=sim, progress=False, engine="local", workers=1)
    # the ingestion's, the events' and the simulation's tables; the estimates' noise is fitted
    # on the wagons present at the time (tables written later are left out)
    tables = ("files", "samples", "events", "predictions", "timeline", "timeline_segments")
    ignore = ("ingested_utc", "detected_utc")  # when it was written
    ours, theirs = snapshot(db, ignore=ignore), snapshot(reference, ignore=ignore)
    for table in tables:
        assert ours[table] == theirs[table], table
    assert ours["samples"] and ours["events"] and ours["predictions"]


def test_a_touched_file_takes_its_new_mtime_in_the_ledger_and_is_not_read_again(
    fleet: Path, db: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same bytes under another modification time (a copy, a touch): nothing is stored
    again, the ledger row takes the new mtime, and the next run does not read the file at all
    (a ledger keeping the old one would have every run, and every rescan of ``watch``, read it
    again)."""
    path = _session(fleet, WAGONS[0], 0)
    quarantined = "logs/SGG-0001/SGG-0001_20240302T060000Z.csv"
    (fleet / quarantined).write_bytes(b"not,a,log\n1,2,3\n")
    _ingest(fleet, db)
    ignore = ("size_bytes", "mtime_ns")
    before = snapshot(db, ignore=ignore)
    for name in (path, quarantined):
        stat = (fleet / name).stat()
        os.utime(fleet / name, ns=(stat.st_atime_ns, stat.st_mtime_ns + 7_000_000_000))

    read: list[str] = []
    real = prepare_module._prepare

    def counting(entry, problems, config):  # type: ignore[no-untyped-def]
        read.append(entry.relpath)
        return real(entry, problems, config)

    monkeypatch.setattr(prepare_module, "_prepare", counting)
    report = _ingest(fleet, db)
    assert sorted(read) == sorted([path, quarantined])  # read and hashed: the same bytes
    assert report.results == [] and report.files_unchanged == 2
    ledger = _ledger(db)
    for name in (path, quarantined):
        stat = (fleet / name).stat()
        assert ledger[name][:2] == (stat.st_size, stat.st_mtime_ns)
    assert ledger[quarantined][2] == "quarantined"
    assert snapshot(db, ignore=ignore) == before  # nothing else changed
    after = snapshot(db)

    read.clear()
    again = _ingest(fleet, db)
    assert read == [] and again.results == [] and again.files_unchanged == 2
    assert snapshot(db) == after
