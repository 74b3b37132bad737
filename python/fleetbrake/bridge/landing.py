"""The landing folder: where the bridge's sessions become log files, durably and once.

**Durable, never partial.** A session's file is written under a hidden temporary name in its
wagon's directory (``logs/<wagon>/.<name>.<client id>.tmp``: the ingestion and the watcher
ignore hidden names), flushed to disk (``fsync``), renamed to its name of the format
(``logs/<wagon>/<wagon>_<YYYYMMDDTHHMMSSZ>.csv[.gz]``, the time of its first sample), and the
directory is flushed too (``fsync``: the rename itself survives a power cut). Directories it
makes are flushed into their parents. Only then does :meth:`LandingFolder.write` return, and
only then are the messages whose samples the file holds acknowledged.

**Once.** MQTT's QoS 1 delivers a message at least once: after a crash, the messages not yet
acknowledged come again, some of whose samples may already be in a file (written just before
the crash). The landing folder itself is the bridge's durable state: before a session is
written, the wagon's files that may hold any of its seconds (named up to ``lookback_s``
before its first sample, up to its last) are read, and the samples at seconds they hold are
dropped. So a second of a wagon lands in at most one file, whatever was redelivered, and the
warehouse holds each sample once (the ingestion drops repeated times within a file, and the
bridge never repeats one across files). What a file holds is remembered while its size and
time stamp stay the same (a file, once complete, never changes): its seconds for the files
read last, its first and last second for many more, so that a file whose span lies outside
a session is not read again.

**Deterministic.** The same samples make the same file, name and bytes: rows sorted by time,
every column of the format in its order, numbers in their shortest exact form, gzip without a
time stamp.

One bridge per client id and landing folder: :meth:`LandingFolder.open` takes a lock
(``<landing>/.fleetbrake-bridge-<client id>.lock``) for as long as the bridge runs.
"""

from __future__ import annotations

import collections
import datetime as dt
import fcntl
import gzip as gzip_module
import io
import logging
import os
import zlib
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np
import polars as pl

from fleetbrake.bridge.payload import EPOCH_UTC, Row, utc_of
from fleetbrake.errors import EXIT_LOCKED, FleetbrakeError
from fleetbrake.fleet.logfile import (
    COLUMNS,
    FLOAT_COLUMNS,
    TIME_FORMAT,
    LogNameError,
    gzip_bytes,
    log_name,
    parse_log_name,
    to_csv_bytes,
    write_log,
)

if TYPE_CHECKING:
    from fleetbrake.bridge.config import BridgeConfig

__all__ = ["LandingBusyError", "LandingError", "LandingFolder", "Written"]

logger = logging.getLogger(__name__)

LOGS_DIR = "logs"
_GZIP_MAGIC = b"\x1f\x8b"
_CACHE_FILES = 512
"""Files whose seconds are remembered (at most 48 h of samples each, as int64)."""
_CACHE_SPANS = 1 << 17
"""Files whose first and last seconds are remembered (which files a session must read)."""


class LandingError(FleetbrakeError):
    """The landing folder cannot be used or written (exit 1); the message names the path."""


class LandingBusyError(FleetbrakeError):
    """Another bridge with the same client id is writing into the landing folder (exit 75:
    try again once it has stopped)."""

    exit_code = EXIT_LOCKED


@dataclass(frozen=True)
class Written:
    """What became of one session."""

    path: Path | None
    """The file written; None when every sample was in the landing folder already."""
    rows: int
    duplicates: int
    """Samples dropped: their second is in a file of the wagon already."""
    conflicts: int
    """Samples dropped because a file that is not the bridge's holds their file name."""


