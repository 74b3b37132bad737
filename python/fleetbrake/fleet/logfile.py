"""The on-board log file format of ``shared/spec/fleet-data.md``: the one implementation.

Everything that knows what a log file looks like lives here: the column names, the range of
values each channel can physically take (:data:`PLAUSIBLE_RANGES`), the file-name convention
``logs/<wagon_id>/<wagon_id>_<YYYYMMDDTHHMMSSZ>.csv[.gz]`` (parse and build), a writer that
turns one session (a polars frame) into exactly the bytes a unit writes, and the imperfections
real units produce, as small pure functions that a synthetic-fleet generator and the tests
combine::

    rng = np.random.default_rng(7)
    frame = swap_neighbours(duplicate_rows(drop_gap(session, rng, gap_s=90), rng, 0.01), rng, 0.01)
    frame = pt1000_open_circuit(frame, rng, duration_s=300)
    write_log(fleet / log_relpath("SGG-0001", start_utc, gzip=True), frame)

    data = truncate_mid_row(to_csv_bytes(frame), rng)      # a unit that lost power
    (fleet / "logs/SGG-0001/SGG-0001_20240301T060000Z.csv").write_bytes(data)

Every frame-level injector takes a frame and a seeded :class:`numpy.random.Generator` and returns
a new frame; the byte-level ones take and return bytes. None of them mutates its input.
"""

from __future__ import annotations

import datetime as dt
import gzip as gzip_module
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from types import MappingProxyType

import numpy as np
import polars as pl

from fleetbrake.errors import FleetbrakeError
from fleetbrake.fleet.registry import WAGON_ID_PATTERN

__all__ = [
    "BLOCK_TEMP_VALID_C",
    "COLUMNS",
    "FLOAT_COLUMNS",
    "LOG_NAME_PATTERN",
    "OPTIONAL_COLUMNS",
    "PLAUSIBLE_RANGES",
    "REQUIRED_COLUMNS",
    "TIME_FORMAT",
    "WAGON_ID_PATTERN",
    "LogName",
    "LogNameError",
    "blank_cells",
    "complete_rows",
    "drop_gap",
    "drop_rows",
    "duplicate_rows",
    "freeze_speed",
    "garbage_bytes",
    "garble_cells",
    "gzip_bytes",
    "jump_speed",
    "log_name",
    "log_relpath",
    "parse_log_name",
    "parse_log_path",
    "pt1000_drift_to_ambient",
    "pt1000_frozen",
    "pt1000_open_circuit",
    "swap_neighbours",
    "to_csv_bytes",
    "truncate_gzip",
    "truncate_mid_row",
    "write_log",
]

# --------------------------------------------------------------------------------------------
# Columns

REQUIRED_COLUMNS: tuple[str, ...] = (
    "time_utc",
    "speed_kmh",
    "distance_m",
    "elevation_m",
    "lat_deg",
    "lon_deg",
    "brake_pressure_bar",
    "block_temp_c",
)
"""Columns every log file has (in any order)."""

OPTIONAL_COLUMNS: tuple[str, ...] = ("ambient_temp_c",)
"""Columns a log file may have; absent means empty."""

COLUMNS: tuple[str, ...] = REQUIRED_COLUMNS + OPTIONAL_COLUMNS
"""Every column fleetbrake reads, in the order its own writer puts them."""

FLOAT_COLUMNS: tuple[str, ...] = COLUMNS[1:]
"""The numeric columns ('.' decimal; empty cell = no value)."""

TIME_FORMAT = "%Y-%m-%dT%H:%M:%SZ"
"""``time_utc`` cells: ISO 8601 UTC, whole seconds, e.g. ``2024-03-01T06:00:00Z``."""

BLOCK_TEMP_VALID_C: tuple[float, float] = (-60.0, 600.0)
"""A Pt1000 reading outside this closed range is a broken wire, not a temperature."""

