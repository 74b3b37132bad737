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
  with every required column (or names one twice). Whether a file is gzip is decided by its
  content, not its name (a mismatch is noted in ``repairs``).
* **Repairs** (file ingested, counted in ``files`` and described in ``files.repairs`` with line
  numbers): a last row cut short (the file does not end in a newline) is dropped; a row whose
  time cell is empty or not a time is dropped; a row timed before the file name's time or more
  than ``max_session_s`` after it is dropped; a repeated time keeps its first row; rows out of
  order are sorted; a numeric cell that is not a finite number, or that lies outside the range
  its channel can physically take (``fleet.logfile.PLAUSIBLE_RANGES``: a speed of 1e308 km/h,
  a pressure of -5 bar), becomes empty (the row is kept; both counted in ``cells_unparsable``);
  a ``block_temp_c`` reading outside [-60, 600] °C is a broken wire: stored as
  ``block_temp_raw_c`` with ``block_temp_fault = true``, ``block_temp_c`` null. A
  line with fewer cells than the header has empty trailing cells, one with more has its extra
  cells ignored.

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

import dataclasses
import datetime as dt
import functools
import hashlib
import itertools
import os
import sys
import time
import zlib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from stat import S_ISDIR
from typing import Any

import duckdb
import numpy as np
import polars as pl
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
from fleetbrake.engine.writer import WriteBehind
from fleetbrake.errors import FleetbrakeError
from fleetbrake.fleet.logfile import (
    BLOCK_TEMP_VALID_C,
    FLOAT_COLUMNS,
    OPTIONAL_COLUMNS,
    PLAUSIBLE_RANGES,
    REQUIRED_COLUMNS,
    TIME_FORMAT,
    LogNameError,
    parse_log_path,
)
from fleetbrake.fleet.registry import Registry, RegistryError, load_registry
from fleetbrake.ingest.events import EventConfig, EventUpdate, update_events
from fleetbrake.warehouse.connection import Warehouse, WarehouseError, open_warehouse, sql

__all__ = [
    "FileResult",
    "FleetDirError",
    "IngestConfig",
    "IngestReport",
    "LogEntry",
    "ParsedLog",
    "Quarantine",
    "Repairs",
    "ingest_fleet",
    "load_fleet_registry",
    "print_report",
    "read_log",
    "run_ingest",
    "scan_logs",
    "stat_logs",
]

REGISTRY_FILE = "fleet.toml"
LOGS_DIR = "logs"
_GZIP_MAGIC = b"\x1f\x8b"
_EPOCH = dt.datetime(1970, 1, 1)
_EXAMPLES = 5
"""How many line numbers (or values) a repair note lists before 'and N more'."""


class FleetDirError(FleetbrakeError):
    """The fleet directory cannot be used at all (missing, not a directory)."""


@dataclass(frozen=True)
class IngestConfig:
    """Knobs of the ingestion."""

    workers: int = 2
    """Threads reading, hashing, decompressing and parsing partitions of files ahead of the
    writer when the ingestion runs in this process (no engine, or an engine of one worker);
    with an engine of more workers, its processes do."""
    in_flight_files: int = 16
    """Unused since the files are read by partitions (``partition_files``, and the engine's
    ``in_flight`` partitions); kept so that configurations naming it still load."""
    max_session_s: int = 48 * 3600
    """A row timed more than this after the file name's time is not of this session."""
    max_file_bytes: int = 1 << 30
    """A larger file is quarantined unread (a session at 1 Hz is a few MB)."""
    partition_files: int = 8
    """A wagon's new files are read in partitions of at most this many files (a worker's unit
    of work, committed by the writer at once: see :func:`ingest_fleet`)."""
    batch_rows: int = 1_000_000
    """Whole partitions are committed together until they hold this many rows (see _Batch):
    DuckDB's writer spends about half the processor time per row on transactions of 0.7 M
    rows and more as on transactions of 0.2 M (``docs/benchmarks.md``)."""
    batch_files: int = 500
    """... or this many files."""
    verify_hashes: bool = False
    """Re-read and hash recorded files even when their size and mtime are unchanged."""
    memory_limit: str = "128MB"
    """DuckDB's buffer pool during the ingestion (restored afterwards): the written blocks it
    caches would otherwise grow with the fleet up to the connection's limit."""
    plausible_ranges: Mapping[str, tuple[float, float]] = field(
        default_factory=lambda: PLAUSIBLE_RANGES
    )
    """Closed range of each numeric channel: a cell outside is cleared and counted as
    unparsable, except ``block_temp_c``, whose readings outside are Pt1000 faults."""

    def __reduce__(self) -> tuple[object, ...]:
        """Picklable (it goes to an engine's workers): the ranges as a plain dict."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        values["plausible_ranges"] = dict(self.plausible_ranges)
        return (_ingest_config, (values,))


def _ingest_config(values: dict[str, Any]) -> IngestConfig:
    return IngestConfig(**values)


class Quarantine(Exception):
    """A file that cannot be ingested: ``code`` says what kind of problem, the message which."""

    def __init__(self, code: str, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason

    def __reduce__(self) -> tuple[object, ...]:  # crosses from a worker process intact
        return (Quarantine, (self.code, self.reason))


@dataclass
class Repairs:
    """What was repaired in one file; every count is also described in :meth:`text`."""

    rows_in_file: int = 0
    rows_no_time: int = 0
    rows_outside_session: int = 0
    rows_duplicate: int = 0
    rows_out_of_order: int = 0
    cells_unparsable: int = 0
    """Cells not a finite number or outside their channel's plausible range (now empty)."""
    block_temp_faults: int = 0
    partial_row_dropped: bool = False
    notes: list[str] = field(default_factory=list)

    def text(self) -> str | None:
        """The notes as one sentence list, or None when nothing was repaired."""
        return "; ".join(self.notes) if self.notes else None


