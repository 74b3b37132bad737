"""The watching service: files that land complete in ``<fleet>/logs`` go through ``run``.

::

    stop = threading.Event()            # set it (e.g. from a SIGTERM handler) to stop
    report = watch_fleet("fleet", "warehouse/fleet.duckdb", WatchConfig(), stop, on_file=print)

One loop, on the calling thread:

* a watchdog observer on ``logs/`` (inotify; with ``poll_s`` the polling observer, for network
  filesystems where inotify sees nothing) queues what happens to files and wakes the loop; the
  :class:`~fleetbrake.app.watch.landing.LandingTracker` decides which are complete;
* a **rescan** at start and every ``rescan_s``: every file under ``logs/`` whose path, size or
  modification time the ingestion ledger does not hold is a candidate (events are lost while
  the service is down, or when the kernel's queue overflows);
* a **unit** of work: as soon as some files are complete, one
  :func:`fleetbrake.app.run.run_fleet` restricted to exactly those files (``files=``; a file
  still being written, or landing during the unit, is not read by it), otherwise exactly what
  ``fleetbrake run`` does (only the wagons they touch are simulated and flagged; quarantine,
  late files, idempotence and the one-writer lock as there). The database is open only during
  the unit, so that read-only connections of other processes (analysts' SQL) get in between;
  when one holds the file, the unit is retried for up to ``wait_s`` seconds;
* the **engine** (``engine``/``workers``) is made and its workers started when the service
  starts, and kept for every unit until it stops;
* **stop** (the event set): the unit in progress finishes and commits, then the loop returns;
* a **health line** every ``health_s`` (files processed, queue, last error), at info level;
* for each file a unit processed, :class:`FileOutcome` to ``on_file``.

An error in one unit is logged once, as a sentence of :mod:`.faults` (not at every retry), and
the service goes on: the unit stops, its files stay queued and are tried again after a
pause, until the fault clears (a full disk under the warehouse, a registry being edited).
``logs/`` turning read-only is said once too (the files already there are still read);
:class:`WatchError` (exit 1) only when it cannot do its job at all: the
fleet directory is gone, or the observer cannot watch.
"""

from __future__ import annotations

import logging
import os
import queue
import random
import threading
import time
from collections import Counter
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from watchdog.events import (
    DirDeletedEvent,
    DirMovedEvent,
    FileClosedEvent,
    FileCreatedEvent,
    FileDeletedEvent,
    FileModifiedEvent,
    FileMovedEvent,
    FileSystemEvent,
    FileSystemEventHandler,
)

from fleetbrake.app.watch.faults import UnitFault, unit_fault
from fleetbrake.app.watch.landing import LOGS_DIR, LandingTracker
from fleetbrake.errors import DatabaseLockedError, FleetbrakeError

if TYPE_CHECKING:
    from watchdog.observers.api import BaseObserver

    from fleetbrake.app.run import RunReport
    from fleetbrake.engine import Engine
    from fleetbrake.ingest.ledger import FileResult
    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.viz.live import LiveTimelines

__all__ = ["FileOutcome", "WatchConfig", "WatchError", "WatchReport", "watch_fleet"]

logger = logging.getLogger(__name__)


class WatchError(FleetbrakeError):
    """The service cannot do its job at all (exit 1): the message names the directory."""


