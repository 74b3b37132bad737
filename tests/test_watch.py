"""``fleetbrake watch``: the service in a process of its own, files landing while it runs.

Every test starts the real command (``fleetbrake watch ... --json``) with the session's
reduced model (``--refinement``, the cache in ``FLEETBRAKE_CACHE_DIR``), drops log files made
by ``tests/fleetgen.py`` into the fleet's ``logs/`` and reads the JSON line of each processed
file; every wait is bounded, and every process a test starts is stopped by it.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import pytest

from fleetbrake.app.watch.landing import LandingTracker
from fleetbrake.fleet.logfile import log_relpath, to_csv_bytes, write_log
from fleetgen import T0_UTC, make_session, write_registry

WAGONS = ["SGG-0001", "SGG-0002"]
BOUND_S = 180.0
"""The longest any wait of these tests may take (the first unit may build the reduced model)."""


# --------------------------------------------------------------------------------------------
# The landing tracker alone (no process, a fake clock)


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_tracker_takes_renamed_and_closed_files_at_once_and_settles_the_others(
    tmp_path: Path,
) -> None:
    clock = _Clock()
    wall_ns = [time.time_ns()]
    tracker = LandingTracker(tmp_path, settle_s=5.0, clock=clock, wall_clock_ns=lambda: wall_ns[0])
    logs = tmp_path / "logs" / "W"
    logs.mkdir(parents=True)
    (logs / "a.csv").write_text("x")
    (logs / "b.csv").write_text("x")
    (logs / "c.csv").write_text("x")

    tracker.writing(logs / ".a.csv.tmp")  # hidden: ignored
    tracker.writing(tmp_path / "fleet.toml")  # not under logs/: ignored
    assert len(tracker) == 0

    tracker.writing(logs / "a.csv")
    tracker.moved(tmp_path / "elsewhere.csv", logs / "b.csv")  # renamed in from outside
    tracker.writing(logs / "c.csv")
    tracker.finished(logs / "c.csv", "closed")
    tracker.refresh()
    assert [e.relpath for e in tracker.complete()] == ["logs/W/b.csv", "logs/W/c.csv"]
    assert [e.relpath for e in tracker.incomplete()] == ["logs/W/a.csv"]

    clock.now += 4.0  # unchanged, but not for settle_s yet (and its mtime is new)
    tracker.refresh()
    assert [e.relpath for e in tracker.incomplete()] == ["logs/W/a.csv"]
    (logs / "a.csv").write_text("xy")  # written again: the settling starts over
    clock.now += 2.0
    tracker.refresh()
    clock.now += 4.0
    tracker.refresh()
    assert [e.relpath for e in tracker.incomplete()] == ["logs/W/a.csv"]
    clock.now += 1.5
    tracker.refresh()
    assert tracker.incomplete() == []
    assert tracker.get("logs/W/a.csv").how == "settled"  # type: ignore[union-attr]

    # a rescan's find whose mtime is already old is settled at the second look
    (logs / "d.csv").write_text("x")
    wall_ns[0] = time.time_ns() + 10 * 10**9
    tracker.found("logs/W/d.csv")
    tracker.refresh()
    assert tracker.get("logs/W/d.csv").complete is False  # type: ignore[union-attr]
    tracker.refresh()
    assert tracker.get("logs/W/d.csv").complete is True  # type: ignore[union-attr]

    # one seen being written settles by the monotonic clock alone, whatever the wall clock
    # says of its modification time (a wall clock jumped forward makes it look old)
    (logs / "e.csv").write_text("x")
    tracker.writing(logs / "e.csv")
    for _ in range(3):
        tracker.refresh()
    assert tracker.get("logs/W/e.csv").complete is False  # type: ignore[union-attr]
    clock.now += 5.0
    tracker.refresh()
    assert tracker.get("logs/W/e.csv").complete is True  # type: ignore[union-attr]

    # taken again once written again after it was complete; forgotten when deleted
    tracker.writing(logs / "b.csv")
    assert not tracker.get("logs/W/b.csv").complete  # type: ignore[union-attr]
    tracker.gone(logs / "b.csv")
    assert tracker.get("logs/W/b.csv") is None


# --------------------------------------------------------------------------------------------
# The service in a process


def _session_bytes(wagon: str, hour: int, seed: int) -> tuple[str, bytes, int]:
    """A generated session of ``wagon`` starting ``hour`` hours after T0: its relative
    path (plain CSV), its bytes and its row count."""
    start = T0_UTC + dt.timedelta(hours=hour)
    session = make_session(np.random.default_rng(seed), start, n_events=5)
    relpath = log_relpath(wagon, start, gzip=False).as_posix()
    return relpath, to_csv_bytes(session.frame), session.frame.height


def _sessions(count: int) -> list[tuple[str, bytes, int]]:
    """``count`` sessions, alternating between the wagons, each 3 hours after the last."""
    return [_session_bytes(WAGONS[k % 2], 3 * (k // 2), seed=100 + k) for k in range(count)]


def _land(fleet: Path, stage: Path, relpath: str, data: bytes) -> None:
    """Write the file outside the fleet, then rename it into place (as a gateway does)."""
    staged = stage / relpath.replace("/", "_")
    staged.parent.mkdir(parents=True, exist_ok=True)
    staged.write_bytes(data)
    target = fleet / relpath
    target.parent.mkdir(parents=True, exist_ok=True)
    os.rename(staged, target)


class Watch:
    """A ``fleetbrake watch --json`` process: its JSON lines as they come, its log."""

    def __init__(
        self, fleet: Path, db: Path, log: Path, cache_dir: Path, refinement: float, *extra: str
    ) -> None:
        exe = Path(sys.executable).with_name("fleetbrake")
        env = {**os.environ, "FLEETBRAKE_CACHE_DIR": str(cache_dir), "RAYON_NUM_THREADS": "1"}
        self.log = log
        self._stderr = open(log, "wb")
        self.process = subprocess.Popen(
            [
                *(str(exe), "-v", "watch", str(fleet), "--db", str(db), "--json"),
                *("--refinement", str(refinement), "--settle", "2", *extra),
            ],
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            env=env,
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()
        self.outcomes: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.put(json.loads(line))

    def wait_started(self) -> None:
        """Until the observer is running (its log says so)."""
        deadline = time.monotonic() + BOUND_S
        while b"watching " not in self.log.read_bytes():
            assert self.process.poll() is None, self.log.read_text()
            assert time.monotonic() < deadline, "the service did not start"
            time.sleep(0.1)

    def wait_for(self, paths: set[str]) -> list[dict[str, Any]]:
        """Until every path in ``paths`` has its outcome line; all lines so far."""
        deadline = time.monotonic() + BOUND_S
        while not paths <= {o["path"] for o in self.outcomes}:
            try:
                self.outcomes.append(self.lines.get(timeout=0.5))
            except queue.Empty:
                assert self.process.poll() is None, self.log.read_text()
                assert time.monotonic() < deadline, (
                    f"waited {BOUND_S} s for {paths}: {self.log.read_text()}"
                )
        return self.outcomes

    def terminate(self) -> int:
        """SIGTERM, then its exit code (bounded); the lines it wrote until then are kept."""
        self.process.send_signal(signal.SIGTERM)
        code = self.process.wait(timeout=BOUND_S)
        self._reader.join(timeout=10)
        while not self.lines.empty():
            self.outcomes.append(self.lines.get())
        return code

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=30)
        self._stderr.close()


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    path = tmp_path / "fleet"
    write_registry(path, WAGONS)
    (path / "logs").mkdir()
    return path


@pytest.fixture
def start_watch(tmp_path: Path, rom_cache_dir: Path, rom_refinement: float) -> Iterator[Any]:
    started: list[Watch] = []

    def start(fleet: Path, db: Path, *extra: str) -> Watch:
        watch = Watch(
            fleet, db, tmp_path / f"watch{len(started)}.log", rom_cache_dir, rom_refinement, *extra
        )
        started.append(watch)
        watch.wait_started()
        return watch

    yield start
    for watch in started:
        watch.stop()


def _reference_run(
    fleet: Path, db: Path, monkeypatch: pytest.MonkeyPatch, cache_dir: Path, refinement: float
) -> Any:
    """``run_fleet`` in this process over ``fleet`` into ``db`` (the session's model)."""
    from fleetbrake.app.run import run_fleet
    from fleetbrake.simulation.config import SimulationConfig

    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(cache_dir))
    return run_fleet(fleet, db, simulation=SimulationConfig(refinement=refinement), progress=False)