PLAUSIBLE_RANGES: Mapping[str, tuple[float, float]] = MappingProxyType(
    {
        # GPS ground speed: never negative; no train runs at 350 km/h, and a GPS jump of some
        # tens of km/h stays inside (the event detection's running median deals with it)
        "speed_kmh": (0.0, 350.0),
        # since the session began, non-decreasing: at most 48 h (a session's longest) at 350 km/h
        "distance_m": (0.0, 2.0e7),
        # GPS altitude: below the lowest land (Dead Sea, -430 m) or above any railway (5,072 m),
        # with room for a poor fix, is not a position
        "elevation_m": (-1_000.0, 9_000.0),
        "lat_deg": (-90.0, 90.0),
        "lon_deg": (-180.0, 180.0),
        # gauge pressure: -1 bar is a vacuum; no wagon's air system holds more than 10 bar
        "brake_pressure_bar": (-1.0, 12.0),
        # outside: a broken Pt1000 wire, kept as a fault (not cleared, see below)
        "block_temp_c": BLOCK_TEMP_VALID_C,
        # air where wagons run: the coldest and hottest ever measured lie within
        "ambient_temp_c": (-90.0, 60.0),
    }
)
"""The closed range of values each numeric channel can physically take, in its unit.

A cell outside is not a measurement (a speed of 1e308 km/h, a pressure of -5 bar): the
ingestion records it as it records a cell that is not a number (counted in
``files.cells_unparsable``, described with its line in ``files.repairs``) and stores the cell
empty. ``block_temp_c`` is the exception the format describes: a reading outside
:data:`BLOCK_TEMP_VALID_C` is a broken wire, stored as a fault with its raw value. ``time_utc``
has its own range, the session's: from the file name's time to 48 h after it.
"""

# --------------------------------------------------------------------------------------------
# File names

_STAMP_FORMAT = "%Y%m%dT%H%M%SZ"

LOG_NAME_PATTERN = re.compile(
    rf"(?P<wagon_id>{WAGON_ID_PATTERN.pattern})_(?P<stamp>\d{{8}}T\d{{6}}Z)\.csv(?P<gz>\.gz)?"
)
"""``<wagon_id>_<YYYYMMDDTHHMMSSZ>.csv[.gz]`` (whole name)."""


class LogNameError(FleetbrakeError, ValueError):
    """A path that does not follow the log file-name convention; the message names it."""


@dataclass(frozen=True)
class LogName:
    """What a log file's path says: whose, when its session began, and whether it is gzip."""

    wagon_id: str
    start_utc: dt.datetime
    """First sample of the session, naive UTC."""
    gzip: bool

    @property
    def name(self) -> str:
        """The file name, ``<wagon_id>_<YYYYMMDDTHHMMSSZ>.csv[.gz]``."""
        return log_name(self.wagon_id, self.start_utc, gzip=self.gzip)

    @property
    def relpath(self) -> PurePosixPath:
        """``logs/<wagon_id>/<name>``, relative to the fleet directory."""
        return log_relpath(self.wagon_id, self.start_utc, gzip=self.gzip)


def _naive_utc(time_utc: dt.datetime) -> dt.datetime:
    if time_utc.tzinfo is not None:
        time_utc = time_utc.astimezone(dt.UTC).replace(tzinfo=None)
    return time_utc


def log_name(wagon_id: str, start_utc: dt.datetime, *, gzip: bool) -> str:
    """File name of the session of ``wagon_id`` whose first sample is ``start_utc``."""
    if not WAGON_ID_PATTERN.fullmatch(wagon_id):
        raise LogNameError(f"wagon id {wagon_id!r} does not match {WAGON_ID_PATTERN.pattern}")
    stamp = _naive_utc(start_utc).strftime(_STAMP_FORMAT)
    return f"{wagon_id}_{stamp}.csv" + (".gz" if gzip else "")


def log_relpath(wagon_id: str, start_utc: dt.datetime, *, gzip: bool) -> PurePosixPath:
    """Path of a session's file relative to the fleet directory: ``logs/<wagon>/<name>``."""
    return PurePosixPath("logs", wagon_id, log_name(wagon_id, start_utc, gzip=gzip))


def parse_log_name(name: str) -> LogName:
    """Read a file name (no directory) of the convention; :class:`LogNameError` otherwise."""
    match = LOG_NAME_PATTERN.fullmatch(name)
    if match is None:
        raise LogNameError(
            f"{name}: file name does not follow <wagon_id>_<YYYYMMDDTHHMMSSZ>.csv[.gz]"
        )
    try:
        start_utc = dt.datetime.strptime(match["stamp"], _STAMP_FORMAT)
    except ValueError:
        raise LogNameError(
            f"{name}: {match['stamp']} in the file name is not a valid UTC time"
        ) from None
    return LogName(match["wagon_id"], start_utc, gzip=match["gz"] is not None)