@dataclass(frozen=True)
class WatchConfig:
    """How the service watches; every duration in seconds.

    Read by: ``fleetbrake watch``.
    """

    poll_s: float | None = None
    """None: the platform's native observer (inotify); else poll the tree every ``poll_s``."""
    settle_s: float = 5.0
    """A file neither renamed into place nor seen closed is complete once its size and
    modification time stayed the same this long."""
    rescan_s: float = 300.0
    """Full rescan of ``logs/`` against the ingestion ledger this often (and at start)."""
    wait_s: float = 30.0
    """A unit waits up to this long for the database (another writer, or readers holding it)
    before it is given up and tried again later."""
    retry_s: float = 5.0
    """Pause after a failed unit before its files are tried again (doubling, up to
    ``rescan_s``)."""
    health_s: float = 60.0
    """A health line in the log this often."""
    tick_s: float = 0.25
    """The loop's period: how often settling files are looked at (an observer's event wakes
    the loop at once), and how soon a stop is seen between units."""
    simulation: SimulationConfig | None = None
    """As ``run``'s (None: its defaults)."""
    flag_config_path: Path | None = None
    """As ``run --flag-config``."""
    engine: str = "local"
    """Where each unit's partitions run (``fleetbrake.engine.make_engine``'s names)."""
    workers: int | None = None
    """Worker processes of the local engine, kept for the service's life (None: the cores;
    1: in the service's own process)."""
    address: str | None = None
    """The Ray cluster of ``engine="ray"`` (None: a local one)."""
    rerun: str | None = None
    """A rerun viewer (``HOST:PORT`` or ``rerun+http://HOST:PORT/proxy``) each unit's new
    timelines are streamed to (:mod:`fleetbrake.viz.live`); None: none."""

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.poll_s is not None and not self.poll_s > 0:
            raise ValueError(f"poll_s must be > 0 s, got {self.poll_s}")
        for name in ("rescan_s", "retry_s", "health_s", "tick_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0 s, got {getattr(self, name)}")
        for name in ("settle_s", "wait_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0 s, got {getattr(self, name)}")


@dataclass(frozen=True)
class FileOutcome:
    """What a unit did with one file (a ``--json`` line of ``fleetbrake watch``)."""

    path: str
    """Relative to the fleet directory, as ``v_files.path``."""
    wagon: str | None
    status: str
    """``ingested`` or ``quarantined``."""
    seconds: float
    """From the service first seeing the file to the unit's commit."""
    flags: dict[str, int]
    """The wagon's flags after the unit, counted by kind."""
    rows: int = 0
    reason: str | None = None
    """Why it was quarantined."""

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "path": self.path,
            "wagon": self.wagon,
            "status": self.status,
            "seconds": round(self.seconds, 3),
            "flags": self.flags,
            "rows": self.rows,
        }
        if self.reason is not None:
            out["reason"] = self.reason
        return out


@dataclass
class WatchReport:
    """What the service did until it stopped."""

    files_ingested: int = 0
    files_quarantined: int = 0
    units: int = 0
    units_failed: int = 0
    last_error: str | None = None
    seconds: float = 0.0

    @property
    def files_processed(self) -> int:
        return self.files_ingested + self.files_quarantined

    def line(self) -> str:
        return (
            f"{self.files_processed} files processed ({self.files_quarantined} quarantined) "
            f"in {self.units} units, {self.units_failed} failed, "
            f"last error: {self.last_error or 'none'}"
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "command": "watch",
            "files": {"ingested": self.files_ingested, "quarantined": self.files_quarantined},
            "units": self.units,
            "units_failed": self.units_failed,
            "last_error": self.last_error,
            "seconds": round(self.seconds, 3),
        }


# --------------------------------------------------------------------------------------------
# The observer


class _Queued(FileSystemEventHandler):
    """Puts the observer's file events on a queue for the service's loop, and wakes it."""

    def __init__(self, events: queue.SimpleQueue[FileSystemEvent], wake: threading.Event) -> None:
        self._events = events
        self._wake = wake

    def on_any_event(self, event: FileSystemEvent) -> None:
        if isinstance(
            event,
            FileCreatedEvent
            | FileModifiedEvent
            | FileClosedEvent
            | FileMovedEvent
            | FileDeletedEvent
            | DirDeletedEvent
            | DirMovedEvent,
        ):
            self._events.put(event)
            self._wake.set()


def _observer(poll_s: float | None) -> BaseObserver:
    if poll_s is not None:
        from watchdog.observers.polling import PollingObserver

        return PollingObserver(timeout=poll_s)
    try:
        from watchdog.observers.inotify import InotifyObserver
    except ImportError:  # not Linux: the platform's own
        from watchdog.observers import Observer

        return Observer()
    # full events: a file renamed in from outside the tree is a move, not a creation
    return InotifyObserver(generate_full_events=True)


def _path(value: bytes | str) -> str:
    return value.decode() if isinstance(value, bytes) else value


