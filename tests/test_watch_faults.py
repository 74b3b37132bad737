"""``watch`` under faults: a full disk under the warehouse, a read-only landing folder, a file
replaced while it is read, and wall-clock jumps.

The service runs in this process (:func:`watch_fleet` on a thread, one worker, the session's
reduced model) so that each test can make the fault happen at a chosen moment. The full disk
and the read-only folder are real: a small ``tmpfs`` is mounted under the warehouse (filled to
its last byte), or over ``logs/`` and remounted read-only, which stops root as well (a
``chmod`` does not); the tests are skipped where this process cannot mount. For each fault:
the service keeps running, says what happened in one sentence logged once (not at every
retry), and once the fault clears the files still queued are processed, leaving the tables
of a run without the fault. Every wait is bounded.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from fleetbrake.app.watch.service import FileOutcome, WatchConfig, watch_fleet
from fleetbrake.ingest import files as ingest_files
from fleetbrake.simulation.config import SimulationConfig
from fleetgen import write_registry
from test_watch import WAGONS, _land, _reference_run, _session_bytes, _sessions, _views

BOUND_S = 60.0
"""The longest any wait of these tests may take."""
LOGGER = "fleetbrake.app.watch.service"


class _Records(logging.Handler):
    """The service's log records; ``started`` is set once it logs that it is watching."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.records: list[logging.LogRecord] = []
        self.started = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)
        if record.getMessage().startswith("watching "):
            self.started.set()


class InProcess:
    """``watch_fleet`` on a thread of this process: its outcomes and log as they come."""

    def __init__(self, fleet: Path, db: Path, refinement: float) -> None:
        self.stop = threading.Event()
        self.outcomes: list[FileOutcome] = []
        config = WatchConfig(
            settle_s=1.0,
            rescan_s=2.0,
            retry_s=0.2,
            health_s=1.0,
            wait_s=5.0,
            workers=1,
            simulation=SimulationConfig(refinement=refinement),
        )
        self.error: BaseException | None = None
        self.handler = _Records()
        logging.getLogger(LOGGER).addHandler(self.handler)
        self.thread = threading.Thread(target=self._run, args=(fleet, db, config), daemon=True)
        self.thread.start()

    def _run(self, fleet: Path, db: Path, config: WatchConfig) -> None:
        try:
            watch_fleet(fleet, db, config, self.stop, on_file=self.outcomes.append)
        except BaseException as error:  # the test says so
            self.error = error

    def log(self) -> str:
        return "\n".join(r.getMessage() for r in self.handler.records)

    def wait_until(self, what: str, done: Callable[[], bool]) -> None:
        deadline = time.monotonic() + BOUND_S
        while not done():
            assert self.thread.is_alive(), f"the service stopped: {self.error!r}"
            assert time.monotonic() < deadline, f"waited {BOUND_S} s for {what}"
            time.sleep(0.05)

    def wait_for(self, paths: set[str]) -> None:
        self.wait_until(str(paths), lambda: paths <= {o.path for o in self.outcomes})

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=BOUND_S)
        assert not self.thread.is_alive()
        assert self.error is None, repr(self.error)


@pytest.fixture
def start(
    rom_cache_dir: Path, rom_refinement: float, monkeypatch: pytest.MonkeyPatch
) -> Iterator[Callable[[Path, Path], InProcess]]:
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    monkeypatch.setenv("RAYON_NUM_THREADS", "1")
    logger = logging.getLogger(LOGGER)
    level = logger.level
    logger.setLevel(logging.INFO)
    started: list[InProcess] = []

    def start(fleet: Path, db: Path) -> InProcess:
        started.append(InProcess(fleet, db, rom_refinement))
        started[-1].wait_until("the service to start", started[-1].handler.started.is_set)
        return started[-1]

    yield start
    for service in started:
        service.stop.set()
        service.thread.join(timeout=BOUND_S)
        logger.removeHandler(service.handler)
    logger.setLevel(level)