@dataclass(frozen=True)
class ParsedLog:
    """One log file read and repaired: the samples to store, sorted by time, and the repairs."""

    frame: pl.DataFrame
    repairs: Repairs

    @property
    def first_utc(self) -> dt.datetime | None:
        """Time of the first sample (None if there is none)."""
        return self.frame["time_utc"].min() if self.frame.height else None  # type: ignore[return-value]

    @property
    def last_utc(self) -> dt.datetime | None:
        """Time of the last sample (None if there is none)."""
        return self.frame["time_utc"].max() if self.frame.height else None  # type: ignore[return-value]


@dataclass(frozen=True)
class FileResult:
    """What this run did with one file."""

    path: str
    wagon_id: str | None
    status: str
    """``ingested`` or ``quarantined``."""
    rows: int
    reason: str | None = None
    repairs: str | None = None
    replaced: bool = False
    """The path was recorded before: with other bytes, or quarantined for a cause that is
    judged again at every run (registry, unreadable, reader error)."""
    size_bytes: int | None = None
    mtime_ns: int | None = None
    """The size and modification time the ledger recorded for it (as stat saw the file
    before it was read: a file written meanwhile has others now)."""


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
    a thread of their own while the next files are read and parsed (:class:`_Batch`), so
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


# --------------------------------------------------------------------------------------------
# Reading one file


def _lines(line_numbers: list[int], total: int) -> str:
    shown = ", ".join(str(n) for n in line_numbers[:_EXAMPLES])
    more = total - min(total, _EXAMPLES)
    word = "line" if total == 1 else "lines"
    return f"{word} {shown}" + (f" and {more} more" if more else "")


def _gunzip(data: bytes, relpath: str) -> bytes:
    """Every member of a gzip stream; :class:`Quarantine` if corrupt or cut short."""
    parts: list[bytes] = []
    rest = data
    try:
        while rest:
            inflater = zlib.decompressobj(wbits=31)
            parts.append(inflater.decompress(rest))
            if not inflater.eof:
                raise Quarantine(
                    "gzip",
                    f"{relpath}: gzip stream truncated after {len(data)} bytes (no end of "
                    "stream): the file was cut short",
                )
            rest = inflater.unused_data
            if not rest.strip(b"\x00"):
                break
    except zlib.error as error:
        raise Quarantine("gzip", f"{relpath}: corrupt gzip stream ({error})") from None
    return b"".join(parts)


def _header(data: bytes, relpath: str) -> tuple[list[str], bytes]:
    """Column names of the first line, and the rest of the data."""
    end = data.find(b"\n")
    if end < 0:
        raise Quarantine("header", f"{relpath}: no complete first line (no header)")
    line, body = data[:end], data[end + 1 :]
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError:
        raise Quarantine(
            "binary", f"{relpath}: not a CSV log: line 1 is not UTF-8 text (binary content)"
        ) from None
    text = text.removeprefix("\ufeff").removesuffix("\r")
    if any(ord(c) < 32 and c != "\t" for c in text):
        raise Quarantine("binary", f"{relpath}: not a CSV log: line 1 holds control characters")
    names = [name.strip() for name in text.split(",")]
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        shown = text if len(text) <= 120 else text[:117] + "..."
        raise Quarantine(
            "header",
            f"{relpath}: line 1 is not a log header: it lacks {', '.join(missing)} "
            f"(found {shown!r})",
        )
    repeated = sorted(
        {n for n in names if n in REQUIRED_COLUMNS + OPTIONAL_COLUMNS and names.count(n) > 1}
    )
    if repeated:
        raise Quarantine("header", f"{relpath}: line 1 names {', '.join(repeated)} more than once")
    return names, body


def _complete_rows(body: bytes, repairs: Repairs) -> bytes:
    """``body`` without a last row cut short (no final newline)."""
    if not body or body.endswith(b"\n"):
        return body
    end = body.rfind(b"\n")
    kept = body[: end + 1]
    line = kept.count(b"\n") + 2
    repairs.partial_row_dropped = True
    repairs.notes.append(f"file ends inside line {line} (cut short): that partial row dropped")
    return kept


