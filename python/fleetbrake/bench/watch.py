"""``fleetbrake bench watch``: seconds from a file's landing to its flags being queryable.

What is measured, as a user would see it:

1. A synthetic fleet (:func:`fleetbrake.synth.generator.generate_fleet`, ``wagons`` x
   ``history_days + 1`` days, with the ordinary imperfections of real logs) is generated in a
   process of its own, not timed (as ``bench fleet`` generates it; ``fleet_dir`` keeps and
   reuses it). Its files of the first ``history_days`` days are the watched fleet's history,
   ingested, simulated and flagged by one ``run`` before the service starts (``history_s``).
   The sessions of its last day are cut into **one-hour session files** (the samples of each
   hour of a good session, as a unit writes them: ``logs/<wagon>/<wagon>_<first sample>.csv``,
   plain CSV), in time order: the files to drop, each on a wagon with history.
2. The service is started as a user starts it: ``fleetbrake watch FLEET --db DB --json``, a
   process of its own (with ``--engine``, ``--workers``, ``--refinement``). Once it has
   started (its start rescan done), its **idle CPU** is measured: the CPU seconds of its
   process and its worker processes over ``idle_s`` seconds with nothing landing, as a
   percentage of one core.
3. ``files`` files are dropped into ``logs/`` at a steady ``rate`` (files per minute): each is
   written under a hidden temporary name in its wagon's folder and renamed into place.
4. Another thread of this process, the **analyst**, watches the database as an analyst's
   script would: it opens the file read-only (its own DuckDB connection, in another process
   than the service; it retries while the service holds it) whenever the file changed, or
   every second, and queries ``v_files`` and ``v_flags`` (``q_bench_watch_files``).

**Latency** of a file: from the moment its rename into place returned to the moment the
analyst's query saw it **queryable**: its row is in ``v_files`` with its status
(``ingested`` or ``quarantined``). The service holds the database (one writable connection)
from the first stage of a unit (ingestion) to its last (flags) and closes it after the
commit; a read-only connection of another process can only be opened in between. So the
file's row is visible to another process only together with everything the unit that took it
wrote: the wagon's events, predictions and flags of that unit are in ``v_flags`` at the same
moment (the analyst reads the wagon's flag count in the same query). A unit that failed after
its ingestion would break this (its file visible without its flags): the service's own lines
say which files it processed (``--json``), and a file without one is counted in
``files_not_reported``.

Figures: each file's latency, p50, p95 and max (linear interpolation between order
statistics), the files, the rate, the idle CPU, the service's units (from its log: how many
stored files, and the mean seconds of each of their stages; how many stored none: the start
rescan's), the history, and the machine's CPU count and load.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleetbrake.bench import BenchConfigError, BenchError, require_extra
from fleetbrake.bench.fleet import _generate

__all__ = ["QUERYABLE", "bench_watch", "print_figures"]

QUERYABLE = (
    "its row is in v_files (ingested or quarantined), read by a read-only connection of "
    "another process; the service holds the database from a unit's ingestion to its flags, "
    "so the unit's flags are in v_flags at the same moment"
)
"""What ``queryable`` means (also in the figures)."""

_START_BOUND_S = 600.0
"""The longest the service may take to start (a first start may build the reduced model)."""
_UNIT_LINE = re.compile(r"unit: (\d+) files in ([0-9.]+) s \(([^)]*)\)")
_STAGE = re.compile(r"(\w+) ([0-9.]+) s")
_HOUR_S = 3600


@dataclass(frozen=True)
class _Drop:
    """A one-hour session file to drop: where it goes and its bytes."""

    relpath: str
    wagon_id: str
    data: bytes
    rows: int


# --------------------------------------------------------------------------------------------
# The fleet: history, and the hours to drop


def _make_fleet(
    source: Path,
    fleet: Path,
    wagons: int,
    history_days: int,
    seed: int,
    refinement: float,
) -> tuple[int, list[_Drop]]:
    """Generate ``wagons`` x ``history_days + 1`` days into ``source`` in a process of its own
    (or reuse the fleet ``source`` holds, if the same); copy the registry and the files of the
    first ``history_days`` days into ``fleet``; the last day's good sessions cut into one-hour
    files (in time order, then wagon). Returns the history's file count and the files to
    drop."""
    from fleetbrake.fleet.logfile import (
        OPTIONAL_COLUMNS,
        REQUIRED_COLUMNS,
        log_relpath,
        to_csv_bytes,
    )
    from fleetbrake.ingest.quarantine import Quarantine
    from fleetbrake.ingest.reading import read_log

    truth = _generate(source, wagons, history_days + 1, seed, refinement, False)
    config = truth.config
    cutoff = dt.datetime.combine(config.start, dt.time()) + dt.timedelta(days=history_days)
    fleet.mkdir(parents=True)
    shutil.copy2(source / "fleet.toml", fleet / "fleet.toml")
    history = 0
    drops: list[tuple[dt.datetime, str, _Drop]] = []
    for file in truth.files:
        if file.start_utc < cutoff:
            target = fleet / file.path
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source / file.path, target)
            history += 1
            continue
        if file.bad is not None or not file.registered:
            continue
        try:
            parsed = read_log((source / file.path).read_bytes(), file.path, file.start_utc)
        except Quarantine:
            continue
        frame = parsed.frame.select(
            c for c in (*REQUIRED_COLUMNS, *OPTIONAL_COLUMNS) if c in parsed.frame.columns
        )
        if frame.height == 0:
            continue
        first = frame["time_utc"].min()
        assert isinstance(first, dt.datetime)
        hour = (frame["time_utc"] - first).dt.total_seconds() // _HOUR_S
        for k in range(int(hour.max() or 0) + 1):  # type: ignore[arg-type]
            piece = frame.filter(hour == k)
            if piece.height < _HOUR_S // 2:  # the session's tail: not a one-hour file
                continue
            start = piece["time_utc"].min()
            assert isinstance(start, dt.datetime)
            start = start.replace(microsecond=0)
            relpath = log_relpath(file.wagon_id, start, gzip=False).as_posix()
            drop = _Drop(relpath, file.wagon_id, to_csv_bytes(piece), piece.height)
            drops.append((start, file.wagon_id, drop))
    drops.sort(key=lambda d: (d[0], d[1]))
    return history, [d for _, _, d in drops]


# --------------------------------------------------------------------------------------------
# The service, in a process of its own


class _Service:
    """``fleetbrake watch FLEET --db DB --json ...`` as a user starts it."""

    def __init__(self, fleet: Path, db: Path, log: Path, args: Sequence[str]) -> None:
        self.log = log
        self._stderr = log.open("wb")
        code = (
            "import sys; from fleetbrake.cli.main import main; sys.argv[0] = 'fleetbrake'; main()"
        )
        self.process = subprocess.Popen(
            [sys.executable, "-c", code, "watch", str(fleet), "--db", str(db), "--json", *args],
            stdout=subprocess.PIPE,
            stderr=self._stderr,
        )
        self.outcomes: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            with contextlib.suppress(ValueError):
                self.outcomes.append(json.loads(line))

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_ready(self, bound_s: float) -> None:
        """Until its log says the start rescan is done (the observer runs before it)."""
        deadline = time.monotonic() + bound_s
        while "rescan: " not in self.text():
            if self.process.poll() is not None:
                raise BenchError(f"bench watch: the service exited at start: {self.text()[-2000:]}")
            if time.monotonic() > deadline:
                raise BenchError(f"bench watch: the service did not start in {bound_s:g} s")
            time.sleep(0.1)

    def cpu_s(self) -> float:
        """CPU seconds of the service's process and its live worker processes."""
        import psutil

        total = 0.0
        try:
            process = psutil.Process(self.process.pid)
            for p in [process, *process.children(recursive=True)]:
                with contextlib.suppress(psutil.Error):
                    times = p.cpu_times()
                    total += times.user + times.system
        except psutil.Error:
            pass
        return total

    def stop(self, bound_s: float = 120.0) -> int | None:
        """SIGTERM (the unit in progress finishes), then its exit code; killed after
        ``bound_s``."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=bound_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=30)
        self._reader.join(timeout=10)
        self._stderr.close()
        return self.process.returncode


def _quiet(service: _Service, bound_s: float, window_s: float = 1.0) -> None:
    """Until the service and its workers used less than 5 % of a core over ``window_s``
    (they have started and imported what they run), for up to ``bound_s``."""
    deadline = time.monotonic() + bound_s
    while time.monotonic() < deadline:
        before = service.cpu_s()
        time.sleep(window_s)
        if service.cpu_s() - before < 0.05 * window_s:
            return


def _units(log: str) -> tuple[int, int, dict[str, float]]:
    """How many units the service's log reports that stored files, how many stored none (the
    start rescan's, for files quarantined for a cause retried at every run), and the mean
    seconds of each stage (``total`` included) of the former."""
    sums: dict[str, float] = {}
    count = empty = 0
    for match in _UNIT_LINE.finditer(log):
        if int(match.group(1)) == 0:
            empty += 1
            continue
        count += 1
        sums["total"] = sums.get("total", 0.0) + float(match.group(2))
        for stage, seconds in _STAGE.findall(match.group(3)):
            sums[stage] = sums.get(stage, 0.0) + float(seconds)
    return count, empty, ({k: round(v / count, 3) for k, v in sums.items()} if count else {})


# --------------------------------------------------------------------------------------------
# The analyst


class _Analyst:
    """Another connection, as an analyst's script: sees when each dropped file becomes
    queryable (see the module)."""

    def __init__(self, db: Path, poll_s: float = 0.01, every_s: float = 1.0) -> None:
        self.db = db
        self.poll_s = poll_s
        self.every_s = every_s
        self.pending: dict[str, float] = {}
        """Path -> monotonic time of its rename, until seen."""
        self.seen: dict[str, tuple[float, str, int]] = {}
        """Path -> (monotonic time seen, status, the wagon's flags then)."""
        self.queries = 0
        self.lock_waits = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def landed(self, relpath: str, at_s: float) -> None:
        with self._lock:
            self.pending[relpath] = at_s

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=30)

    def wait(self, bound_s: float) -> bool:
        """Until nothing is pending (True) or ``bound_s`` passed (False)."""
        deadline = time.monotonic() + bound_s
        while time.monotonic() < deadline:
            with self._lock:
                if not self.pending:
                    return True
            time.sleep(0.05)
        return False

    def _stat(self) -> tuple[int, int, bool]:
        try:
            stat = self.db.stat()
        except OSError:
            return (0, 0, False)
        wal = self.db.with_name(self.db.name + ".wal").exists()
        return (stat.st_mtime_ns, stat.st_size, wal)

    def _run(self) -> None:
        import duckdb

        from fleetbrake.warehouse.connection import sql

        statement = sql("q_bench_watch_files")
        last_stat: tuple[int, int, bool] | None = None
        dirty = True
        last_query = 0.0
        while not self._stop.is_set():
            with self._lock:
                paths = list(self.pending)
            stat = self._stat()
            if stat != last_stat:
                dirty = True
            if not paths or not (dirty or time.monotonic() - last_query >= self.every_s):
                self._stop.wait(self.poll_s)
                continue
            try:
                con = duckdb.connect(str(self.db), read_only=True)
            except duckdb.Error:  # held by the service (or not made yet): soon again
                self.lock_waits += 1
                self._stop.wait(self.poll_s)
                continue
            try:
                rows = con.execute(statement, {"paths": paths}).fetchall()
            finally:
                con.close()
            now = time.monotonic()
            self.queries += 1
            last_query, last_stat, dirty = now, stat, False
            with self._lock:
                for path, status, flags in rows:
                    if path in self.pending:
                        del self.pending[path]
                        self.seen[path] = (now, str(status), int(flags))