def _views(db: Path) -> dict[str, list[tuple[Any, ...]]]:
    """What the public views hold, without the columns that tell when it was written."""
    queries = {
        "files": "SELECT path, wagon_id, status, rows, reason FROM v_files",
        "events": "SELECT * FROM v_events",
        "flags": "SELECT wagon_id, event_id, kind, severity, start_utc, end_utc, evidence "
        "FROM v_flags",
        "predictions": "SELECT event_id, time_utc, model_revision, "
        "round(predicted_sensor_c, 6) FROM v_predictions",
    }
    con = duckdb.connect(str(db), read_only=True)
    try:
        return {name: sorted(con.execute(q).fetchall(), key=repr) for name, q in queries.items()}
    finally:
        con.close()


def test_files_renamed_into_place_are_ingested_and_flagged_as_run_would(
    fleet: Path,
    tmp_path: Path,
    start_watch: Any,
    monkeypatch: pytest.MonkeyPatch,
    rom_cache_dir: Path,
    rom_refinement: float,
) -> None:
    """Files renamed into ``logs/`` (from outside the tree, and through ``write_log``'s hidden
    temporary name inside it) while the service runs: each is processed once, in units, and
    the views end up as one ``run`` over the same files makes them, flags included."""
    db = tmp_path / "wh" / "fleet.duckdb"
    watch = start_watch(fleet, db)
    sessions = _sessions(4)
    for k, (relpath, data, _) in enumerate(sessions):
        if k % 2:
            write_log(fleet / relpath, data)  # hidden temporary name, renamed within logs/
        else:
            _land(fleet, tmp_path / "stage", relpath, data)
        if k == 1:
            watch.wait_for({sessions[0][0], sessions[1][0]})  # a second unit for the rest
    outcomes = watch.wait_for({relpath for relpath, _, _ in sessions})
    assert watch.terminate() == 0

    assert sorted(o["path"] for o in outcomes) == sorted(r for r, _, _ in sessions)
    for outcome, (relpath, _, rows) in zip(
        sorted(outcomes, key=lambda o: o["path"]), sorted(sessions), strict=True
    ):
        assert outcome["path"] == relpath
        assert outcome["status"] == "ingested"
        assert outcome["rows"] == rows
        assert outcome["wagon"] == relpath.split("/")[1]
        assert outcome["seconds"] >= 0

    reference = tmp_path / "reference.duckdb"
    _reference_run(fleet, reference, monkeypatch, rom_cache_dir, rom_refinement)
    watched, expected = _views(db), _views(reference)
    assert expected["flags"], "the generated sessions raise no flag: the test shows nothing"
    assert watched == expected
    # the last unit's line counts its wagon's flags as they stayed (an earlier unit's line
    # counts them as they were then: a wagon's flags may move with the fleet's later data)
    last = outcomes[-1]
    assert sum(last["flags"].values()) == sum(1 for f in expected["flags"] if f[0] == last["wagon"])