def _apply(tracker: LandingTracker, event: FileSystemEvent) -> None:
    src = _path(event.src_path)
    if isinstance(event, FileMovedEvent | DirMovedEvent):
        if isinstance(event, FileMovedEvent):
            tracker.moved(src, _path(event.dest_path))
        # a directory's moves come with one event per file in it (watchdog generates them)
    elif isinstance(event, FileClosedEvent):
        tracker.finished(src, "closed")
    elif isinstance(event, FileCreatedEvent | FileModifiedEvent):
        tracker.writing(src)
    elif isinstance(event, FileDeletedEvent):
        tracker.gone(src)


# --------------------------------------------------------------------------------------------
# The service


def _ledger(db_path: Path, wait_s: float) -> dict[str, tuple[int, int]] | None:
    """Path -> (size, mtime_ns) of the files the ingestion ledger holds for good (those
    quarantined for a cause judged again at every run are left out, as every unit retries
    them); ``{}`` without a database, None when it could not be read within ``wait_s``."""
    if not db_path.exists():
        return {}
    rows = _query(db_path, wait_s, "q_ingest_known_files")
    if rows is None:
        return None
    retried = {"registry", "unreadable", "error"}
    # columns: path, file_id, sha256, size_bytes, mtime_ns, status, quarantine_code, ...
    return {row[0]: (int(row[3]), int(row[4])) for row in rows if row[6] not in retried}


def _query(
    db_path: Path, wait_s: float, name: str, params: dict[str, object] | None = None
) -> list[tuple[Any, ...]] | None:
    """The rows of the packaged query ``name`` on a read-only connection (held for the query
    only), retried while the database is held; None when it stayed held ``wait_s``."""
    from fleetbrake.warehouse.connection import open_warehouse, sql

    deadline = time.monotonic() + wait_s
    while True:
        try:
            with open_warehouse(db_path, read_only=True) as wh:
                return wh.con.execute(sql(name), params or {}).fetchall()
        except DatabaseLockedError:
            if time.monotonic() >= deadline:
                return None
            time.sleep(random.uniform(0.1, 0.5))