@contextlib.contextmanager
def _tmpfs(where: Path, size: str) -> Iterator[Path]:
    """A ``tmpfs`` of ``size`` mounted on ``where`` (skips the test where mounting is not
    allowed), unmounted at the end."""
    where.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
        capture_output=True,
        check=False,
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def _remount(where: Path, mode: str) -> None:
    subprocess.run(["mount", "-o", f"remount,{mode}", str(where)], check=True)


def _fill(folder: Path) -> Path:
    """A file in ``folder`` written until its filesystem has no byte left."""
    filler = folder / "filler"
    block = b"\0" * (1 << 16)
    with open(filler, "wb", buffering=0) as out:
        try:
            while True:
                out.write(block)
        except OSError as error:
            assert error.errno == errno.ENOSPC
    with open(filler, "ab", buffering=0) as out:  # the last partial block
        with contextlib.suppress(OSError):
            while True:
                out.write(b"\0" * 512)
    return filler


@pytest.fixture
def same_as_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, rom_cache_dir: Path, rom_refinement: float
) -> Callable[[Path, Path], None]:
    """``same_as_run(fleet, db)``: asserts that ``db`` holds what ``run`` makes of ``fleet``."""

    def same_as_run(fleet: Path, db: Path) -> None:
        reference = tmp_path / "reference.duckdb"
        _reference_run(fleet, reference, monkeypatch, rom_cache_dir, rom_refinement)
        assert _views(db) == _views(reference)

    return same_as_run


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    write_registry(tmp_path / "fleet", WAGONS)
    return tmp_path / "fleet"


def test_a_full_disk_under_the_warehouse_is_said_once_and_the_files_wait_for_space(
    fleet: Path,
    tmp_path: Path,
    start: Any,
    same_as_run: Any,
) -> None:
    """The warehouse on a 48 MB ``tmpfs``, filled to its last byte after the first unit:
    DuckDB's commit gets ENOSPC from the kernel. Freeing the space lets the queued files in."""
    first, second, third = _sessions(3)
    with _tmpfs(tmp_path / "warehouse", "48m") as folder:
        db = folder / "fleet.duckdb"
        watch = start(fleet, db)
        _land(fleet, tmp_path / "stage", first[0], first[1])
        watch.wait_for({first[0]})
        filler = _fill(folder)
        _land(fleet, tmp_path / "stage", second[0], second[1])
        _land(fleet, tmp_path / "stage", third[0], third[1])
        watch.wait_until("three retries", lambda: watch.log().count("trying again in") >= 3)
        log = watch.log()
        full = f"the disk of the warehouse ({folder}) is full: the unit stops"
        assert log.count(full) == 1, log
        assert "unit failed" not in log, log
        assert not any(r.exc_info for r in watch.handler.records), "a traceback for a full disk"
        assert {o.path for o in watch.outcomes} == {first[0]}
        filler.unlink()
        watch.wait_for({second[0], third[0]})
        assert watch.log().count("units commit again") == 1
        watch.close()
        assert {o.status for o in watch.outcomes} == {"ingested"}
        same_as_run(fleet, db)


def test_a_read_only_landing_folder_is_said_once_and_landing_resumes_when_writable(
    fleet: Path,
    tmp_path: Path,
    start: Any,
    same_as_run: Any,
) -> None:
    """``logs/`` is a ``tmpfs`` remounted read-only while the service runs (a write then
    fails with EROFS, for root too), then read-write again."""
    first, second, third = _sessions(3)
    db = tmp_path / "fleet.duckdb"
    with _tmpfs(fleet / "logs", "16m") as logs:
        stage = logs / ".stage"  # hidden, and on the same filesystem (renamed from)
        _land(fleet, stage, first[0], first[1])
        _remount(logs, "ro")  # read-only from the start, one file there
        watch = start(fleet, db)
        watch.wait_for({first[0]})  # what is there is read
        read_only = f"{logs} is on a read-only filesystem: no file can land"
        watch.wait_until("the read-only sentence", lambda: read_only in watch.log())
        with pytest.raises(OSError) as refused:
            _land(fleet, stage, second[0], second[1])
        assert refused.value.errno == errno.EROFS
        watch.wait_until("two health lines", lambda: watch.log().count("health:") >= 2)
        _remount(logs, "rw")
        watch.wait_until("writable again", lambda: "writable again" in watch.log())
        _land(fleet, stage, second[0], second[1])
        _land(fleet, stage, third[0], third[1])
        watch.wait_for({second[0], third[0]})
        log = watch.log()
        assert log.count(read_only) == 1, log
        assert log.count(f"{logs} is writable again") == 1, log
        assert "unit failed" not in log, log
        watch.close()
        same_as_run(fleet, db)