# --------------------------------------------------------------------------------------------
# The benchmark


def _percentile(values: Sequence[float], q: float) -> float | None:
    import numpy as np

    return round(float(np.percentile(values, q)), 3) if values else None


def _drop(fleet: Path, drop: _Drop) -> float:
    """Write ``drop`` under a hidden name in its folder, rename it into place; the monotonic
    time the rename returned."""
    target = fleet / drop.relpath
    target.parent.mkdir(parents=True, exist_ok=True)
    staged = target.with_name(f".{target.name}.bench.tmp")
    staged.write_bytes(drop.data)
    os.rename(staged, target)
    return time.monotonic()


@contextlib.contextmanager
def _workspace(workdir: str | Path | None) -> Iterator[Path]:
    tmp = Path(tempfile.mkdtemp(prefix="fleetbrake-bench-watch-", dir=workdir))
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def bench_watch(
    *,
    wagons: int = 4,
    history_days: int = 1,
    files: int = 20,
    rate_per_min: float = 12.0,
    seed: int = 0,
    refinement: float = 1.0,
    engine: str = "local",
    workers: int | None = None,
    idle_s: float = 10.0,
    workdir: str | Path | None = None,
    fleet_dir: str | Path | None = None,
    bound_s: float = 300.0,
    service_log: str | Path | None = None,
    echo: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the benchmark (see the module); return the figures. ``fleet_dir``: generate the
    fleet there and keep it, or reuse the one it holds. ``echo``: where each file's
    line goes (once the service has stopped). ``bound_s``: the longest wait for the last file after it
    was dropped. ``service_log``: keep the service's log (stderr) there. Needs psutil (the
    ``bench`` extra)."""
    require_extra("bench watch", "psutil")
    for name, value in (("wagons", wagons), ("history_days", history_days), ("files", files)):
        if value < 1:
            raise BenchConfigError(f"{name} must be >= 1, got {value}")
    for name, number in (("rate", rate_per_min), ("refinement", refinement), ("bound", bound_s)):
        if not number > 0:
            raise BenchConfigError(f"{name} must be > 0, got {number}")
    if not idle_s >= 0:
        raise BenchConfigError(f"idle must be >= 0 s, got {idle_s}")
    from fleetbrake.app.run import run_fleet
    from fleetbrake.engine import make_engine
    from fleetbrake.fleet.registry import WagonConfig
    from fleetbrake.model.rom import ReducedModel
    from fleetbrake.simulation.config import SimulationConfig

    make_engine(engine, workers).close()  # a bad engine or count: refused before any work
    say = echo or (lambda _line: None)
    with _workspace(workdir) as tmp:
        ReducedModel.for_wagon(WagonConfig(wagon_id="SGG-0001"), refinement=refinement)
        began = time.perf_counter()
        fleet, db = tmp / "fleet", tmp / "warehouse" / "fleet.duckdb"
        source = Path(fleet_dir) if fleet_dir is not None else tmp / "source"
        history, drops = _make_fleet(source, fleet, wagons, history_days, seed, refinement)
        generate_s = time.perf_counter() - began
        if len(drops) < files:
            raise BenchConfigError(
                f"the fleet's last day has {len(drops)} one-hour files, fewer than --files "
                f"{files}: give more --wagons"
            )
        drops = drops[:files]
        simulation = SimulationConfig(refinement=refinement)
        began = time.perf_counter()
        run_fleet(fleet, db, simulation=simulation, progress=False, engine=engine, workers=workers)
        history_s = time.perf_counter() - began

        args = ["--refinement", repr(refinement), "--engine", engine]
        if workers is not None:
            args += ["--workers", str(workers)]
        service = _Service(fleet, db, tmp / "watch.log", args)
        analyst = _Analyst(db)
        interval_s = 60.0 / rate_per_min
        try:
            service.wait_ready(_START_BOUND_S)
            _quiet(service, _START_BOUND_S)  # the workers finish importing
            cpu_before, idle_began = service.cpu_s(), time.monotonic()
            time.sleep(idle_s)
            idle_cpu = service.cpu_s() - cpu_before
            idle_wall = time.monotonic() - idle_began
            load = os.getloadavg()[0]
            analyst.start()
            landed: dict[str, float] = {}
            next_s = time.monotonic()
            for drop in drops:
                time.sleep(max(0.0, next_s - time.monotonic()))
                landed[drop.relpath] = _drop(fleet, drop)
                analyst.landed(drop.relpath, landed[drop.relpath])
                next_s += interval_s
            complete = analyst.wait(bound_s)
        finally:
            analyst.stop()
            exit_code = service.stop()
        log = service.text()
        if service_log is not None:
            Path(service_log).write_text(log)
        units, units_empty, unit_stage_s = _units(log)
        reported = {o.get("path") for o in service.outcomes}

    per_file: list[dict[str, Any]] = []
    latencies: list[float] = []
    for drop in drops:
        seen = analyst.seen.get(drop.relpath)
        latency = round(seen[0] - landed[drop.relpath], 3) if seen else None
        if latency is not None:
            latencies.append(latency)
        item = {
            "path": drop.relpath,
            "wagon": drop.wagon_id,
            "rows": drop.rows,
            "latency_s": latency,
            "status": seen[1] if seen else None,
            "wagon_flags": seen[2] if seen else None,
        }
        per_file.append(item)
        say(
            f"{drop.relpath}: "
            + (
                f"{latency:.3f} s, {item['status']}, wagon flags {item['wagon_flags']}"
                if seen
                else "not seen"
            )
        )
    return {
        "benchmark": "watch",
        "files": len(drops),
        "files_queryable": len(latencies),
        "files_not_reported": sum(1 for d in drops if d.relpath not in reported),
        "complete": complete,
        "rate_per_min": rate_per_min,
        "interval_s": round(interval_s, 3),
        "p50_s": _percentile(latencies, 50),
        "p95_s": _percentile(latencies, 95),
        "max_s": round(max(latencies), 3) if latencies else None,
        "idle_cpu_percent": round(100.0 * idle_cpu / idle_wall, 3) if idle_wall > 0 else None,
        "idle_s": round(idle_wall, 2),
        "units": units,
        "units_empty": units_empty,
        "unit_stage_s_mean": unit_stage_s,
        "per_file": per_file,
        "queryable": QUERYABLE,
        "analyst_queries": analyst.queries,
        "analyst_lock_waits": analyst.lock_waits,
        "service_exit_code": exit_code,
        "wagons": wagons,
        "history_days": history_days,
        "history_files": history,
        "history_s": round(history_s, 2),
        "generate_s": round(generate_s, 1),
        "engine": engine,
        "workers": workers,
        "refinement": refinement,
        "cpus": os.cpu_count(),
        "load_avg_1min_at_start": round(load, 2),
        "date_utc": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def print_figures(figures: dict[str, Any], echo: Callable[[str], None] = print) -> None:
    """The summary for people (each file's line is printed by :func:`bench_watch`, the JSON
    line by the caller)."""
    echo(
        f"{figures['files_queryable']} of {figures['files']} one-hour files queryable, dropped "
        f"at {figures['rate_per_min']:g} per minute on {figures['wagons']} wagons with "
        f"{figures['history_days']} day(s) of history: p50 {figures['p50_s']} s, "
        f"p95 {figures['p95_s']} s, max {figures['max_s']} s"
    )
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in figures["unit_stage_s_mean"].items())
    echo(
        f"service: {figures['units']} units that stored files (mean: {stages or 'none'}) and "
        f"{figures['units_empty']} that stored none, idle CPU "
        f"{figures['idle_cpu_percent']} % of a core over {figures['idle_s']} s, exit "
        f"{figures['service_exit_code']}; engine {figures['engine']} "
        f"(workers {figures['workers'] or 'default'}), refinement {figures['refinement']:g}; "
        f"{figures['cpus']} CPUs, load average {figures['load_avg_1min_at_start']} at start"
    )