def parse_log_path(relpath: str | PurePosixPath) -> LogName:
    """Read a path relative to the fleet directory: ``logs/<wagon_id>/<wagon_id>_<stamp>.csv[.gz]``.

    The wagon directory must be the wagon of the file name; :class:`LogNameError` (naming the
    path) otherwise.
    """
    parts = PurePosixPath(relpath).parts
    if len(parts) != 3 or parts[0] != "logs":
        raise LogNameError(f"{relpath}: a log file must be at logs/<wagon_id>/<file name>")
    try:
        parsed = parse_log_name(parts[2])
    except LogNameError as error:
        raise LogNameError(f"{relpath}: {str(error).split(': ', 1)[1]}") from None
    if parsed.wagon_id != parts[1]:
        raise LogNameError(
            f"{relpath}: file of wagon {parsed.wagon_id} in the directory of wagon {parts[1]}"
        )
    return parsed


# --------------------------------------------------------------------------------------------
# Writer


def to_csv_bytes(frame: pl.DataFrame) -> bytes:
    """One session as the CSV bytes a unit writes: header, one row per frame row, '\\n' ends.

    Columns are written in the frame's order (the format allows any). A datetime ``time_utc``
    is written as ``YYYY-MM-DDTHH:MM:SSZ``; a string column is written as it is (that is how
    an injector puts a non-parsable value in); nulls are empty cells. Floats are written in
    their shortest round-trip form. No quoting.
    """
    if frame.width == 0:
        raise ValueError("a log file needs at least one column")
    exprs = []
    for name, dtype in frame.schema.items():
        if dtype.is_temporal():
            exprs.append(pl.col(name).dt.strftime(TIME_FORMAT))
        else:
            exprs.append(pl.col(name))
    text = frame.select(exprs).write_csv(null_value="", quote_style="never", line_terminator="\n")
    return text.encode("utf-8")


def gzip_bytes(data: bytes, *, level: int = 6) -> bytes:
    """``data`` as one gzip member, deterministic (no time stamp, no file name)."""
    return gzip_module.compress(data, compresslevel=level, mtime=0)


def write_log(
    path: str | os.PathLike[str],
    frame: pl.DataFrame | bytes,
    *,
    gzip: bool | None = None,
    level: int = 6,
) -> Path:
    """Write one session (a frame, or CSV bytes from an injector) to ``path``.

    ``gzip=None`` compresses when the name ends in ``.gz``. Parent directories are made. The
    file appears complete or not at all: it is written to a hidden temporary name in the same
    directory (which the ingestion ignores) and renamed.
    """
    path = Path(path)
    data = to_csv_bytes(frame) if isinstance(frame, pl.DataFrame) else bytes(frame)
    if gzip is None:
        gzip = path.name.endswith(".gz")
    if gzip:
        data = gzip_bytes(data, level=level)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    temporary.write_bytes(data)
    os.replace(temporary, path)
    return path


def complete_rows(csv_bytes: bytes) -> int:
    """Number of complete data rows (ending in a newline) of plain CSV bytes with a header."""
    return max(csv_bytes.count(b"\n") - 1, 0)


# --------------------------------------------------------------------------------------------
# Imperfections: frame level