class _Service:
    def __init__(
        self,
        fleet_dir: Path,
        db_path: Path,
        config: WatchConfig,
        stop: threading.Event,
        on_file: Callable[[FileOutcome], None] | None,
    ) -> None:
        self.fleet_dir = fleet_dir
        self.db_path = db_path
        self.config = config
        self.stop = stop
        self.on_file = on_file
        self.tracker = LandingTracker(fleet_dir, config.settle_s)
        self.events: queue.SimpleQueue[FileSystemEvent] = queue.SimpleQueue()
        self.wake = threading.Event()
        """Set by the observer's thread with each event: the loop looks at once (a file
        renamed into place goes to a unit without waiting for the next tick)."""
        self.report = WatchReport()
        self.began = time.monotonic()
        self.next_rescan = 0.0  # at once
        self.next_health = self.began + config.health_s
        self.next_unit = 0.0
        self.pause_s = config.retry_s
        self._engine: Engine | None = None
        self.live: LiveTimelines | None = None
        """The live viewer of ``config.rerun``, from the service's start."""
        self.retaken: set[str] = set()
        """Files a unit read while they were still being written (see :meth:`_unit`)."""
        self.fault: UnitFault | None = None
        """Why the last unit failed (logged once, until it changes or a unit commits)."""
        self.landing_read_only = False
        """Whether ``logs/`` was on a read-only filesystem at the last step."""

    def engine(self) -> Engine:
        """The engine every unit runs on, made at the service's start (its workers started
        then, importing the stages' modules, while the service waits for the first file) and
        kept for every unit, not started at each; remade after a unit that failed on it."""
        from fleetbrake.app.run import STAGE_MODULES
        from fleetbrake.engine import make_engine

        if self._engine is None:
            self._engine = make_engine(
                self.config.engine,
                self.config.workers,
                preload=STAGE_MODULES,
                address=self.config.address,
            )
            self._engine.start()
        return self._engine

    def _close_engine(self) -> None:
        if self._engine is not None:
            engine, self._engine = self._engine, None
            engine.close()

    # ---- the loop ------------------------------------------------------------------------

    def run(self) -> WatchReport:
        logs = self.fleet_dir / LOGS_DIR
        try:
            logs.mkdir(exist_ok=True)
        except OSError as error:
            raise WatchError(f"{logs}: cannot make the landing folder ({error})") from None
        import fleetbrake.app.run  # noqa: F401  (the units' code, imported before the first file)

        self.engine()  # the workers start while nothing has landed yet
        if self.config.rerun is not None:
            from fleetbrake.viz.live import LiveTimelines

            self.live = LiveTimelines(self.config.rerun)
        observer = _observer(self.config.poll_s)
        observer.schedule(_Queued(self.events, self.wake), str(logs), recursive=True)
        try:
            observer.start()
        except OSError as error:
            raise WatchError(
                f"{logs}: cannot watch ({error}); raise fs.inotify.max_user_watches or use --poll"
            ) from None
        how = f"polling every {self.config.poll_s:g} s" if self.config.poll_s else "inotify"
        logger.info("watching %s (%s), database %s", logs, how, self.db_path)
        try:
            while not self.stop.is_set():
                self.wake.clear()
                self._step(observer)
                self.wake.wait(self.config.tick_s)  # a stop is seen within a tick
        finally:
            observer.stop()
            observer.join(timeout=5.0)
            self._close_engine()
            if self.live is not None:
                self.live.close()
            self.report.seconds = time.monotonic() - self.began
        logger.info("watch stopped: %s", self.report.line())
        return self.report

    def _step(self, observer: BaseObserver) -> None:
        if not self.fleet_dir.is_dir() or not (self.fleet_dir / LOGS_DIR).is_dir():
            raise WatchError(f"{self.fleet_dir}: the fleet directory (or its logs/) is gone")
        if not observer.is_alive():
            raise WatchError(f"{self.fleet_dir / LOGS_DIR}: the observer stopped")
        self._landing_writable()
        self._drain()
        now = time.monotonic()
        if now >= self.next_rescan:
            self._rescan()
        self.tracker.refresh()
        if self.tracker.complete() and now >= self.next_unit:
            self._unit()
        if time.monotonic() >= self.next_health:
            self._health()

    def _drain(self) -> None:
        while True:
            try:
                _apply(self.tracker, self.events.get_nowait())
            except queue.Empty:
                return

    def _changed_since_read(self, results: list[FileResult]) -> set[str]:
        """The paths of ``results`` whose size or modification time is no longer what the
        ledger recorded when the unit read them (still being written then)."""
        changed: set[str] = set()
        for result in results:
            try:
                stat = (self.fleet_dir / result.path).stat()
            except OSError:
                continue  # gone: nothing to take again
            if (result.size_bytes, result.mtime_ns) != (stat.st_size, stat.st_mtime_ns):
                changed.add(result.path)
        return changed

    def _stored_outcome(self, relpath: str, seconds: float) -> None:
        """The outcome of a file taken again whose bytes had been read whole already (the
        unit found it unchanged), from what the warehouse holds of it."""
        try:
            rows = _query(
                self.db_path, self.config.wait_s, "q_watch_stored_file", {"path": relpath}
            )
        except FleetbrakeError as error:
            logger.warning("%s: cannot read its outcome: %s", relpath, error)
            return
        if not rows:
            return
        wagon, status, count, reason, flags = rows[0]
        if status == "quarantined":
            self.report.files_quarantined += 1
        else:
            self.report.files_ingested += 1
        if self.on_file is not None:
            self.on_file(
                FileOutcome(
                    path=relpath,
                    wagon=wagon,
                    status=status,
                    seconds=seconds,
                    flags={item["kind"]: int(item["n"]) for item in flags or []},
                    rows=int(count or 0),
                    reason=reason,
                )
            )

    def _health(self) -> None:
        ready, writing = self.tracker.complete(), self.tracker.incomplete()
        logger.info(
            "health: %d files processed (%d quarantined), %d units (%d failed), queue %d "
            "(%d being written), last error: %s",
            self.report.files_processed,
            self.report.files_quarantined,
            self.report.units,
            self.report.units_failed,
            len(ready) + len(writing),
            len(writing),
            self.report.last_error or "none",
        )
        self.next_health = time.monotonic() + self.config.health_s

    def _rescan(self) -> None:
        from fleetbrake.ingest.scan import scan_logs

        try:
            ledger = _ledger(self.db_path, self.config.wait_s)
        except FleetbrakeError as error:  # e.g. a database of a newer schema: the unit says so
            logger.error("rescan: %s", error)
            self.report.last_error = f"{type(error).__name__}: {error}"
            ledger = None
        if ledger is None:
            logger.warning(
                "rescan: %s not readable for %g s; trying again in %g s",
                self.db_path,
                self.config.wait_s,
                self.config.retry_s,
            )
            self.next_rescan = time.monotonic() + self.config.retry_s
            return
        found = 0
        for entry in scan_logs(self.fleet_dir):
            if ledger.get(entry.relpath) != (entry.size_bytes, entry.mtime_ns):
                if self.tracker.get(entry.relpath) is None:
                    found += 1
                self.tracker.found(entry.relpath)
        logger.info("rescan: %d files not in the ledger", found)
        self.next_rescan = time.monotonic() + self.config.rescan_s

    # ---- a unit --------------------------------------------------------------------------

    def _run_fleet(self, files: Collection[str]) -> RunReport | None:
        """One ``run_fleet`` over exactly ``files`` (a file that lands meanwhile waits for
        the next unit), retried while the database is held (for up to ``wait_s``; the first
        retries soon, as a reader's query is short); None when stopped while waiting
        (nothing was written)."""
        from fleetbrake.app.run import run_fleet

        deadline = time.monotonic() + self.config.wait_s
        pause_s = 0.02
        while True:
            try:
                return run_fleet(
                    self.fleet_dir,
                    self.db_path,
                    wait_s=max(0.0, deadline - time.monotonic()),
                    simulation=self.config.simulation,
                    flag_config_path=self.config.flag_config_path,
                    progress=False,
                    engine=self.engine(),
                    files=files,
                )
            except DatabaseLockedError:
                if time.monotonic() >= deadline:
                    raise
                logger.debug("%s is held by another process; trying again", self.db_path)
            if self.stop.wait(random.uniform(pause_s, 2 * pause_s)):
                return None
            pause_s = min(2 * pause_s, 0.25)

    def _failed(self, error: Exception, queued: int) -> None:
        """A failed unit said once per distinct fault (the service tries again with backoff,
        and the files stay queued until the fault clears); repeats go to the debug log."""
        fault = unit_fault(error, self.db_path, queued)
        if fault.key == (self.fault.key if self.fault is not None else None):
            logger.debug("unit failed again: %s", error)
            return
        self.fault = fault
        logger.error("%s", fault.sentence, exc_info=error if fault.traceback else None)

    def _recovered(self) -> None:
        """A unit committed after failed ones: said once."""
        if self.fault is None:
            return
        if self.fault.key.startswith("registry"):
            logger.warning("the registry is accepted again; the queued files are processed")
        else:
            logger.warning("units commit again; the queued files are processed")
        self.fault = None

    def _landing_writable(self) -> None:
        """Said once when ``logs/`` turns read-only (nothing new can land; the files there
        are still read), and once when it is writable again."""
        logs = self.fleet_dir / LOGS_DIR
        try:
            read_only = bool(os.statvfs(logs).f_flag & os.ST_RDONLY)
        except OSError:
            return  # gone: the next step says so
        if read_only == self.landing_read_only:
            return
        self.landing_read_only = read_only
        if read_only:
            logger.warning(
                "%s is on a read-only filesystem: no file can land until it is writable "
                "again; the files already there are processed",
                logs,
            )
        else:
            logger.warning("%s is writable again", logs)

    def _unit(self) -> None:
        began = time.monotonic()
        taken = {e.relpath for e in self.tracker.complete()}
        try:
            report = self._run_fleet(taken)
        except Exception as error:  # one unit's failure never stops the service
            if not self.fleet_dir.is_dir():
                raise WatchError(f"{self.fleet_dir}: the fleet directory is gone") from None
            self.report.units_failed += 1
            self.report.last_error = f"{type(error).__name__}: {error}"
            self._failed(error, len(taken))
            if not isinstance(error, FleetbrakeError):
                self._close_engine()  # a fresh one for the next unit
            self.next_unit = time.monotonic() + self.pause_s
            logger.info("trying again in %g s", self.pause_s)
            self.pause_s = min(2 * self.pause_s, self.config.rescan_s)
            return
        if report is None:
            return
        self._recovered()
        committed = time.monotonic()
        self.report.units += 1
        self.pause_s = self.config.retry_s
        self._drain()  # what happened during the unit, before its files are attributed
        changed = self._changed_since_read(report.ingest.results)
        flags = Counter(
            (flag.wagon_id, flag.kind) for flag in (report.flags.flags if report.flags else [])
        )
        for result in report.ingest.results:
            entry = self.tracker.get(result.path)
            if result.path in changed or (entry is not None and not entry.complete):
                # written again after it was handed to the unit, which may have read it
                # half-written: it stays queued, and the next unit reads it again (its new
                # bytes replace what was stored of it)
                logger.warning(
                    "%s: changed while it was read (written to, or replaced); read again",
                    result.path,
                )
                self.tracker.writing(self.fleet_dir / result.path)
                self.retaken.add(result.path)
                continue
            self.retaken.discard(result.path)
            entry = self.tracker.pop(result.path)
            seen = entry.seen_s if entry is not None else began
            outcome = FileOutcome(
                path=result.path,
                wagon=result.wagon_id,
                status=result.status,
                seconds=committed - seen,
                flags={k: n for (w, k), n in sorted(flags.items()) if w == result.wagon_id},
                rows=result.rows,
                reason=result.reason,
            )
            if result.status == "quarantined":
                self.report.files_quarantined += 1
                logger.warning("%s quarantined: %s", result.path, result.reason)
            else:
                self.report.files_ingested += 1
            if self.on_file is not None:
                self.on_file(outcome)
        for relpath in sorted(taken):  # complete and in the ledger as they are: nothing to do
            entry = self.tracker.get(relpath)
            if entry is not None and entry.complete:
                self.tracker.pop(relpath)
                if relpath in self.retaken:  # its bytes were whole when read after all
                    self.retaken.discard(relpath)
                    self._stored_outcome(relpath, committed - entry.seen_s)
        logger.info(
            "unit: %d files in %.2f s (%s)",
            len(report.ingest.results),
            committed - began,
            ", ".join(f"{k} {v:.2f} s" for k, v in report.stage_s.items()),
        )
        if self.live is not None:  # the new timelines to the live viewer (never raises)
            results = report.ingest.results
            self.live.after_unit(
                self.db_path, [(r.path, r.wagon_id) for r in results if r.path not in self.retaken]
            )


def watch_fleet(
    fleet_dir: str | Path,
    db_path: str | Path,
    config: WatchConfig | None = None,
    stop: threading.Event | None = None,
    *,
    on_file: Callable[[FileOutcome], None] | None = None,
) -> WatchReport:
    """``fleetbrake watch``: process every file landing complete in ``<fleet_dir>/logs``
    through ``run``'s code path until ``stop`` is set (see the module).

    Raises before watching what :func:`fleetbrake.ingest.files.load_fleet_registry` raises for
    an unusable fleet directory or registry, and :class:`WatchError` when it cannot go on.
    """
    from fleetbrake.engine import make_engine
    from fleetbrake.ingest.files import load_fleet_registry

    fleet_dir, db_path = Path(fleet_dir), Path(db_path)
    load_fleet_registry(fleet_dir)  # an unusable fleet is refused before anything else
    config = config or WatchConfig()
    # an engine that cannot be had is refused now (exit 2), not at the first unit; the
    # service makes its own at the first unit and keeps it
    make_engine(config.engine, config.workers, address=config.address).close()
    service = _Service(fleet_dir, db_path, config, stop or threading.Event(), on_file)
    return service.run()
