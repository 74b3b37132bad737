"""The on-board log file format of ``shared/spec/fleet-data.md``: the one implementation.

Everything that knows what a log file looks like lives here: the column names, the range of
values each channel can physically take (:data:`PLAUSIBLE_RANGES`), the file-name convention
``logs/<wagon_id>/<wagon_id>_<YYYYMMDDTHHMMSSZ>.csv[.gz]`` (parse and build), and a writer
that turns one session (a polars frame) into exactly the bytes a unit writes::

    write_log(fleet / log_relpath("SGG-0001", start_utc, gzip=True), frame)

The imperfections real units produce (missing and duplicated rows, empty cells, truncated
files, sensor faults, ...) are made on purpose, for synthetic fleets and tests, apart from the
format: ``fleetbrake.synth.corrupt``.
"""

from __future__ import annotations

import datetime as dt
import gzip as gzip_module
import os
import re
import secrets
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from types import MappingProxyType

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
    "complete_rows",
    "gzip_bytes",
    "log_name",
    "log_relpath",
    "parse_log_name",
    "parse_log_path",
    "to_csv_bytes",
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


def fsync_directory(path: Path) -> None:
    """Flush a directory's entries to disk (a rename or a new entry in it survives a power cut)."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def make_directories(path: Path, *, durable: bool = False) -> None:
    """``mkdir -p path``; ``durable``: each directory made is flushed into its parent."""
    missing: list[Path] = []
    here = path
    while not here.is_dir():
        missing.append(here)
        here = here.parent
    for directory in reversed(missing):
        try:
            directory.mkdir()
        except FileExistsError:
            continue
        if durable:
            fsync_directory(directory.parent)


def write_log(
    path: str | os.PathLike[str],
    frame: pl.DataFrame | bytes,
    *,
    gzip: bool | None = None,
    level: int = 6,
    durable: bool = False,
    tag: str | None = None,
) -> Path:
    """Write one session (a frame, or CSV bytes from an injector) to ``path``.

    ``gzip=None`` compresses when the name ends in ``.gz``. Parent directories are made. The
    file appears complete or not at all: it is written to a hidden temporary name in the same
    directory (which the ingestion ignores), ``.<name>.<tag>.tmp``, and renamed into place.
    ``tag`` defaults to the process id and a random token, so concurrent writers never share
    a temporary file; a writer that cleans up after a crash of its own names its tag.
    ``durable``: the file is flushed to disk before the rename, and the directory after it
    (what a service that acknowledges data once it is written needs).
    """
    path = Path(path)
    data = to_csv_bytes(frame) if isinstance(frame, pl.DataFrame) else bytes(frame)
    if gzip is None:
        gzip = path.name.endswith(".gz")
    if gzip:
        data = gzip_bytes(data, level=level)
    make_directories(path.parent, durable=durable)
    tag = tag if tag is not None else f"{os.getpid()}.{secrets.token_hex(4)}"
    temporary = path.with_name(f".{path.name}.{tag}.tmp")
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        if durable:
            os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(temporary, path)
    if durable:
        fsync_directory(path.parent)
    return path


def complete_rows(csv_bytes: bytes) -> int:
    """Number of complete data rows (ending in a newline) of plain CSV bytes with a header."""
    return max(csv_bytes.count(b"\n") - 1, 0)