def _pick(rng: np.random.Generator, n: int, fraction: float, *, low: int = 0) -> np.ndarray:
    """Sorted distinct row indices in ``[low, n)``, about ``fraction`` of the rows."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must be in [0, 1], got {fraction}")
    available = n - low
    if available <= 0:
        return np.empty(0, dtype=np.int64)
    count = round(fraction * available)
    return np.sort(rng.choice(available, size=count, replace=False)) + low


def _span(
    rng: np.random.Generator, n: int, length: int, start: int | None, *, low: int = 0
) -> tuple[int, int]:
    """A run of ``length`` rows ``[start, stop)``, random where ``start`` is None."""
    length = max(0, min(length, n - low))
    if start is None:
        start = int(rng.integers(low, n - length + 1)) if n - length >= low else low
    return start, min(start + length, n)


def drop_rows(frame: pl.DataFrame, rng: np.random.Generator, fraction: float) -> pl.DataFrame:
    """Missing samples: about ``fraction`` of the rows (never the first) removed, scattered."""
    gone = _pick(rng, frame.height, fraction, low=1)
    keep = np.ones(frame.height, dtype=bool)
    keep[gone] = False
    return frame.filter(pl.Series(keep))


def drop_gap(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    gap_s: int,
    *,
    start: int | None = None,
) -> pl.DataFrame:
    """A gap: ``gap_s`` consecutive rows removed (never the first row), at row ``start`` or anywhere."""
    first, stop = _span(rng, frame.height, gap_s, start, low=1)
    return pl.concat([frame.slice(0, first), frame.slice(stop)])


def duplicate_rows(frame: pl.DataFrame, rng: np.random.Generator, fraction: float) -> pl.DataFrame:
    """Duplicated samples: about ``fraction`` of the rows written twice, the copy right after."""
    twice = _pick(rng, frame.height, fraction)
    counts = np.ones(frame.height, dtype=np.int64)
    counts[twice] = 2
    order = np.repeat(np.arange(frame.height), counts)
    return frame[order]


def swap_neighbours(frame: pl.DataFrame, rng: np.random.Generator, fraction: float) -> pl.DataFrame:
    """Slightly out of order: about ``fraction`` of the rows swapped with the next one.

    Swaps never overlap and never move the first row (whose time names the file).
    """
    order = np.arange(frame.height)
    if frame.height < 3:
        return frame.clone()
    candidates = _pick(rng, frame.height - 1, fraction, low=1)
    last = -2
    for i in candidates:
        if i > last + 1:
            order[i], order[i + 1] = order[i + 1], order[i]
            last = i
    return frame[order]


def blank_cells(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    fraction: float,
    columns: tuple[str, ...] | None = None,
) -> pl.DataFrame:
    """Empty cells: in each of ``columns`` (default: every column), about ``fraction`` of the
    cells set to null (written as empty)."""
    columns = tuple(frame.columns) if columns is None else columns
    updates = []
    for name in columns:
        blank = np.zeros(frame.height, dtype=bool)
        blank[_pick(rng, frame.height, fraction)] = True
        updates.append(pl.when(pl.Series(blank)).then(None).otherwise(pl.col(name)).alias(name))
    return frame.with_columns(updates)


def garble_cells(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    fraction: float,
    columns: tuple[str, ...],
    *,
    text: str = "#VALUE!",
) -> pl.DataFrame:
    """Non-parsable values: about ``fraction`` of the cells of ``columns`` replaced by ``text``.

    The columns become strings (a datetime ``time_utc`` formatted as the writer would).
    """
    updates = []
    for name in columns:
        garbled = np.zeros(frame.height, dtype=bool)
        garbled[_pick(rng, frame.height, fraction)] = True
        column = pl.col(name)
        if frame.schema[name].is_temporal():
            as_text = column.dt.strftime(TIME_FORMAT)
        else:
            as_text = column.cast(pl.String)
        updates.append(
            pl.when(pl.Series(garbled)).then(pl.lit(text)).otherwise(as_text).alias(name)
        )
    return frame.with_columns(updates)


def freeze_speed(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    duration_s: int,
    *,
    start: int | None = None,
) -> pl.DataFrame:
    """GPS speed frozen while the fix is poor: ``duration_s`` rows repeat the speed of the first."""
    return _freeze(frame, "speed_kmh", rng, duration_s, start)


def _freeze(
    frame: pl.DataFrame,
    column: str,
    rng: np.random.Generator,
    duration_s: int,
    start: int | None,
) -> pl.DataFrame:
    """``duration_s`` rows of ``column`` (a span drawn by :func:`_span`) repeat the first's value."""
    first, stop = _span(rng, frame.height, duration_s, start)
    values = frame[column].to_numpy().copy()
    values[first:stop] = values[first]
    return frame.with_columns(pl.Series(column, values, dtype=pl.Float64))


def jump_speed(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    count: int,
    *,
    jump_kmh: float = 60.0,
    max_length_s: int = 3,
) -> pl.DataFrame:
    """GPS speed jumps: ``count`` short runs (1..``max_length_s`` rows) off by ±``jump_kmh``,
    never below zero."""
    speed = frame["speed_kmh"].to_numpy().copy()
    for _ in range(count):
        length = int(rng.integers(1, max_length_s + 1))
        first, stop = _span(rng, frame.height, length, None)
        sign = 1.0 if rng.random() < 0.5 else -1.0
        speed[first:stop] = np.maximum(speed[first:stop] + sign * jump_kmh, 0.0)
    return frame.with_columns(pl.Series("speed_kmh", speed, dtype=pl.Float64))