def _parse_cells(body: bytes, names: list[str]) -> tuple[pl.DataFrame, pl.DataFrame | None]:
    """The known columns of ``body``: ``time_utc`` as text, numbers as Float64.

    The body is parsed under a clean copy of its header (so the header, not the first data
    line, says how many cells a line has). Fast path: typed parse. If a cell is not a number,
    a line has more cells than the header, or the bytes are not UTF-8, every column is parsed
    as text (extra cells ignored, bad bytes replaced) and cast cell by cell; then the text is
    returned too, for the notes. A line with fewer cells has empty trailing cells.
    """
    wanted = [i for i, name in enumerate(names) if name in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    placeholders = [name if i in wanted else f"_ignored_{i}" for i, name in enumerate(names)]
    data = ",".join(placeholders).encode() + b"\n" + body
    typed = pl.Schema(
        {name: (pl.Float64 if name in FLOAT_COLUMNS else pl.String) for name in placeholders}
    )
    try:
        frame = pl.read_csv(data, schema=typed, columns=wanted, quote_char=None)
        return frame, None
    except pl.exceptions.PolarsError:
        pass
    text = pl.read_csv(
        data,
        schema=pl.Schema({name: pl.String for name in placeholders}),
        columns=wanted,
        quote_char=None,
        truncate_ragged_lines=True,
        encoding="utf8-lossy",
    )
    numbers = text.with_columns(
        pl.col(c).str.strip_chars().cast(pl.Float64, strict=False)
        for c in FLOAT_COLUMNS
        if c in text.columns
    )
    return numbers, text


def _line_numbers(frame: pl.DataFrame, mask: pl.Series) -> list[int]:
    """File line numbers of the rows where ``mask`` holds (header = line 1)."""
    if "_line" in frame.columns:
        return frame["_line"].filter(mask).to_list()  # one column, not the whole frame
    return (mask.arg_true() + 2).to_list()


def _clear_unparsable(
    frame: pl.DataFrame, text: pl.DataFrame | None, repairs: Repairs
) -> pl.DataFrame:
    """Numeric cells that are not a finite number become null; counted and noted."""
    present = [c for c in FLOAT_COLUMNS if c in frame.columns]
    not_finite = {c: pl.col(c).is_not_null() & ~pl.col(c).is_finite() for c in present}
    if text is None:
        (count,) = frame.select(pl.sum_horizontal(e.sum() for e in not_finite.values())).row(0)
        if not count:
            return frame
        bad = frame.select(e.alias(c) for c, e in not_finite.items())
    else:
        raw = text.select(pl.col(c).str.strip_chars() for c in present)
        bad = frame.select(
            (
                not_finite[c] | pl.lit(raw[c].is_not_null() & (raw[c] != "") & frame[c].is_null())
            ).alias(c)
            for c in present
        )
    counts = bad.sum().row(0, named=True)
    total = sum(counts.values())
    if not total:
        return frame
    repairs.cells_unparsable = total
    examples = []
    for c, count in counts.items():
        if not count:
            continue
        rows = bad[c].arg_true().head(_EXAMPLES).to_list()
        source = text if text is not None else frame
        shown = [repr(source[c][r]) for r in rows[:2]]
        examples.append(
            f"{c} {_lines([r + 2 for r in rows], count)} ({', '.join(shown)}"
            + (", ..." if count > 2 else "")
            + ")"
        )
    repairs.notes.append(
        f"{total} cell{'s' if total > 1 else ''} not a finite number, now empty: "
        + "; ".join(examples)
    )
    return frame.with_columns(
        pl.when(bad[c]).then(None).otherwise(pl.col(c)).alias(c) for c in present if counts[c]
    )


def _clear_implausible(
    frame: pl.DataFrame, ranges: Mapping[str, tuple[float, float]], repairs: Repairs
) -> pl.DataFrame:
    """Numeric cells outside their channel's plausible range become null; counted with the
    unparsable ones and noted. ``block_temp_c`` is left to :func:`_block_temp_faults`."""
    checked = {c: ranges[c] for c in FLOAT_COLUMNS if c in ranges and c in frame.columns}
    checked.pop("block_temp_c", None)
    if not checked or frame.height == 0:
        return frame
    # fast path (every file of a working unit): each column's extremes within its range
    lowest = frame.select(pl.col(c).min() for c in checked).row(0, named=True)
    highest = frame.select(pl.col(c).max() for c in checked).row(0, named=True)
    inside = [
        (lowest[c] is None or lowest[c] >= lo) and (highest[c] is None or highest[c] <= hi)
        for c, (lo, hi) in checked.items()
    ]
    if all(inside):
        return frame
    bad = frame.select(
        (~pl.col(c).is_between(lo, hi)).fill_null(False).alias(c) for c, (lo, hi) in checked.items()
    )
    counts = bad.sum().row(0, named=True)
    total = sum(counts.values())
    repairs.cells_unparsable += total
    examples = []
    for c, n in counts.items():
        if not n:
            continue
        low, high = checked[c]
        rows = bad[c].arg_true()
        shown = [f"{v:g}" for v in frame[c].gather(rows.head(2)).to_list()]
        examples.append(
            f"{c} outside [{low:g}, {high:g}] {_lines((rows + 2).head(_EXAMPLES).to_list(), n)} "
            f"({', '.join(shown)}" + (", ..." if n > 2 else "") + ")"
        )
    repairs.notes.append(
        f"{total} cell{'s' if total > 1 else ''} outside the range the channel can take (not a "
        "measurement), now empty: " + "; ".join(examples)
    )
    return frame.with_columns(
        pl.when(bad[c]).then(None).otherwise(pl.col(c)).alias(c) for c in counts if counts[c]
    )


def _in_order(time_utc: pl.Series, start_utc: dt.datetime, latest_utc: dt.datetime) -> bool:
    """Every time present, within the session, strictly increasing: nothing to repair."""
    if time_utc.null_count() or time_utc.is_empty():
        return time_utc.is_empty()
    us = time_utc.to_physical().to_numpy()
    start_us = int((start_utc - _EPOCH) / dt.timedelta(microseconds=1))
    latest_us = int((latest_utc - _EPOCH) / dt.timedelta(microseconds=1))
    return bool(us[0] >= start_us and us[-1] <= latest_us and np.all(np.diff(us) > 0))


def _times(
    frame: pl.DataFrame,
    text_time: pl.Series,
    start_utc: dt.datetime,
    config: IngestConfig,
    repairs: Repairs,
) -> pl.DataFrame:
    """Parse ``time_utc``, drop rows without a usable time, keep the first of repeated times,
    sort; counted and noted. Adds ``_line`` (file line numbers) when rows move or go."""
    frame = frame.with_columns(
        pl.col("time_utc").str.to_datetime(TIME_FORMAT, time_unit="us", strict=False, cache=False)
    )
    latest_utc = start_utc + dt.timedelta(seconds=config.max_session_s)
    if _in_order(frame["time_utc"], start_utc, latest_utc):
        return frame
    frame = frame.with_columns(pl.int_range(2, frame.height + 2, dtype=pl.Int64).alias("_line"))
    # The repairs are judged in numpy on the times alone (each polars call on a column costs
    # about as much as the judgement); the whole frame is gathered once at the end.
    time_utc = frame["time_utc"]
    no_time = time_utc.is_null().to_numpy()
    rows = np.arange(frame.height)
    if no_time.any():
        lines = (rows[no_time] + 2).tolist()
        raw = text_time.filter(pl.Series(no_time))
        empty = int((raw.is_null() | (raw.str.strip_chars() == "")).sum())
        repairs.rows_no_time = len(lines)
        examples = [repr(v) for v in raw.drop_nulls().to_list() if v.strip()][:2]
        detail = f"{empty} empty" + (
            f", {len(lines) - empty} not a time ({', '.join(examples)})"
            if len(lines) > empty
            else ""
        )
        repairs.notes.append(
            f"{len(lines)} row{'s' if len(lines) > 1 else ''} without a time dropped "
            f"({detail}): {_lines(lines, len(lines))}"
        )
        rows = rows[~no_time]
    us = time_utc.to_physical().fill_null(0).to_numpy()[rows]
    start_us = int((start_utc - _EPOCH) / dt.timedelta(microseconds=1))
    latest_us = int((latest_utc - _EPOCH) / dt.timedelta(microseconds=1))
    outside = (us < start_us) | (us > latest_us)
    if outside.any():
        lines = (rows[outside] + 2).tolist()
        repairs.rows_outside_session = len(lines)
        repairs.notes.append(
            f"{len(lines)} row{'s' if len(lines) > 1 else ''} timed before the file name's "
            f"time {start_utc:%Y-%m-%dT%H:%M:%SZ} or more than {config.max_session_s} s after "
            f"it dropped: {_lines(lines, len(lines))}"
        )
        rows, us = rows[~outside], us[~outside]
    repeated = np.ones(us.size, dtype=bool)
    repeated[np.unique(us, return_index=True)[1]] = False  # the first of each time is kept
    if repeated.any():
        lines = (rows[repeated] + 2).tolist()
        repairs.rows_duplicate = len(lines)
        repairs.notes.append(
            f"{len(lines)} row{'s' if len(lines) > 1 else ''} repeating an earlier row's time "
            f"dropped (the first kept): {_lines(lines, len(lines))}"
        )
        rows, us = rows[~repeated], us[~repeated]
    if rows.size < frame.height:
        frame = frame.gather(rows)  # the kept rows, in file order
    late = np.zeros(us.size, dtype=bool)
    late[1:] = us[1:] < np.maximum.accumulate(us)[:-1]
    if late.any():
        lines = (rows[late] + 2).tolist()
        repairs.rows_out_of_order = len(lines)
        repairs.notes.append(
            f"{len(lines)} row{'s' if len(lines) > 1 else ''} out of time order, sorted: "
            f"{_lines(lines, len(lines))}"
        )
        frame = frame.sort("time_utc", maintain_order=True)
    return frame


def _block_temp_faults(frame: pl.DataFrame, config: IngestConfig, repairs: Repairs) -> pl.DataFrame:
    """Split ``block_temp_c`` into valid readings and out-of-range faults (raw value kept)."""
    low_c, high_c = config.plausible_ranges.get("block_temp_c", BLOCK_TEMP_VALID_C)
    raw = pl.col("block_temp_c")
    fault = (raw < low_c) | (raw > high_c)
    faulty = frame.select(fault.fill_null(False)).to_series()
    count = int(faulty.sum())
    if not count:
        return frame.with_columns(
            pl.lit(None, dtype=pl.Float64).alias("block_temp_raw_c"),
            pl.lit(False).alias("block_temp_fault"),
        )
    lines = _line_numbers(frame, faulty)
    values = frame.filter(faulty)["block_temp_c"]
    lowest, highest = float(values.min()), float(values.max())  # type: ignore[arg-type]
    repairs.block_temp_faults = count
    repairs.notes.append(
        f"{count} block_temp_c reading{'s' if count > 1 else ''} outside "
        f"[{low_c:g}, {high_c:g}] degC (broken wire; {lowest:g} to {highest:g}) "
        f"kept as faults, not temperatures: {_lines(lines, count)}"
    )
    return frame.with_columns(
        pl.when(fault).then(None).otherwise(raw).alias("block_temp_c"),
        pl.when(fault).then(raw).otherwise(None).alias("block_temp_raw_c"),
        faulty.alias("block_temp_fault"),
    )


def read_log(
    data: bytes,
    relpath: str,
    start_utc: dt.datetime,
    config: IngestConfig | None = None,
) -> ParsedLog:
    """Read and repair one log file's bytes (gzip or not); :class:`Quarantine` if unusable.

    ``start_utc`` is the time of the file name. The frame has ``time_utc`` (Datetime, sorted,
    distinct), every numeric column of :data:`~fleetbrake.fleet.logfile.FLOAT_COLUMNS` (Float64, null
    where empty), ``block_temp_raw_c`` and ``block_temp_fault``.
    """
    config = config or IngestConfig()
    if not data:
        raise Quarantine("empty", f"{relpath}: empty file (0 bytes)")
    repairs = Repairs()
    if data.startswith(_GZIP_MAGIC):
        data = _gunzip(data, relpath)
        if not relpath.endswith(".gz"):
            repairs.notes.append("gzip content in a file named .csv: decompressed")
    elif relpath.endswith(".gz"):
        repairs.notes.append("plain CSV in a file named .csv.gz: read as it is")
    names, body = _header(data, relpath)
    body = _complete_rows(body, repairs)
    frame, text = _parse_cells(body, names)
    repairs.rows_in_file = frame.height
    frame = _clear_unparsable(frame, text, repairs)
    frame = _clear_implausible(frame, config.plausible_ranges, repairs)
    for name in OPTIONAL_COLUMNS:
        if name not in frame.columns:
            frame = frame.with_columns(pl.lit(None, dtype=pl.Float64).alias(name))
    text_time = (text if text is not None else frame)["time_utc"]
    frame = _times(frame, text_time, start_utc, config, repairs)
    frame = _block_temp_faults(frame, config, repairs)
    frame = frame.select("time_utc", *FLOAT_COLUMNS, "block_temp_raw_c", "block_temp_fault")
    return ParsedLog(frame, repairs)


# --------------------------------------------------------------------------------------------
# The fleet directory


@dataclass(frozen=True)
class LogEntry:
    """A file found under ``logs/``."""

    relpath: str
    """Relative to the fleet directory, '/'-separated."""
    path: Path
    size_bytes: int
    mtime_ns: int


def scan_logs(fleet_dir: Path) -> list[LogEntry]:
    """Every file under ``<fleet>/logs`` (any depth), hidden names skipped, sorted by path."""
    root = fleet_dir / LOGS_DIR
    entries: list[LogEntry] = []
    if not root.is_dir():
        return entries
    for directory, subdirs, files in os.walk(root):
        subdirs[:] = [d for d in subdirs if not d.startswith(".")]
        for name in files:
            if name.startswith("."):
                continue
            path = Path(directory, name)
            try:
                stat = path.stat()
            except FileNotFoundError:
                continue  # removed while scanning
            relpath = path.relative_to(fleet_dir).as_posix()
            entries.append(LogEntry(relpath, path, stat.st_size, stat.st_mtime_ns))
    entries.sort(key=lambda e: e.relpath)
    return entries


def stat_logs(fleet_dir: Path, relpaths: Iterable[str]) -> list[LogEntry]:
    """The files ``relpaths`` (relative to the fleet directory, ``/``-separated) as
    :func:`scan_logs` would list them, and nothing else under ``logs/``: those that are gone,
    are not files, or are not names :func:`scan_logs` lists (outside ``logs/``, hidden) are
    left out. Sorted by path."""
    entries: list[LogEntry] = []
    for relpath in sorted(set(relpaths)):
        parts = PurePosixPath(relpath).parts
        if (
            len(parts) < 2
            or parts[0] != LOGS_DIR
            or any(p.startswith(".") or p == ".." for p in parts[1:])
            or PurePosixPath(relpath).as_posix() != relpath
        ):
            continue
        path = fleet_dir / relpath
        try:
            stat = path.stat()
        except OSError:
            continue  # gone (or unreachable) since it was handed over
        if not S_ISDIR(stat.st_mode):
            entries.append(LogEntry(relpath, path, stat.st_size, stat.st_mtime_ns))
    return entries


@dataclass(frozen=True)
class _Known:
    """What the warehouse already holds about a path."""

    file_id: int
    sha256: str
    size_bytes: int
    mtime_ns: int
    status: str
    quarantine_code: str | None
    reason: str | None
    wagon_id: str | None
    first_utc: dt.datetime | None
    last_utc: dt.datetime | None


def _known_files(wh: Warehouse) -> dict[str, _Known]:
    rows = wh.con.execute(sql("q_ingest_known_files")).fetchall()
    return {row[0]: _Known(*row[1:]) for row in rows}


def _needs_reading(entry: LogEntry, known: _Known | None, config: IngestConfig) -> bool:
    if known is None or config.verify_hashes or known.quarantine_code in _RETRIED_CODES:
        return True
    return (known.size_bytes, known.mtime_ns) != (entry.size_bytes, entry.mtime_ns)


@dataclass(frozen=True)
class _Prepared:
    """A file read by a worker: its identity and either its samples or why it is quarantined."""

    entry: LogEntry
    sha256: str
    wagon_id: str | None
    parsed: ParsedLog | None = None
    quarantine: Quarantine | None = None


def _sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        while chunk := handle.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


_RETRIED_CODES = frozenset({"registry", "unreadable", "error"})
"""Quarantine reasons judged again at every run, as their cause may have gone away: the
registry fixed, the file made readable, the reader fixed."""


def _path_wagon(relpath: str) -> str | None:
    """The wagon directory of a path ``logs/<wagon>/<file>``, None for any other shape."""
    parts = relpath.split("/")
    return parts[1] if len(parts) == 3 else None


def _registry_problem(registry: Registry, wagon_id: str) -> str | None:
    """Why ``wagon_id``'s files cannot be ingested with this registry, None if they can."""
    if wagon_id in registry.wagons:
        return None
    try:
        registry.wagon(wagon_id)
        return f"wagon {wagon_id} is not in the registry"
    except RegistryError as error:  # UnknownWagonError: its message says why
        return str(error)


def _prepare(
    entry: LogEntry, problems: Mapping[str, str | None], config: IngestConfig
) -> _Prepared | None:
    """Read, hash and judge one file (runs in a worker); None if it vanished. ``problems``:
    :func:`_registry_problem` of the wagon of each file name."""
    try:
        return _judge(entry, problems, config)
    except FileNotFoundError:
        return None
    except OSError as error:
        reason = f"{entry.relpath}: cannot be read ({error.strerror or error})"
        return _Prepared(
            entry, "", _path_wagon(entry.relpath), quarantine=Quarantine("unreadable", reason)
        )


def _judge(entry: LogEntry, problems: Mapping[str, str | None], config: IngestConfig) -> _Prepared:
    try:
        name = parse_log_path(entry.relpath)
    except LogNameError as error:
        return _Prepared(
            entry,
            _sha256_file(entry.path),
            _path_wagon(entry.relpath),
            quarantine=Quarantine("name", str(error)),
        )
    if entry.size_bytes > config.max_file_bytes:
        reason = (
            f"{entry.relpath}: {entry.size_bytes} bytes, more than a session can be "
            f"(limit {config.max_file_bytes}); not read"
        )
        return _Prepared(
            entry, _sha256_file(entry.path), name.wagon_id, quarantine=Quarantine("size", reason)
        )
    data = entry.path.read_bytes()
    sha256 = hashlib.sha256(data).hexdigest()
    message = problems[name.wagon_id]
    if message is not None:
        return _Prepared(
            entry,
            sha256,
            name.wagon_id,
            quarantine=Quarantine("registry", f"{entry.relpath}: {message}"),
        )
    try:
        parsed = read_log(data, entry.relpath, name.start_utc, config)
    except Quarantine as problem:
        return _Prepared(entry, sha256, name.wagon_id, quarantine=problem)
    except Exception as error:  # a reader bug must not stop the fleet: the file says which
        reason = f"{entry.relpath}: could not be read ({type(error).__name__}: {error})"
        return _Prepared(entry, sha256, name.wagon_id, quarantine=Quarantine("error", reason))
    return _Prepared(entry, sha256, name.wagon_id, parsed=parsed)


def _utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(tzinfo=None)


_FILES_SCHEMA = pl.Schema(
    {
        "file_id": pl.Int64(),
        "path": pl.String(),
        "wagon_id": pl.String(),
        "sha256": pl.String(),
        "size_bytes": pl.Int64(),
        "mtime_ns": pl.Int64(),
        "status": pl.String(),
        "quarantine_code": pl.String(),
        "reason": pl.String(),
        "rows": pl.Int64(),
        "rows_in_file": pl.Int64(),
        "rows_no_time": pl.Int64(),
        "rows_outside_session": pl.Int64(),
        "rows_duplicate": pl.Int64(),
        "rows_out_of_order": pl.Int64(),
        "cells_unparsable": pl.Int64(),
        "block_temp_faults": pl.Int64(),
        "partial_row_dropped": pl.Boolean(),
        "repairs": pl.String(),
        "first_utc": pl.Datetime("us"),
        "last_utc": pl.Datetime("us"),
        "ingested_utc": pl.Datetime("us"),
    }
)
"""Columns of a ``files`` row, as :class:`_Batch` collects them."""

_DIRTY_SCHEMA = pl.Schema(
    {
        "wagon_id": pl.String(),
        "from_utc": pl.Datetime("us"),
        "to_utc": pl.Datetime("us"),
        "file_id": pl.Int64(),
    }
)

_REFRESH_SCHEMA = pl.Schema(
    {"file_id": pl.Int64(), "size_bytes": pl.Int64(), "mtime_ns": pl.Int64()}
)
"""Columns of a ledger refresh (:meth:`_Batch.refresh`)."""


def _file_row(prepared: _Prepared, file_id: int) -> dict[str, object]:
    """The ``files`` row of a prepared file."""
    entry, parsed, problem = prepared.entry, prepared.parsed, prepared.quarantine
    repairs = parsed.repairs if parsed is not None else Repairs()
    return {
        "file_id": file_id,
        "path": entry.relpath,
        "wagon_id": prepared.wagon_id,
        "sha256": prepared.sha256,
        "size_bytes": entry.size_bytes,
        "mtime_ns": entry.mtime_ns,
        "status": "ingested" if parsed is not None else "quarantined",
        "quarantine_code": problem.code if problem else None,
        "reason": problem.reason if problem else None,
        "rows": parsed.frame.height if parsed is not None else 0,
        "rows_in_file": repairs.rows_in_file if parsed is not None else None,
        "rows_no_time": repairs.rows_no_time,
        "rows_outside_session": repairs.rows_outside_session,
        "rows_duplicate": repairs.rows_duplicate,
        "rows_out_of_order": repairs.rows_out_of_order,
        "cells_unparsable": repairs.cells_unparsable,
        "block_temp_faults": repairs.block_temp_faults,
        "partial_row_dropped": repairs.partial_row_dropped,
        "repairs": repairs.text(),
        "first_utc": parsed.first_utc if parsed is not None else None,
        "last_utc": parsed.last_utc if parsed is not None else None,
        "ingested_utc": _utc_now(),
    }


@dataclass(frozen=True)
class _Held:
    """A batch handed to the writer thread (:meth:`_Batch.flush`): its files' rows, samples,
    dirty ranges, the file ids they replace and the ledger refreshes."""

    files: list[dict[str, object]]
    samples: list[pl.DataFrame]
    dirty: list[dict[str, object]]
    replaced: list[int]
    refreshed: list[dict[str, object]]


class _Batch:
    """Partitions of files written together, in one transaction, once they hold
    ``batch_rows`` rows (or ``batch_files`` files).

    A partition, and so a file, is never split: a file's ``files`` row, its samples and its
    dirty time range (and the removal of what its path held before) are in the same
    transaction, with the other files of its partition and batch. Few large inserts are much
    faster in DuckDB than many small ones (full row groups are written straight to the
    database file, in parallel).

    The transactions run on a thread of their own (:class:`~fleetbrake.engine.writer.WriteBehind`),
    one at a time and in order, while the caller gathers the next batch and keeps the
    engine's workers fed (the writer blocked in an insert left them idle: ``write`` was a
    third of the ingestion's seconds, ``docs/benchmarks.md``). The caller must not use the
    warehouse's connection until the block ends (the ingestion's loop does not).
    """

    def __init__(self, wh: Warehouse, config: IngestConfig) -> None:
        self._wh = wh
        self._config = config
        self.write_s = 0.0
        """Seconds the caller waited for its writes (a batch's transaction not yet done when
        the next is handed over, the last one), of the whole ingestion."""
        self._writer: WriteBehind[_Held] = WriteBehind(self._write)
        self._clear()

    def _clear(self) -> None:
        self._files: list[dict[str, object]] = []
        self._samples: list[pl.DataFrame] = []
        self._dirty: list[dict[str, object]] = []
        self._replaced: list[int] = []
        self._refreshed: list[dict[str, object]] = []
        self._rows = 0

    def add(self, prepared: _Prepared, known: _Known | None, file_id: int) -> FileResult:
        """Queue one file (replacing what its path held); see :meth:`end_partition`."""
        row = _file_row(prepared, file_id)
        if known is not None:
            self._replaced.append(known.file_id)
            if known.status == "ingested" and known.first_utc is not None:
                self._dirty.append(
                    _dirty_row(known.wagon_id, known.first_utc, known.last_utc, file_id)
                )
        self._files.append(row)
        parsed = prepared.parsed
        if parsed is not None and parsed.frame.height:
            self._samples.append(
                parsed.frame.with_columns(
                    pl.lit(prepared.wagon_id, dtype=pl.String).alias("wagon_id"),
                    pl.lit(file_id, dtype=pl.Int64).alias("file_id"),
                )
            )
            self._dirty.append(
                _dirty_row(prepared.wagon_id, parsed.first_utc, parsed.last_utc, file_id)
            )
            self._rows += parsed.frame.height
        return FileResult(
            path=prepared.entry.relpath,
            wagon_id=prepared.wagon_id,
            status=str(row["status"]),
            rows=int(row["rows"]),  # type: ignore[call-overload]
            reason=row["reason"],  # type: ignore[arg-type]
            repairs=row["repairs"],  # type: ignore[arg-type]
            replaced=known is not None,
            size_bytes=prepared.entry.size_bytes,
            mtime_ns=prepared.entry.mtime_ns,
        )

    def refresh(self, prepared: _Prepared, known: _Known | None) -> None:
        """The file is recorded with these bytes (:func:`_unchanged`): its ledger row takes
        the size and modification time it has now, if they differ."""
        entry = prepared.entry
        if known is not None and (known.size_bytes, known.mtime_ns) != (
            entry.size_bytes,
            entry.mtime_ns,
        ):
            self._refreshed.append(
                {
                    "file_id": known.file_id,
                    "size_bytes": entry.size_bytes,
                    "mtime_ns": entry.mtime_ns,
                }
            )

    def end_partition(self) -> None:
        """A partition's files are queued: flush when the batch is full. A partition is never
        split between transactions; small ones share one (few large inserts are much faster
        in DuckDB than many small ones)."""
        if self._rows >= self._config.batch_rows or len(self._files) >= self._config.batch_files:
            self.flush()

    def flush(self) -> None:
        """Hand the queued files to the writer thread, to be written in one transaction
        (after the batch before it, which this waits for)."""
        if not self._files and not self._refreshed:
            return
        held = _Held(self._files, self._samples, self._dirty, self._replaced, self._refreshed)
        self._clear()
        began = time.perf_counter()
        self._writer.submit(held)
        self.write_s += time.perf_counter() - began

    def _write(self, held: _Held) -> None:
        """One batch's transaction (on the writer thread)."""
        con = self._wh.con
        files = pl.DataFrame(held.files, schema=_FILES_SCHEMA, orient="row")
        dirty = pl.DataFrame(held.dirty, schema=_DIRTY_SCHEMA, orient="row")
        refreshed = pl.DataFrame(held.refreshed, schema=_REFRESH_SCHEMA, orient="row")
        samples = pl.concat(held.samples) if held.samples else None
        with self._wh.transaction():
            if held.replaced:
                ids = {"ids": held.replaced}
                con.execute(sql("q_ingest_delete_samples"), ids)
                con.execute(sql("q_ingest_delete_files"), ids)
            if files.height:
                _insert(con, "file_batch", files, sql("q_insert_files"))
            if samples is not None:
                _insert(con, "sample_batch", samples, sql("q_insert_samples"))
            if dirty.height:
                _insert(con, "dirty_batch", dirty, sql("q_insert_event_dirty"))
            if refreshed.height:
                _insert(con, "refresh_batch", refreshed, sql("q_ingest_refresh_files"))

    def __enter__(self) -> _Batch:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        """Write what is queued and wait for it (an error: only the batch being written
        ends, nothing more is written)."""
        try:
            if exc_type is None:
                self.flush()
                began = time.perf_counter()
                self._writer.wait()
                self.write_s += time.perf_counter() - began
        finally:
            self._writer.__exit__(exc_type, *rest)


def _insert(con: duckdb.DuckDBPyConnection, name: str, frame: pl.DataFrame, statement: str) -> None:
    """Run ``statement`` with ``frame`` registered as ``name``."""
    con.register(name, frame)
    try:
        con.execute(statement)
    finally:
        con.unregister(name)


def _dirty_row(
    wagon_id: str | None,
    from_utc: dt.datetime | None,
    to_utc: dt.datetime | None,
    file_id: int,
) -> dict[str, object]:
    return {"wagon_id": wagon_id, "from_utc": from_utc, "to_utc": to_utc, "file_id": file_id}


def _unchanged(prepared: _Prepared, known: _Known | None) -> bool:
    """The file is recorded with these bytes and would be recorded the same way again."""
    if known is None or known.sha256 != prepared.sha256:
        return False
    if known.quarantine_code not in _RETRIED_CODES:
        return True
    problem = prepared.quarantine
    return problem is not None and (problem.code, problem.reason) == (
        known.quarantine_code,
        known.reason,
    )


@dataclass(frozen=True)
class _FilePartition:
    """A worker's unit of work: some new files of one wagon directory, in path order, with
    what the registry says about the wagons their names give (judged by the parent, so the
    registry is not shipped to every worker)."""

    entries: tuple[LogEntry, ...]
    problems: Mapping[str, str | None]

    def __str__(self) -> str:
        first = self.entries[0].relpath
        return f"{first.rsplit('/', 1)[0]} ({len(self.entries)} files from {first})"


def _partitions(
    entries: list[LogEntry], registry: Registry, config: IngestConfig
) -> Iterator[_FilePartition]:
    """``entries`` (sorted by path) cut into runs of one directory of at most
    ``partition_files`` files: the order of the files is kept across partitions."""
    for _, group in itertools.groupby(entries, key=lambda e: e.relpath.rsplit("/", 1)[0]):
        files = list(group)
        for start in range(0, len(files), max(1, config.partition_files)):
            chunk = tuple(files[start : start + max(1, config.partition_files)])
            wagons = set()
            for entry in chunk:
                try:
                    wagons.add(parse_log_path(entry.relpath).wagon_id)
                except LogNameError:
                    pass
            yield _FilePartition(chunk, {w: _registry_problem(registry, w) for w in wagons})


def _prepare_partition(partition: _FilePartition, config: IngestConfig) -> list[_Prepared | None]:
    """Read, hash, judge and parse a partition's files, in order (a pure function of the
    files: runs in an engine's worker, or on a thread of this process)."""
    return [_prepare(entry, partition.problems, config) for entry in partition.entries]


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
    what raises); bad files never raise (they are quarantined). ``progress=None`` shows a
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
    report = IngestReport(
        fleet_dir=fleet_dir,
        db_path=wh.path,
        registry_problems=[str(p) for p in registry.problems],
    )
    entries = scan_logs(fleet_dir) if files is None else stat_logs(fleet_dir, files)
    report.files_seen = len(entries)
    known = _known_files(wh)
    todo = [e for e in entries if _needs_reading(e, known.get(e.relpath), config)]
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
            _Batch(wh, config) as batch,
        ):
            for partition in engine.map(
                functools.partial(_prepare_partition, config=config),
                _partitions(todo, registry, config),
            ):
                for prepared in partition:
                    if prepared is None:  # removed since the scan
                        report.files_seen -= 1
                        bar.advance(0)
                        continue
                    before = known.get(prepared.entry.relpath)
                    if _unchanged(prepared, before):
                        report.files_unchanged += 1
                        batch.refresh(prepared, before)
                    else:
                        report.results.append(batch.add(prepared, before, next_id))
                        next_id += 1
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
    database is touched) and :class:`~fleetbrake.warehouse.connection.WarehouseError` (locked, unusable,
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
        f"{len(ingested)} ingested ({report.rows:,} rows), {len(quarantined)} quarantined, "
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
