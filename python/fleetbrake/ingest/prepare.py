"""What the workers do with the new files: partitions of a wagon directory's files, each file
read, hashed and judged (samples to ingest, or the reason it is quarantined).

:func:`prepare_partition` is a pure function of the files (it runs in an engine's worker, or
on a thread of this process); the registry's verdict on each wagon is judged by the parent
(:func:`partitions`) and travels with the partition, so that the registry is not shipped to
every worker.
"""

from __future__ import annotations

import hashlib
import itertools
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from fleetbrake.fleet.logfile import LogNameError, parse_log_path
from fleetbrake.fleet.registry import Registry
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.quarantine import Quarantine, path_wagon, registry_problem
from fleetbrake.ingest.reading import ParsedLog, read_log
from fleetbrake.ingest.scan import LogEntry

__all__ = ["FilePartition", "Prepared", "partitions", "prepare_partition"]


@dataclass(frozen=True)
class Prepared:
    """A file read by a worker: its identity and either its samples or why it is quarantined
    (both when its rows were read and every one was rejected: ``parsed`` then says which and
    why, and holds no sample)."""

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


def _prepare(
    entry: LogEntry, problems: Mapping[str, str | None], config: IngestConfig
) -> Prepared | None:
    """Read, hash and judge one file (runs in a worker); None if it vanished. ``problems``:
    :func:`registry_problem` of the wagon of each file name."""
    try:
        return _judge(entry, problems, config)
    except FileNotFoundError:
        return None
    except OSError as error:
        reason = f"{entry.relpath}: cannot be read ({error.strerror or error})"
        return Prepared(
            entry, "", path_wagon(entry.relpath), quarantine=Quarantine("unreadable", reason)
        )


def _judge(entry: LogEntry, problems: Mapping[str, str | None], config: IngestConfig) -> Prepared:
    try:
        name = parse_log_path(entry.relpath)
    except LogNameError as error:
        return Prepared(
            entry,
            _sha256_file(entry.path),
            path_wagon(entry.relpath),
            quarantine=Quarantine("name", str(error)),
        )
    if entry.size_bytes > config.max_file_bytes:
        reason = (
            f"{entry.relpath}: {entry.size_bytes} bytes, more than a session can be "
            f"(limit {config.max_file_bytes}); not read"
        )
        return Prepared(
            entry, _sha256_file(entry.path), name.wagon_id, quarantine=Quarantine("size", reason)
        )
    data = entry.path.read_bytes()
    sha256 = hashlib.sha256(data).hexdigest()
    message = problems[name.wagon_id]
    if message is not None:
        return Prepared(
            entry,
            sha256,
            name.wagon_id,
            quarantine=Quarantine("registry", f"{entry.relpath}: {message}"),
        )
    try:
        parsed = read_log(data, entry.relpath, name.start_utc, config)
    except Quarantine as problem:
        return Prepared(entry, sha256, name.wagon_id, quarantine=problem)
    except Exception as error:  # a reader bug must not stop the fleet: the file says which
        reason = f"{entry.relpath}: could not be read ({type(error).__name__}: {error})"
        return Prepared(entry, sha256, name.wagon_id, quarantine=Quarantine("error", reason))
    rejected = parsed.repairs.rejected_text()
    if rejected is not None and not parsed.frame.height:  # every row read is bad: nothing kept
        nothing_kept = Quarantine("rows", f"{entry.relpath}: no row kept, {rejected}")
        return Prepared(entry, sha256, name.wagon_id, parsed=parsed, quarantine=nothing_kept)
    return Prepared(entry, sha256, name.wagon_id, parsed=parsed)


@dataclass(frozen=True)
class FilePartition:
    """A worker's unit of work: some new files of one wagon directory, in path order, with
    what the registry says about the wagons their names give (judged by the parent, so the
    registry is not shipped to every worker)."""

    entries: tuple[LogEntry, ...]
    problems: Mapping[str, str | None]

    def __str__(self) -> str:
        first = self.entries[0].relpath
        return f"{first.rsplit('/', 1)[0]} ({len(self.entries)} files from {first})"


def partitions(
    entries: list[LogEntry], registry: Registry, config: IngestConfig
) -> Iterator[FilePartition]:
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
            yield FilePartition(chunk, {w: registry_problem(registry, w) for w in wagons})


def prepare_partition(partition: FilePartition, config: IngestConfig) -> list[Prepared | None]:
    """Read, hash, judge and parse a partition's files, in order (a pure function of the
    files: runs in an engine's worker, or on a thread of this process)."""
    return [_prepare(entry, partition.problems, config) for entry in partition.entries]