def test_a_file_written_slowly_is_taken_only_once_complete(
    fleet: Path, tmp_path: Path, start_watch: Any
) -> None:
    """A file written in place, in bursts 0.5 s apart for about 5 s (longer than --settle), is
    taken once it is closed, whole; meanwhile another file renamed into place is taken by a
    unit of its own (a unit reads exactly the files handed to it, never the half-written
    one). Both observers; with the polling one, the start rescan's unit (the first round's
    files) runs while the slow file is being written: it is not read then, and its one
    outcome line and its stored rows are the whole file's."""
    for observer in ("inotify", "poll"):
        db = tmp_path / f"{observer}.duckdb"
        extra = ("--poll", "0.3") if observer == "poll" else ()
        watch = start_watch(fleet, db, *extra)
        hour = 0 if observer == "inotify" else 12
        slow, data, rows = _session_bytes(WAGONS[0], hour, seed=7)
        other, other_data, _ = _session_bytes(WAGONS[1], hour, seed=8)
        target = fleet / slow
        target.parent.mkdir(parents=True, exist_ok=True)
        chunks = [
            data[i : i + len(data) // 10 + 1] for i in range(0, len(data), len(data) // 10 + 1)
        ]
        with open(target, "wb") as handle:
            for k, chunk in enumerate(chunks):
                handle.write(chunk)
                handle.flush()
                if k == 2:
                    _land(fleet, tmp_path / "stage", other, other_data)
                time.sleep(0.5)
        outcomes = watch.wait_for({slow, other})
        assert watch.terminate() == 0
        taken = [o for o in outcomes if o["path"] == slow]
        assert len(taken) == 1, outcomes
        # never handed to a unit while it was written: never read half-written
        assert "changed while it was read" not in watch.log.read_text()
        assert taken[0]["rows"] == rows
        con = duckdb.connect(str(db), read_only=True)
        try:
            stored = con.execute("SELECT rows FROM v_files WHERE path = $p", {"p": slow}).fetchall()
        finally:
            con.close()
        assert stored == [(rows,)]


def test_files_that_landed_while_down_are_taken_by_the_start_rescan(
    fleet: Path,
    tmp_path: Path,
    start_watch: Any,
    monkeypatch: pytest.MonkeyPatch,
    rom_cache_dir: Path,
    rom_refinement: float,
) -> None:
    """One file was ingested by an earlier ``run``; two more landed while no service ran
    (no event seen by anyone), and a bad one: the start rescan takes exactly the new ones,
    the bad one quarantined as ``run`` does, and the service goes on."""
    db = tmp_path / "fleet.duckdb"
    sessions = _sessions(3)
    _land(fleet, tmp_path / "stage", sessions[0][0], sessions[0][1])
    _reference_run(fleet, db, monkeypatch, rom_cache_dir, rom_refinement)
    for relpath, data, _ in sessions[1:]:
        _land(fleet, tmp_path / "stage", relpath, data)
    bad = "logs/SGG-0001/SGG-0001_20240302T060000Z.csv"
    (fleet / bad).write_bytes(b"not,a,log\n1,2,3\n")
    past = time.time() - 3600
    for relpath in [*(r for r, _, _ in sessions[1:]), bad]:
        os.utime(fleet / relpath, (past, past))

    watch = start_watch(fleet, db)
    new = {sessions[1][0], sessions[2][0], bad}
    outcomes = watch.wait_for(new)
    late, late_data, _ = _session_bytes(WAGONS[1], 30, seed=9)  # the service goes on
    _land(fleet, tmp_path / "stage", late, late_data)
    outcomes = watch.wait_for(new | {late})
    assert watch.terminate() == 0
    assert sorted(o["path"] for o in outcomes) == sorted(new | {late})
    status = {o["path"]: o["status"] for o in outcomes}
    assert status.pop(bad) == "quarantined"
    assert set(status.values()) == {"ingested"}


READER = r"""
import json, sys, time
import duckdb
db, seconds, bound = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
queries = waits = 0
longest = 0.0
end = time.monotonic() + seconds
while time.monotonic() < end:
    began = time.monotonic()
    while True:  # the bounded retry of docs/operations.md
        try:
            con = duckdb.connect(db, read_only=True)
            break
        except duckdb.IOException as error:
            if "lock" not in str(error).lower() or time.monotonic() - began > bound:
                raise
            waits += 1
            time.sleep(0.05)
    longest = max(longest, time.monotonic() - began)
    try:
        con.execute("SELECT count(*) FROM v_flags").fetchall()
        con.execute("SELECT wagon_id, count(*) FROM v_events GROUP BY wagon_id").fetchall()
        queries += 1
    finally:
        con.close()
    time.sleep(0.1)
print(json.dumps({"queries": queries, "waits": waits, "longest_s": longest}))
"""


def test_readers_in_another_process_query_the_views_while_files_land(
    fleet: Path, tmp_path: Path, start_watch: Any
) -> None:
    """Two reader processes open the database read-only again and again and query
    ``v_flags`` and ``v_events`` while files keep landing: no reader waits longer than its
    bounded retry (it fails if it does), and the service, waiting for them in turn, processes
    every file."""
    db = tmp_path / "fleet.duckdb"
    sessions = _sessions(6)
    _land(fleet, tmp_path / "stage", sessions[0][0], sessions[0][1])
    watch = start_watch(fleet, db)
    watch.wait_for({sessions[0][0]})  # the database exists, the model is built
    bound_s = 30.0
    readers = [
        subprocess.Popen(
            [sys.executable, "-c", READER, str(db), "20", str(bound_s)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        for _ in range(2)
    ]
    try:
        for relpath, data, _ in sessions[1:]:
            _land(fleet, tmp_path / "stage", relpath, data)
            time.sleep(2.0)
        results = [reader.communicate(timeout=BOUND_S) for reader in readers]
    finally:
        for reader in readers:
            if reader.poll() is None:
                reader.kill()
                reader.wait(timeout=30)
    for reader, (out, err) in zip(readers, results, strict=True):
        assert reader.returncode == 0, err.decode()
        stats = json.loads(out)
        assert stats["queries"] > 10
        assert stats["longest_s"] <= bound_s
    outcomes = watch.wait_for({relpath for relpath, _, _ in sessions})
    assert watch.terminate() == 0
    assert {o["status"] for o in outcomes} == {"ingested"}
    assert "unit failed" not in watch.log.read_text()


def test_sigterm_mid_stream_exits_0_and_leaves_a_consistent_database(
    fleet: Path,
    tmp_path: Path,
    start_watch: Any,
    monkeypatch: pytest.MonkeyPatch,
    rom_cache_dir: Path,
    rom_refinement: float,
) -> None:
    """Files keep landing; SIGTERM once the first is processed: exit 0, and a ``run`` over
    the directory afterwards takes exactly the files the service had not processed, ending
    where one ``run`` over everything ends."""
    db = tmp_path / "fleet.duckdb"
    sessions = _sessions(8)
    watch = start_watch(fleet, db)
    landed: list[str] = []
    stop_at = None
    for relpath, data, _ in sessions:
        _land(fleet, tmp_path / "stage", relpath, data)
        landed.append(relpath)
        if len(landed) == 2:
            watch.wait_for({landed[0]})
            watch.process.send_signal(signal.SIGTERM)
            stop_at = time.monotonic()
        time.sleep(0.1)
    assert stop_at is not None
    code = watch.process.wait(timeout=BOUND_S)
    assert code == 0, watch.log.read_text()
    watch.terminate()  # collects the last lines (the process has exited)
    processed = {o["path"] for o in watch.outcomes}
    assert landed[0] in processed
    assert processed < set(landed)

    after = _reference_run(fleet, db, monkeypatch, rom_cache_dir, rom_refinement)
    assert {r.path for r in after.ingest.results} == set(landed) - processed
    reference = tmp_path / "reference.duckdb"
    _reference_run(fleet, reference, monkeypatch, rom_cache_dir, rom_refinement)
    assert _views(db) == _views(reference)


def test_a_touched_file_is_looked_at_once_not_at_every_rescan(
    fleet: Path,
    tmp_path: Path,
    start_watch: Any,
    monkeypatch: pytest.MonkeyPatch,
    rom_cache_dir: Path,
    rom_refinement: float,
) -> None:
    """A file ingested by a ``run`` and then touched (same bytes, new mtime): the start
    rescan finds it, one unit reads it, finds its bytes unchanged and refreshes its ledger
    row; every later rescan finds nothing (before, each rescan found it and ran a unit for
    it). Nothing is stored again, and no outcome line is written for it."""
    db = tmp_path / "fleet.duckdb"
    relpath, data, _ = _sessions(1)[0]
    _land(fleet, tmp_path / "stage", relpath, data)
    _reference_run(fleet, db, monkeypatch, rom_cache_dir, rom_refinement)
    before = _views(db)
    later = time.time() + 60
    os.utime(fleet / relpath, (later, later))

    watch = start_watch(fleet, db, "--rescan", "0.5")

    def lines() -> list[str]:
        return watch.log.read_text().splitlines()

    def wait_until(done: Any) -> None:
        deadline = time.monotonic() + BOUND_S
        while not done():
            assert watch.process.poll() is None, watch.log.read_text()
            assert time.monotonic() < deadline, watch.log.read_text()
            time.sleep(0.2)

    wait_until(lambda: any("unit: " in line for line in lines()))  # it settled, was read
    unit = next(k for k, line in enumerate(lines()) if "unit: " in line)
    wait_until(lambda: sum("rescan: " in line for line in lines()[unit:]) >= 3)
    assert watch.terminate() == 0
    rescans = [line for line in lines() if "rescan: " in line]
    assert "rescan: 1 files not in the ledger" in rescans[0]
    after = [line for line in lines()[unit:] if "rescan: " in line]
    assert all("rescan: 0 files not in the ledger" in line for line in after), after
    assert sum("unit: " in line for line in lines()) == 1
    assert watch.outcomes == []
    assert _views(db) == before


def test_exit_1_when_the_fleet_directory_is_missing_or_goes_away(
    fleet: Path, tmp_path: Path, start_watch: Any
) -> None:
    exe = Path(sys.executable).with_name("fleetbrake")
    missing = subprocess.run(
        [str(exe), "watch", str(tmp_path / "nowhere"), "--db", str(tmp_path / "x.duckdb")],
        capture_output=True,
        timeout=60,
    )
    assert missing.returncode == 1
    assert b"nowhere" in missing.stderr

    watch = start_watch(fleet, tmp_path / "fleet.duckdb")
    shutil.rmtree(fleet)
    assert watch.process.wait(timeout=60) == 1
    assert "gone" in watch.log.read_text()


def test_an_invalid_registry_is_logged_once_and_the_service_keeps_running(
    fleet: Path, tmp_path: Path, start_watch: Any
) -> None:
    db = tmp_path / "fleet.duckdb"
    (first, second, third) = _sessions(3)
    watch = start_watch(fleet, db)
    _land(fleet, tmp_path / "stage", first[0], first[1])
    watch.wait_for({first[0]})
    registry = fleet / "fleet.toml"
    good = registry.read_text(encoding="utf-8")
    entry = f'id = "{WAGONS[0]}"\n'
    registry.write_text(good.replace(entry, entry + "cylinder_diameter_m = -0.254\n"))
    _land(fleet, tmp_path / "stage", second[0], second[1])
    refused = "the registry cannot be used"
    deadline = time.monotonic() + BOUND_S
    while watch.log.read_text().split(refused)[-1].count("trying again in") < 2:
        assert watch.process.poll() is None, watch.log.read_text()
        assert time.monotonic() < deadline, watch.log.read_text()
        time.sleep(0.2)
    log = watch.log.read_text()
    assert log.count(refused) == 1, log  # once, though the unit was tried again
    assert f"wagon {WAGONS[0]}, key cylinder_diameter_m: must be a number in [0.1, 0.6] m" in log
    assert second[0] not in {o["path"] for o in watch.outcomes}
    registry.write_text(good)  # fixed: the queued file is taken, and the next one
    _land(fleet, tmp_path / "stage", third[0], third[1])
    outcomes = watch.wait_for({second[0], third[0]})
    assert {o["status"] for o in outcomes} == {"ingested"}
    assert "the registry is accepted again" in watch.log.read_text()
    assert watch.terminate() == 0