def session_frame(rows: dict[int, Row], seconds: np.ndarray) -> pl.DataFrame:
    """The samples at ``seconds`` (sorted) as a frame of the log format's columns."""
    values = list(zip(*(rows[int(s)] for s in seconds), strict=True))
    micros = seconds.astype(np.int64) * 1_000_000
    data: dict[str, pl.Series] = {
        "time_utc": pl.Series("time_utc", micros, dtype=pl.Int64).cast(pl.Datetime("us"))
    }
    for i, name in enumerate(FLOAT_COLUMNS):
        data[name] = pl.Series(name, values[i], dtype=pl.Float64)
    return pl.DataFrame(data).select(COLUMNS)


class LandingFolder:
    """A fleet directory that receives log files (see the module's doc)."""

    def __init__(
        self, root: Path, client_id: str, *, gzip: bool = False, lookback_s: float = 48 * 3600
    ) -> None:
        self.root = Path(root)
        self.client_id = client_id
        self.gzip = gzip
        self.lookback_s = lookback_s
        self._lock_fd: int | None = None
        self._seconds: collections.OrderedDict[Path, tuple[tuple[int, int], np.ndarray]] = (
            collections.OrderedDict()
        )
        self._spans: collections.OrderedDict[Path, tuple[tuple[int, int], tuple[int, int]]] = (
            collections.OrderedDict()
        )
        self._cleaned: set[str] = set()
        self._tmp_suffix = f".{client_id}.tmp"  # what write_log names its temporary with our tag

    @classmethod
    def of(cls, config: BridgeConfig) -> LandingFolder:
        """The landing folder of a bridge's settings (not opened yet)."""
        return cls(config.landing, config.client_id, gzip=config.gzip, lookback_s=config.lookback_s)

    # ------------------------------------------------------------------ lock

    def open(self) -> LandingFolder:
        """Check the folder and take the bridge's lock on it."""
        if not self.root.is_dir():
            raise LandingError(f"{self.root}: no such landing folder (a fleet directory)")
        lock_path = self.root / f".fleetbrake-bridge-{self.client_id}.lock"
        try:
            fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as error:
            raise LandingError(f"{lock_path}: cannot open the bridge's lock ({error})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise LandingBusyError(
                f"{self.root}: another bridge with client id {self.client_id} is writing here "
                f"(it holds {lock_path.name})"
            ) from None
        self._lock_fd = fd
        return self

    def close(self) -> None:
        """Release the lock."""
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def __enter__(self) -> LandingFolder:
        return self.open()

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ writing

    def write(self, wagon_id: str, rows: dict[int, Row]) -> Written:
        """Write one session of ``wagon_id`` (second -> values), less the seconds that the
        wagon's files hold already, durably; :class:`LandingError` naming the file if the
        disk refuses."""
        seconds = np.array(sorted(rows), dtype=np.int64)
        held = self._seconds_held(wagon_id, int(seconds[0]), int(seconds[-1]))
        fresh = seconds[~np.isin(seconds, held)]
        duplicates = len(seconds) - len(fresh)
        conflicts = 0
        directory = self.root / LOGS_DIR / wagon_id
        while len(fresh):
            path = directory / log_name(wagon_id, utc_of(int(fresh[0])), gzip=self.gzip)
            if not path.exists():
                break
            # a file by this name that does not hold its first second is not one of ours
            logger.error(
                "%s: exists and does not hold the sample of %s at %s: sample dropped",
                path,
                wagon_id,
                utc_of(int(fresh[0])).strftime(TIME_FORMAT),
            )
            fresh = fresh[1:]
            conflicts += 1
        if not len(fresh):
            return Written(None, 0, duplicates, conflicts)
        data = to_csv_bytes(session_frame(rows, fresh))
        if self.gzip:
            data = gzip_bytes(data)
        try:
            self._write_durably(path, data)
        except OSError as error:
            raise LandingError(f"{path}: cannot be written ({error})") from error
        self._remember(path, fresh)
        return Written(path, len(fresh), duplicates, conflicts)

    def _write_durably(self, path: Path, data: bytes) -> None:
        write_log(path, data, gzip=False, durable=True, tag=self.client_id)

    # ------------------------------------------------------------------ what is held

    def _seconds_held(self, wagon_id: str, first_s: int, last_s: int) -> np.ndarray:
        """Seconds from ``first_s`` to ``last_s`` held by the wagon's files (those named from
        ``lookback_s`` before ``first_s`` to ``last_s``)."""
        directory = self.root / LOGS_DIR / wagon_id
        try:
            entries = list(os.scandir(directory))
        except FileNotFoundError:
            return np.empty(0, dtype=np.int64)
        except OSError as error:
            raise LandingError(f"{directory}: cannot be listed ({error})") from error
        clean = wagon_id not in self._cleaned
        self._cleaned.add(wagon_id)
        held: list[np.ndarray] = []
        for entry in entries:
            if entry.name.startswith("."):
                if clean and entry.name.endswith(self._tmp_suffix):
                    # left by a bridge of this client id that was killed while writing
                    Path(entry.path).unlink(missing_ok=True)
                continue
            try:
                name = parse_log_name(entry.name)
            except LogNameError:
                continue
            start_s = (name.start_utc - EPOCH_UTC) // dt.timedelta(seconds=1)
            if name.wagon_id == wagon_id and first_s - self.lookback_s <= start_s <= last_s:
                seconds = self._file_seconds(Path(entry.path), first_s, last_s)
                if seconds is not None:
                    held.append(seconds)
        return np.unique(np.concatenate(held)) if held else np.empty(0, dtype=np.int64)

    def _remember(self, path: Path, seconds: np.ndarray) -> None:
        """Note a file's seconds (and its span, kept longer: it decides which files to read)."""
        stat = path.stat()
        identity = (stat.st_size, stat.st_mtime_ns)
        span = (int(seconds[0]), int(seconds[-1])) if len(seconds) else (1, 0)
        self._seconds[path] = (identity, seconds)
        self._seconds.move_to_end(path)
        while len(self._seconds) > _CACHE_FILES:
            self._seconds.popitem(last=False)
        self._spans[path] = (identity, span)
        self._spans.move_to_end(path)
        while len(self._spans) > _CACHE_SPANS:
            self._spans.popitem(last=False)

    def _file_seconds(self, path: Path, first_s: int, last_s: int) -> np.ndarray | None:
        """The seconds of a log file's rows; None when the file holds none from ``first_s``
        to ``last_s`` (as far as its span, remembered, tells without reading it)."""
        try:
            stat = path.stat()
        except FileNotFoundError:
            return None
        identity = (stat.st_size, stat.st_mtime_ns)
        span = self._spans.get(path)
        if span is not None and span[0] == identity:
            self._spans.move_to_end(path)
            low, high = span[1]
            if high < first_s or low > last_s:
                return None
        cached = self._seconds.get(path)
        if cached is not None and cached[0] == identity:
            self._seconds.move_to_end(path)
            return cached[1]
        seconds = read_seconds(path)
        self._remember(path, seconds)
        return seconds


def read_seconds(path: Path) -> np.ndarray:
    """The distinct ``time_utc`` of a log file's rows, as seconds since 1970 (sorted); none
    when the file cannot be read (logged), rows whose time is not one are left out."""
    try:
        data = path.read_bytes()
        if data.startswith(_GZIP_MAGIC):
            data = gzip_module.decompress(data)
        frame = pl.read_csv(
            io.BytesIO(data),
            columns=["time_utc"],
            infer_schema=False,
            truncate_ragged_lines=True,
            ignore_errors=True,
        )
        times = frame["time_utc"].str.strptime(pl.Datetime("us"), TIME_FORMAT, strict=False)
    except (OSError, EOFError, zlib.error, pl.exceptions.PolarsError, ValueError) as error:
        logger.warning("%s: cannot read its times (%s): none of its samples is known", path, error)
        return np.empty(0, dtype=np.int64)
    micros = times.drop_nulls().cast(pl.Int64).to_numpy()
    return np.unique(micros // 1_000_000)
