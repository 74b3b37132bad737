"""Crash safety and the one-writer lock: SIGKILL mid-run, then a re-run, equals an uninterrupted run."""

from __future__ import annotations

import datetime as dt
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import duckdb
import numpy as np
import pytest

import fleetbrake
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import run_ingest
from fleetbrake.synth import corrupt
from fleetgen import T0_UTC, make_session, snapshot, write_registry, write_session

WALL_CLOCK = ("ingested_utc", "detected_utc", "applied_utc")
"""Columns that say when a row was written: the only ones allowed to differ between runs."""

PACKAGE_ROOT = str(Path(fleetbrake.__file__).resolve().parents[1])
WAGONS = ["SGG-0001", "SGG-0002", "SGG-0003"]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([PACKAGE_ROOT, env.get("PYTHONPATH", "")])
    return env


def _spawn(script: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(script), *args],
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _wait_for(path: Path, process: subprocess.Popen[str], timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        if process.poll() is not None:
            raise AssertionError(f"child ended early: {process.communicate()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"{path} did not appear")
        time.sleep(0.02)


def _kill(process: subprocess.Popen[str], *, may_have_ended: bool = False) -> None:
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=30)
    assert process.returncode == -signal.SIGKILL or (may_have_ended and process.returncode == 0)


def _count(db: Path, sql: str) -> int:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.execute(sql).fetchone()[0]
    finally:
        con.close()


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three wagons, 60 files with brakings and imperfections, two bad files."""
    root = tmp_path_factory.mktemp("crash") / "fleet"
    write_registry(root, WAGONS)
    rng = np.random.default_rng(5)
    for w, wagon in enumerate(WAGONS):
        for k in range(20):
            start = T0_UTC + dt.timedelta(hours=3 * k + w)
            session = make_session(rng, start, n_events=4, noise=True)
            frame = corrupt.swap_neighbours(
                corrupt.duplicate_rows(session.frame, rng, 0.01), rng, 0.01
            )
            write_session(root, wagon, frame, start, gzip=bool(k % 2))
    (root / "logs" / "SGG-0001" / "SGG-0001_20250101T000000Z.csv.gz").write_bytes(b"junk")
    (root / "logs" / "SGG-0404").mkdir()
    write_session(root, "SGG-0404", session.frame, T0_UTC)
    return root


SMALL_BATCHES = {"batch_rows": 20_000}


@pytest.fixture(scope="module")
def reference(fleet: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[tuple]]:
    """The tables after one uninterrupted run."""
    db = tmp_path_factory.mktemp("reference") / "fleet.duckdb"
    run_ingest(fleet, db, config=IngestConfig(**SMALL_BATCHES), progress=False)
    tables = snapshot(db, ignore=WALL_CLOCK)
    assert len(tables["files"]) == 62 and len(tables["events"]) > 150
    assert tables["event_dirty"] == []
    return tables


PAUSE_INGEST = """
import sys, time
from pathlib import Path
import fleetbrake.ingest.ledger as ledger
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import run_ingest
fleet, db, marker, after = sys.argv[1], sys.argv[2], Path(sys.argv[3]), int(sys.argv[4])
insert = ledger._insert
flushes = []
def pausing(con, name, frame, statement):
    insert(con, name, frame, statement)
    if name == "sample_batch":
        flushes.append(frame.height)
        if len(flushes) == after:  # inside the open transaction: samples in, not committed
            marker.write_text(str(len(flushes)))
            time.sleep(600)
ledger._insert = pausing
run_ingest(fleet, db, config=IngestConfig(batch_rows=20_000), progress=False)
"""


def test_sigkill_inside_a_transaction_then_rerun_equals_uninterrupted(
    fleet: Path, reference: dict[str, list[tuple]], tmp_path: Path
) -> None:
    db = tmp_path / "fleet.duckdb"
    committed = 0
    for after in (2, 3, 1):
        marker = tmp_path / f"paused-{after}"
        child = _spawn(PAUSE_INGEST, str(fleet), str(db), str(marker), str(after))
        _wait_for(marker, child)
        _kill(child)
        before, committed = committed, _count(db, "SELECT count(*) FROM files")
        # the batch being written is gone, whole: no file without its samples or back;
        # the batches before it are there
        assert (before < committed < 62) if after > 1 else (committed == before)
        assert _count(db, "SELECT count(*) FROM samples") == _count(
            db, "SELECT coalesce(sum(rows), 0) FROM files"
        )
        assert (
            _count(
                db, "SELECT count(*) FROM samples WHERE file_id NOT IN (SELECT file_id FROM files)"
            )
            == 0
        )
        assert _count(db, "SELECT count(*) FROM event_dirty") > 0
    run_ingest(fleet, db, config=IngestConfig(**SMALL_BATCHES), progress=False)
    assert snapshot(db, ignore=WALL_CLOCK) == reference


PAUSE_EVENTS = """
import sys, time
from pathlib import Path
import fleetbrake.ingest.events as events
fleet, db, marker, hook, commit_events = sys.argv[1], sys.argv[2], Path(sys.argv[3]), sys.argv[4], int(sys.argv[5])
events._COMMIT_EVENTS = commit_events
original = getattr(events, hook)
def pausing(*args, **kwargs):
    original(*args, **kwargs)
    marker.write_text(hook)  # the first batch: committed, or its insert done, not committed
    time.sleep(600)
setattr(events, hook, pausing)
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import run_ingest
run_ingest(fleet, db, config=IngestConfig(batch_rows=20_000), progress=False)
"""


@pytest.mark.parametrize(
    ("hook", "committed_wagons"),
    [
        ("_update_wagons", 2),  # the first batch (two wagons) committed, the second not begun
        ("_insert_events", 0),  # inside the first batch's transaction, after its insert
    ],
)
def test_sigkill_during_event_detection_then_rerun_equals_uninterrupted(
    fleet: Path,
    reference: dict[str, list[tuple]],
    tmp_path: Path,
    hook: str,
    committed_wagons: int,
) -> None:
    per_wagon = [sum(row[1] == wagon for row in reference["events"]) for wagon in WAGONS]
    assert all(n > 0 for n in per_wagon)
    # batches of whole wagons: the first two wagons together, the third alone
    commit_events = per_wagon[0] + per_wagon[1]
    db = tmp_path / "fleet.duckdb"
    marker = tmp_path / "paused"
    child = _spawn(PAUSE_EVENTS, str(fleet), str(db), str(marker), hook, str(commit_events))
    _wait_for(marker, child)
    _kill(child)
    assert _count(db, "SELECT count(*) FROM files") == 62
    # whole wagons: each either has its events and no dirty range, or dirty ranges and none
    assert _count(db, "SELECT count(DISTINCT wagon_id) FROM events") == committed_wagons
    assert _count(db, "SELECT count(DISTINCT wagon_id) FROM event_dirty") == 3 - committed_wagons
    assert (
        _count(
            db,
            "SELECT count(*) FROM events WHERE wagon_id IN (SELECT wagon_id FROM event_dirty)",
        )
        == 0
    )
    report = run_ingest(fleet, db, config=IngestConfig(**SMALL_BATCHES), progress=False)
    assert report.results == [] and report.events is not None
    assert report.events.wagons == 3 - committed_wagons
    assert snapshot(db, ignore=WALL_CLOCK) == reference


RUN = """
import sys
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import run_ingest
run_ingest(sys.argv[1], sys.argv[2], config=IngestConfig(batch_rows=20_000), progress=False)
"""


@pytest.mark.slow
def test_sigkill_at_random_moments_then_rerun_equals_uninterrupted(
    fleet: Path, reference: dict[str, list[tuple]], tmp_path: Path
) -> None:
    started = time.monotonic()
    full = _spawn(RUN, str(fleet), str(tmp_path / "timing.duckdb"))
    assert full.wait(timeout=300) == 0, full.communicate()
    run_s = time.monotonic() - started
    db = tmp_path / "fleet.duckdb"
    rng = np.random.default_rng(1)
    partial_states = 0
    for _ in range(6):
        child = _spawn(RUN, str(fleet), str(db))
        time.sleep(float(rng.uniform(0.2, 0.9)) * run_s)
        _kill(child, may_have_ended=True)
        if db.exists():
            tables = "SELECT count(*) FROM information_schema.tables WHERE table_name = 'files'"
            if not _count(db, tables):  # killed before the schema's commit: nothing stored
                partial_states += 1
                continue
            files = _count(db, "SELECT count(*) FROM files")
            dirty = _count(db, "SELECT count(*) FROM event_dirty")
            partial_states += files < 62 or dirty > 0
    assert partial_states >= 1, "no kill landed in the middle of a run"
    run_ingest(fleet, db, config=IngestConfig(**SMALL_BATCHES), progress=False)
    assert snapshot(db, ignore=WALL_CLOCK) == reference


# --------------------------------------------------------------------------------------------
# One writer at a time

HOLD = """
import sys, time
from pathlib import Path
from fleetbrake.warehouse.connection import open_warehouse
with open_warehouse(sys.argv[1]) as wh:
    Path(sys.argv[2]).write_text("holding")
    time.sleep(float(sys.argv[3]))
"""

HOLD_RAW = """
import sys, time, duckdb
from pathlib import Path
con = duckdb.connect(sys.argv[1])
Path(sys.argv[2]).write_text("holding")
time.sleep(float(sys.argv[3]))
"""


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetbrake.cli.main", *args],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_a_second_writer_exits_with_a_clear_message(fleet: Path, tmp_path: Path) -> None:
    db = tmp_path / "fleet.duckdb"
    marker = tmp_path / "holding"
    holder = _spawn(HOLD, str(db), str(marker), "600")
    try:
        _wait_for(marker, holder)
        result = _cli("ingest", str(fleet), "--db", str(db))
        assert result.returncode == 75
        assert f"{db}: another fleetbrake process (pid {holder.pid}, since " in result.stderr
        assert "nothing was changed" in result.stderr
        assert "Traceback" not in result.stderr
    finally:
        _kill(holder)
    assert _count(db, "SELECT count(*) FROM files") == 0


def test_a_second_writer_waits_when_asked(fleet: Path, tmp_path: Path) -> None:
    db = tmp_path / "fleet.duckdb"
    marker = tmp_path / "holding"
    holder = _spawn(HOLD, str(db), str(marker), "2")
    _wait_for(marker, holder)
    started = time.monotonic()
    result = _cli("ingest", str(fleet), "--db", str(db), "--wait", "120")
    assert result.returncode == 0, result.stderr
    assert holder.wait(timeout=60) == 0
    assert time.monotonic() - started > 0.5  # it did wait for the holder
    assert _count(db, "SELECT count(*) FROM files") == 62


def test_a_database_open_elsewhere_is_reported_not_touched(fleet: Path, tmp_path: Path) -> None:
    db = tmp_path / "fleet.duckdb"
    duckdb.connect(str(db)).close()
    marker = tmp_path / "holding"
    holder = _spawn(HOLD_RAW, str(db), str(marker), "600")
    try:
        _wait_for(marker, holder)
        result = _cli("ingest", str(fleet), "--db", str(db))
        assert result.returncode == 75
        assert f"{db}: the database is open in another process" in result.stderr
    finally:
        _kill(holder)
    assert _count(db, "SELECT count(*) FROM information_schema.tables") == 0