def pt1000_open_circuit(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    duration_s: int,
    *,
    start: int | None = None,
    reading_c: float | None = None,
) -> pl.DataFrame:
    """A broken Pt1000 wire: ``duration_s`` rows read far out of range.

    ``reading_c`` defaults to a random value above 600 °C (open wire) or below -60 °C (short).
    """
    first, stop = _span(rng, frame.height, duration_s, start)
    if reading_c is None:
        reading_c = float(
            rng.uniform(850.0, 1200.0) if rng.random() < 0.5 else rng.uniform(-250.0, -200.0)
        )
    temp_c = frame["block_temp_c"].to_numpy().copy()
    temp_c[first:stop] = reading_c
    return frame.with_columns(pl.Series("block_temp_c", temp_c, dtype=pl.Float64))


def pt1000_frozen(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    duration_s: int,
    *,
    start: int | None = None,
) -> pl.DataFrame:
    """A loose Pt1000 reading a frozen value: ``duration_s`` rows repeat the first one's reading."""
    return _freeze(frame, "block_temp_c", rng, duration_s, start)


def pt1000_drift_to_ambient(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    *,
    tau_s: float = 600.0,
    ambient_c: float | None = None,
    start: int | None = None,
) -> pl.DataFrame:
    """A Pt1000 coming loose: from row ``start`` (random if None) on, the reading decouples from
    the block and relaxes towards ambient with time constant ``tau_s``.

    ``ambient_c`` defaults to the frame's ``ambient_temp_c`` (row by row), else 10 °C.
    """
    first, _ = _span(rng, frame.height, 1, start)
    temp_c = frame["block_temp_c"].to_numpy().copy()
    if ambient_c is not None:
        ambient = np.full(frame.height, ambient_c)
    elif "ambient_temp_c" in frame.columns:
        ambient = frame["ambient_temp_c"].fill_null(10.0).to_numpy().astype(np.float64)
    else:
        ambient = np.full(frame.height, 10.0)
    elapsed_s = np.arange(frame.height - first, dtype=np.float64)
    weight = np.exp(-elapsed_s / tau_s)
    temp_c[first:] = weight * temp_c[first:] + (1.0 - weight) * ambient[first:]
    return frame.with_columns(pl.Series("block_temp_c", temp_c, dtype=pl.Float64))


# --------------------------------------------------------------------------------------------
# Imperfections: byte level


def truncate_mid_row(csv_bytes: bytes, rng: np.random.Generator) -> bytes:
    """A unit that lost power: plain CSV cut inside a random data row (not at its end).

    The result keeps :func:`complete_rows` complete rows and ends in a partial one. Needs at
    least one data row.
    """
    line_ends = np.flatnonzero(np.frombuffer(csv_bytes, dtype=np.uint8) == ord("\n"))
    if len(line_ends) < 2:
        raise ValueError("truncate_mid_row needs a header and at least one data row")
    row = int(rng.integers(1, len(line_ends)))  # data row: between line_ends[row-1] and [row]
    row_start, row_end = int(line_ends[row - 1]) + 1, int(line_ends[row])
    if row_end - row_start < 2:
        return csv_bytes[:row_start]
    cut = int(rng.integers(row_start + 1, row_end))
    return csv_bytes[:cut]


def truncate_gzip(gz_bytes: bytes, rng: np.random.Generator) -> bytes:
    """A gzip file cut mid-stream (between 10 % and 90 % of its length)."""
    if len(gz_bytes) < 20:
        raise ValueError("truncate_gzip needs a gzip stream of at least 20 bytes")
    cut = int(rng.integers(int(0.1 * len(gz_bytes)) + 10, int(0.9 * len(gz_bytes))))
    return gz_bytes[:cut]


def garbage_bytes(rng: np.random.Generator, size: int = 4096, *, kind: str = "binary") -> bytes:
    """A file that is not CSV at all.

    ``kind="binary"``: random bytes. ``"text"``: readable lines that are no log (an error
    page). ``"zeros"``: NUL bytes (a file system that lost its data).
    """
    if kind == "binary":
        return rng.bytes(size)
    if kind == "zeros":
        return bytes(size)
    if kind == "text":
        words = ["error", "unit", "restart", "flash", "sector", "retry", "ok", "0x1f", "boot"]
        lines: list[str] = []
        while sum(len(line) + 1 for line in lines) < size:
            lines.append(" ".join(str(w) for w in rng.choice(words, size=int(rng.integers(3, 9)))))
        return ("\n".join(lines) + "\n").encode()[:size]
    raise ValueError(f"kind must be 'binary', 'text' or 'zeros', got {kind!r}")
