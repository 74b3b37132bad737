"""Why a unit of ``fleetbrake watch`` failed, as one sentence the service logs once.

A unit that fails stops (what its stages committed stays, and the next unit completes the
rest) and its files stay queued; the service tries again with backoff. The same fault would
otherwise be logged at every retry, so
each failure is reduced to a :class:`UnitFault` whose ``key`` names the fault, not the
attempt: the service logs the sentence when the key changes, and says once that units commit
again when one does.

The fault is found anywhere in the exception's chain: DuckDB reports a full disk as the
failed commit's error, and the rollback that follows may raise one of its own in front of it.
"""

from __future__ import annotations

import errno
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

from fleetbrake.errors import FleetbrakeError
from fleetbrake.fleet.registry import RegistryError

__all__ = ["UnitFault", "unit_fault"]

_DISK_FULL = "No space left on device"
_READ_ONLY = "Read-only file system"


class UnitFault(NamedTuple):
    """A failed unit, as the service says it."""

    key: str
    """The same for every retry that fails for the same reason."""
    sentence: str
    """What happened, to the files and to the service, in one sentence."""
    traceback: bool = False
    """Whether the traceback goes with it (an unexpected error: a bug to report)."""


def _chain(error: BaseException) -> Iterator[BaseException]:
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        yield current
        current = current.__cause__ or current.__context__


def _has(error: BaseException, code: int, text: str) -> bool:
    return any(
        (isinstance(e, OSError) and e.errno == code) or text in str(e) for e in _chain(error)
    )


def unit_fault(error: Exception, db_path: Path, queued: int) -> UnitFault:
    """The fault of a unit over ``queued`` files that raised ``error``."""
    files = f"its {queued} files stay queued"
    if isinstance(error, RegistryError):
        return UnitFault(
            f"registry: {error}",
            "the registry cannot be used, so the unit is skipped and "
            f"{files} until it is fixed: {error}",
        )
    if _has(error, errno.ENOSPC, _DISK_FULL):
        return UnitFault(
            "disk full",
            f"the disk of the warehouse ({db_path.parent}) is full: the unit stops and "
            f"{files} until space is freed",
        )
    if _has(error, errno.EROFS, _READ_ONLY):
        return UnitFault(
            "warehouse read-only",
            f"the warehouse's folder ({db_path.parent}) is on a read-only filesystem: the unit "
            f"stops and {files} until it is writable",
        )
    text = f"{type(error).__name__}: {error}"
    if isinstance(error, FleetbrakeError):
        return UnitFault(text, f"unit failed ({queued} files queued): {error}")
    return UnitFault(text, f"unit failed ({queued} files queued): {text}", traceback=True)
