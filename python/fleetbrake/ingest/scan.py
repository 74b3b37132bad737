"""The log files of a fleet directory (``shared/spec/fleet-data.md``): every file under
``logs/``, or the given ones, with the size and modification time stat saw (hidden names,
starting with ``.``, are temporary files of copies in progress and are not listed)."""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from stat import S_ISDIR

__all__ = ["LOGS_DIR", "LogEntry", "scan_logs", "stat_logs"]

LOGS_DIR = "logs"


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