def test_a_file_replaced_between_its_stat_and_its_read_is_read_again(
    fleet: Path,
    tmp_path: Path,
    start: Any,
    same_as_run: Any,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The unit's stat of the file is made, then the file is replaced (``os.replace`` of
    another session under its name) before the unit reads it: the ledger's size and time are
    the old file's, the bytes the new one's. The file is read again, and the tables are those
    of the new file."""
    (relpath, old, _), *_ = _sessions(1)
    _, new, _ = _session_bytes(WAGONS[0], 0, seed=7)
    stat_logs = ingest_files.stat_logs
    replaced: list[str] = []

    def stat_then_replace(fleet_dir: Path, relpaths: Any) -> Any:
        entries = stat_logs(fleet_dir, relpaths)
        if relpath in {e.relpath for e in entries} and not replaced:
            staged = tmp_path / "replacement.csv"
            staged.write_bytes(new)
            os.replace(staged, fleet / relpath)
            replaced.append(relpath)
        return entries

    monkeypatch.setattr(ingest_files, "stat_logs", stat_then_replace)
    db = tmp_path / "fleet.duckdb"
    watch = start(fleet, db)
    _land(fleet, tmp_path / "stage", relpath, old)
    watch.wait_for({relpath})
    watch.wait_until("the rescan after it", lambda: watch.log().count("rescan:") >= 2)
    watch.close()
    assert replaced == [relpath]
    log = watch.log()
    assert log.count(f"{relpath}: changed while it was read") == 1, log
    assert [(o.path, o.status) for o in watch.outcomes] == [(relpath, "ingested")]
    assert (fleet / relpath).read_bytes() == new
    same_as_run(fleet, db)


def test_wall_clock_jumps_neither_stall_nor_storm_the_service(
    monkeypatch: pytest.MonkeyPatch, fleet: Path, tmp_path: Path, start: Any, same_as_run: Any
) -> None:
    """``time.time`` and ``time.time_ns`` of this process jump a day forward and back every
    0.3 s (the clock of the machine cannot be set by a test): files still settle and are
    taken, and the rescans and health lines keep their monotonic periods (2 s and 1 s)."""
    real_time, real_ns = time.time, time.time_ns
    began = time.monotonic()

    def jump_s() -> float:
        return 86400.0 * (1 if int((time.monotonic() - began) / 0.3) % 2 else -1)

    monkeypatch.setattr(time, "time", lambda: real_time() + jump_s())
    monkeypatch.setattr(time, "time_ns", lambda: real_ns() + int(jump_s() * 1e9))
    first, second = _sessions(2)
    db = tmp_path / "fleet.duckdb"
    watch = start(fleet, db)
    _land(fleet, tmp_path / "stage", first[0], first[1])
    # written in place with a pause: complete when closed, or once settled
    target = fleet / second[0]
    target.parent.mkdir(parents=True, exist_ok=True)
    with open(target, "wb") as out:
        out.write(second[1][: len(second[1]) // 2])
        out.flush()
        time.sleep(0.6)
        out.write(second[1][len(second[1]) // 2 :])
    watch.wait_for({first[0], second[0]})
    time.sleep(4.0)
    elapsed = time.monotonic() - began
    watch.close()
    log = watch.log()
    assert 1 <= log.count("rescan:") <= elapsed / 2.0 + 2, log
    assert 3 <= log.count("health:") <= elapsed / 1.0 + 2, log
    assert [o.status for o in watch.outcomes] == ["ingested", "ingested"]
    monkeypatch.setattr(time, "time", real_time)
    monkeypatch.setattr(time, "time_ns", real_ns)
    same_as_run(fleet, db)
