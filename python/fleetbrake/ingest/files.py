"""Ingestion of a fleet directory (``shared/spec/fleet-data.md``) into the warehouse.

::

    from fleetbrake.ingest.files import ingest_fleet
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse("warehouse/fleet.duckdb") as wh:
        report = ingest_fleet("fleet", wh)          # RegistryError if fleet.toml is unusable
    report.ingested, report.quarantined, report.rows

What happens to each file under ``<fleet>/logs`` (hidden names, starting with ``.``, are
ignored: they are temporary files of copies in progress):

* **Identity.** A file is its path (relative to the fleet directory) and the sha256 of its bytes.
  A path already recorded with the same size and mtime is not read again (``verify_hashes``
  reads it anyway); one with other bytes replaces its earlier row and samples; one with the
  same bytes under another size or mtime (copied, touched) keeps its row and samples, and the
  row takes the new size and mtime (so it is not read again). A re-run adds
  nothing; a late file (older than files already ingested) is taken when it comes.
* **Atomicity.** A file's ``files`` row, its samples and the time range whose events must be
  recomputed (``event_dirty``) are always in the same transaction; whole partitions (a wagon
  directory's new files, at most ``partition_files``) are grouped into transactions of about
  ``batch_rows`` rows (for DuckDB's direct writes). A run killed
  at any point leaves whole files or nothing of them; the next run completes the work with
  the same result.
* **Quarantine** (``status = 'quarantined'``, ``rows = 0``, ``reason`` naming the file): a path
  not of the form ``logs/<wagon_id>/<wagon_id>_<YYYYMMDDTHHMMSSZ>.csv[.gz]`` (or a wagon
  directory not matching the file name), a wagon that has no valid registry entry (retried at
  every run, so it is taken once the registry is fixed), an empty file, a gzip stream that is
  corrupt or truncated (its rows up to the cut could be read, but nothing vouches for them: no
  end of stream, no checksum), content that is not text, a first line that is not a header
  with every required column (or names one twice), data rows read of which none is kept
  (``quarantine_code = 'rows'``, the reason naming each rejected line and why). Whether a file
  is gzip is decided by its content, not its name (a mismatch is noted in ``repairs``).
* **Every row accounted for**: a row read is stored or rejected (``rows_in_file = rows +
  rows_rejected``). The rejected rows are those of the repairs below that drop a row, and a
  row with more or fewer fields than the header (a cell added or lost moves the others out of
  their columns). ``reason`` of an ingested file with rejected rows says how many, which lines
  and why (``"<path>: 2 rows rejected: ..."``); ``file_rejections`` (``v_file_rejections``)
  holds every run of rejected lines with why; each such file is logged (a warning naming it
  and the count) and the run's report counts them (:attr:`IngestReport.rows_rejected`).
* **Repairs** (file ingested, counted in ``files`` and described in ``files.repairs`` with line
  numbers): a last row cut short (the file does not end in a newline) is dropped; a row whose
  time cell is empty or not a time is dropped; a row timed before the file name's time or more
  than ``max_session_s`` after it is dropped; a repeated time keeps its first row; rows out of
  order are sorted; a numeric cell that is not a finite number, or that lies outside the range
  its channel can physically take (``fleet.logfile.PLAUSIBLE_RANGES``: a speed of 1e308 km/h,
  a pressure of -5 bar), becomes empty (the row is kept; both counted in ``cells_unparsable``);
  a ``block_temp_c`` reading outside [-60, 600] °C is a broken wire: stored as
  ``block_temp_raw_c`` with ``block_temp_fault = true``, ``block_temp_c`` null. A blank line
  is a row without a time.

Speed: the new files are cut into partitions (a wagon directory's files, at most
``partition_files`` of them), which an engine (:mod:`fleetbrake.engine`) reads, hashes,
decompresses and parses: in worker processes (:class:`~fleetbrake.engine.LocalEngine`), or
in this process on ``workers`` threads (the default inline engine; zlib, hashlib and polars
release the GIL). This process alone writes, one partition at a time in path order, so the
file ids and every table are the same with any engine; its transactions run on a thread of
their own, in order, while the next partitions are parsed. A few partitions (the engine's
``in_flight``) and one batch are held in memory, and DuckDB's buffer pool is bounded
(``memory_limit``), so memory does not grow with the fleet.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import duckdb
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeRemainingColumn,
)

from fleetbrake.engine import Engine, InlineEngine
from fleetbrake.errors import FleetbrakeError
from fleetbrake.fleet.registry import Registry, load_registry
from fleetbrake.ingest.config import EventConfig, IngestConfig
from fleetbrake.ingest.events import EventUpdate, update_events
from fleetbrake.ingest.ledger import Batch, FileResult, known_files, needs_reading, unchanged
from fleetbrake.ingest.prepare import partitions, prepare_partition
from fleetbrake.ingest.scan import scan_logs, stat_logs
from fleetbrake.warehouse.connection import Warehouse, WarehouseError, open_warehouse, sql

__all__ = [
    "REGISTRY_FILE",
    "FleetDirError",
    "IngestReport",
    "ingest_fleet",
    "load_fleet_registry",
    "print_report",
    "run_ingest",
]

REGISTRY_FILE = "fleet.toml"

logger = logging.getLogger(__name__)


class FleetDirError(FleetbrakeError):
    """The fleet directory cannot be used at all (missing, not a directory)."""


@dataclass
class IngestReport:
    """Outcome of one ingestion run."""

    fleet_dir: Path
    db_path: Path
    files_seen: int = 0
    files_unchanged: int = 0
    results: list[FileResult] = field(default_factory=list)
    registry_problems: list[str] = field(default_factory=list)
    seconds: float = 0.0
    write_s: float = 0.0
    """Of ``seconds``, those spent waiting for the warehouse's writes: the transactions run on
    a thread of their own while the next files are read and parsed (:class:`~fleetbrake.ingest.ledger.Batch`), so
    this is what they did not overlap (a transaction still running when the next batch is
    full, the last one), and the checkpoint."""
    events: EventUpdate | None = None
    """What the event detection that followed changed (None if it did not run)."""

    @property
    def ingested(self) -> list[FileResult]:
        """Files ingested by this run."""
        return [r for r in self.results if r.status == "ingested"]

    @property
    def quarantined(self) -> list[FileResult]:
        """Files quarantined by this run."""
        return [r for r in self.results if r.status == "quarantined"]

    @property
    def rows(self) -> int:
        """Samples stored by this run."""
        return sum(r.rows for r in self.results)

    @property
    def rows_rejected(self) -> int:
        """Rows read by this run but not stored (each named in its file's reason)."""
        return sum(r.rows_rejected for r in self.results)


def _show_progress(progress: bool | None) -> bool:
    return sys.stderr.isatty() if progress is None else progress


def load_fleet_registry(fleet_dir: str | os.PathLike[str]) -> Registry:
    """The registry of a fleet directory; :class:`FleetDirError` if ``fleet_dir`` is not a
    directory, :class:`~fleetbrake.fleet.registry.RegistryError` if ``fleet.toml`` is unusable."""
    fleet_dir = Path(fleet_dir)
    if not fleet_dir.is_dir():
        raise FleetDirError(f"{fleet_dir}: no such fleet directory")
    return load_registry(fleet_dir / REGISTRY_FILE)


def ingest_fleet(
    fleet_dir: str | os.PathLike[str],
    wh: Warehouse,
    *,
    registry: Registry | None = None,
    config: IngestConfig | None = None,
    progress: bool | None = None,
    engine: Engine | None = None,
    files: Iterable[str] | None = None,
) -> IngestReport:
    """Ingest every file of ``fleet_dir`` that the warehouse does not hold yet.

    ``files``: only these paths (relative to the fleet directory, as ``v_files.path``; see
    :func:`stat_logs`) are looked at, instead of every file under ``logs/`` (a unit of
    ``fleetbrake watch``: a file that lands meanwhile is not read). A file the warehouse holds
    with the same bytes under another size or modification time (copied, touched) is not
    stored again, but its ledger row takes the new ones, so that it is not read again.

    ``registry`` defaults to the fleet's ``fleet.toml`` (see :func:`load_fleet_registry` for
    what raises); before anything is written, every entry of a wagon the warehouse holds is
    checked (:meth:`~fleetbrake.fleet.registry.Registry.check_held`: an invalid one raises
    :class:`~fleetbrake.fleet.registry.InvalidRegistryError`, for ``run``, ``ingest`` and
    each unit of ``watch`` alike); bad files never raise (they are quarantined). ``progress=None`` shows a
    progress bar when stderr is a terminal.

    The new files are cut into partitions (a wagon directory's files, at most
    ``config.partition_files`` of them) that ``engine``'s workers read, hash, judge and parse
    (with no engine, or one of a single worker: ``config.workers`` threads of this process,
    an :class:`~fleetbrake.engine.InlineEngine`); this process, the single writer, takes their results in path order and
    commits each partition's files in one transaction (with the partitions before it, until
    they hold ``batch_rows`` rows). The tables are the same with any engine.
    """
    config = config or IngestConfig()
    if engine is None or engine.workers == 1:  # in this process: threads, ahead of the writer
        engine = InlineEngine(threads=config.workers)
    fleet_dir = Path(fleet_dir)
    started = time.perf_counter()
    if registry is None:
        registry = load_fleet_registry(fleet_dir)
    registry.check_held(_held_wagons(wh))  # before anything is written
    report = IngestReport(
        fleet_dir=fleet_dir,
        db_path=wh.path,
        registry_problems=[str(p) for p in registry.problems],
    )
    entries = scan_logs(fleet_dir) if files is None else stat_logs(fleet_dir, files)
    report.files_seen = len(entries)
    known = known_files(wh)
    todo = [e for e in entries if needs_reading(e, known.get(e.relpath), config)]
    report.files_unchanged = len(entries) - len(todo)
    row = wh.con.execute(sql("q_ingest_last_file_id")).fetchone()
    next_id = (int(row[0]) if row is not None else 0) + 1

    # Cheaper bulk inserts: rows of a batch need not keep their order (parallel appends), and
    # zstd (tried on every string column) costs about a tenth of the insert for no smaller file.
    with wh.settings(
        memory_limit=config.memory_limit,
        preserve_insertion_order=False,
        disabled_compression_methods="zstd",
    ):
        with (
            _Progress(len(todo), enabled=_show_progress(progress)) as bar,
            Batch(wh, config) as batch,
        ):
            for partition in engine.map(
                functools.partial(prepare_partition, config=config),
                partitions(todo, registry, config),
            ):
                for prepared in partition:
                    if prepared is None:  # removed since the scan
                        report.files_seen -= 1
                        bar.advance(0)
                        continue
                    before = known.get(prepared.entry.relpath)
                    if unchanged(prepared, before):
                        report.files_unchanged += 1
                        batch.refresh(prepared, before)
                    else:
                        result = batch.add(prepared, before, next_id)
                        report.results.append(result)
                        next_id += 1
                        if result.rows_rejected:
                            logger.warning(
                                "%s: %d of %d rows read rejected (see v_file_rejections)",
                                result.path,
                                result.rows_rejected,
                                result.rows + result.rows_rejected,
                            )
                    bar.advance(prepared.parsed.frame.height if prepared.parsed is not None else 0)
                batch.end_partition()
        report.write_s = batch.write_s
        if report.results:  # (a ledger refresh alone writes too little to checkpoint)
            began = time.perf_counter()
            wh.con.execute("CHECKPOINT")  # while the memory is bounded, not at close
            report.write_s += time.perf_counter() - began
    report.seconds = time.perf_counter() - started
    return report


class _Progress:
    """A rich progress bar over files (with a row count), or nothing."""

    def __init__(self, total_files: int, *, enabled: bool) -> None:
        self._bar: Progress | None = None
        self._rows = 0
        if enabled and total_files:
            self._bar = Progress(
                TextColumn("ingesting"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("files, {task.fields[rows]:,} rows"),
                TimeRemainingColumn(),
                console=Console(stderr=True),
                transient=True,
            )
            self._task = self._bar.add_task("ingest", total=total_files, rows=0)

    def __enter__(self) -> _Progress:
        if self._bar is not None:
            self._bar.start()
        return self

    def advance(self, rows: int) -> None:
        if self._bar is not None:
            self._rows += rows
            self._bar.update(self._task, advance=1, rows=self._rows)

    def __exit__(self, *exc: object) -> None:
        if self._bar is not None:
            self._bar.stop()


def run_ingest(
    fleet_dir: str | os.PathLike[str],
    db_path: str | os.PathLike[str],
    *,
    wait_s: float = 0.0,
    config: IngestConfig | None = None,
    event_config: EventConfig | None = None,
    progress: bool | None = None,
    engine: Engine | None = None,
) -> IngestReport:
    """``fleetbrake ingest``: check the fleet directory and its registry, open the warehouse
    (waiting up to ``wait_s`` for another writer), ingest, detect events, close.

    Raises :class:`FleetDirError`, :class:`~fleetbrake.fleet.registry.RegistryError` (before the
    database is touched), :class:`~fleetbrake.fleet.registry.InvalidRegistryError` when an
    entry of a wagon the warehouse holds is invalid (before anything is written) and :class:`~fleetbrake.warehouse.connection.WarehouseError` (locked, unusable,
    or failing while written: disk full, ...; what was committed before stays).
    """
    registry = load_fleet_registry(fleet_dir)
    with open_warehouse(db_path, wait_s=wait_s) as wh:
        try:
            report = ingest_fleet(
                fleet_dir, wh, registry=registry, config=config, progress=progress, engine=engine
            )
            report.events = update_events(wh, event_config, engine=engine)
        except duckdb.Error as error:
            raise WarehouseError(f"{db_path}: {error}") from error
    return report


def print_report(report: IngestReport, console: Console | None = None) -> None:
    """Summary of a run for people: counts, every quarantined file with its reason."""
    out = console or Console(soft_wrap=True)  # a reason stays on one line, for grep
    ingested, quarantined = report.ingested, report.quarantined
    out.print(
        f"{report.fleet_dir} -> {report.db_path}: {report.files_seen} files seen, "
        f"{len(ingested)} ingested ({report.rows:,} rows, {report.rows_rejected:,} rejected), "
        f"{len(quarantined)} quarantined, "
        f"{report.files_unchanged} already held, in {report.seconds:.1f} s"
    )
    repaired = [r for r in ingested if r.repairs]
    if repaired:
        out.print(f"{len(repaired)} ingested files were repaired (see files.repairs).")
    for problem in report.registry_problems:
        out.print(f"[yellow]registry:[/yellow] {escape(problem)}")
    for result in quarantined:
        out.print(f"[red]quarantined:[/red] {escape(result.reason or result.path)}")
    if report.events is not None:
        ev = report.events
        out.print(
            f"events: {ev.added} new or changed, {ev.removed} removed, {ev.unchanged} unchanged "
            f"({ev.chains} stretches of {ev.wagons} wagons looked at); {ev.total} in total"
        )


def _held_wagons(wh: Warehouse) -> list[str]:
    """The wagons whose registry entries a run stored: those with results in the warehouse,
    whose entries every run checks (:meth:`~fleetbrake.fleet.registry.Registry.check_held`),
    whether or not they have new files."""
    return [row[0] for row in wh.con.execute(sql("q_simulation_stored_wagons")).fetchall()]
