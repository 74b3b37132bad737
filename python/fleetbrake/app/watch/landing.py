"""Which files under ``<fleet>/logs`` are complete, and which are still being written.

A file is taken once it is complete:

* **renamed into place** (a move within the watched tree, or into it from elsewhere): the
  writer made it whole under another name first (``fleet.logfile.write_log`` and the MQTT
  bridge write ``.<name>.<tag>.tmp`` and rename it) — complete at once;
* **closed after writing** (inotify's ``IN_CLOSE_WRITE``) — complete at once;
* **settled**: its size and modification time have not changed for ``settle_s`` seconds,
  seen by two looks at it (the polling observer, a file found by a rescan, a writer that keeps
  the file open between bursts). A file whose modification time is already ``settle_s`` old
  when it is first looked at is settled at the next look, unless it was seen being written
  (the wall clock that dates it may have jumped; a file seen being written settles by the
  monotonic clock alone).

Hidden names (a component starting with ``.``) are ignored, as the ingestion ignores them.
A file created or modified again after it was complete is being written again: it waits.

:class:`LandingTracker` is driven from one thread (the service's loop); the observer's thread
only queues events for it.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

__all__ = ["Landing", "LandingTracker"]

LOGS_DIR = "logs"


@dataclass
class Landing:
    """A file under ``logs/`` not yet processed."""

    relpath: str
    """Relative to the fleet directory, ``/``-separated (as ``files.path`` holds it)."""
    seen_s: float
    """When the service first saw it (monotonic clock)."""
    complete: bool = False
    how: str = ""
    """What made it complete: ``renamed``, ``closed`` or ``settled``."""
    size: int | None = None
    mtime_ns: int | None = None
    stable_since_s: float = 0.0
    """Since when (monotonic) size and modification time have been as they are."""
    looks: int = 0
    """How many times its size and modification time were read unchanged in a row."""
    seen_writing: bool = False
    """Whether it was seen being created or written to (then it settles by ``stable_since_s``
    alone, never by the age of its modification time)."""


class LandingTracker:
    """The files under ``logs/`` that have landed (or are landing) and are not processed yet."""

    def __init__(
        self,
        fleet_dir: Path,
        settle_s: float,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall_clock_ns: Callable[[], int] | None = None,
    ) -> None:
        self.fleet_dir = Path(os.path.abspath(fleet_dir))
        self.settle_s = settle_s
        self._clock = clock
        # the wall clock only dates files (their modification times); every wait is timed
        # by ``clock``, monotonic, so that a jump of the wall clock neither stalls nor hurries
        # one (None: ``time.time_ns``, looked up at each call)
        self._wall_ns = wall_clock_ns or (lambda: time.time_ns())
        self._files: dict[str, Landing] = {}

    # ---------------------------------------------------------------------------------------
    # What the observer and the rescans report

    def relpath(self, path: str | os.PathLike[str]) -> str | None:
        """``path``'s name relative to the fleet directory when it is a visible file name
        under ``logs/`` (at any depth), else None."""
        if not path:
            return None
        try:
            rel = PurePosixPath(Path(os.path.abspath(path)).relative_to(self.fleet_dir).as_posix())
        except ValueError:
            return None
        parts = rel.parts
        if len(parts) < 2 or parts[0] != LOGS_DIR or any(p.startswith(".") for p in parts[1:]):
            return None
        return rel.as_posix()

    def _entry(self, relpath: str) -> Landing:
        entry = self._files.get(relpath)
        if entry is None:
            entry = self._files[relpath] = Landing(relpath, seen_s=self._clock())
        return entry

    def writing(self, path: str | os.PathLike[str]) -> None:
        """``path`` was created or written to: it is (again) being written."""
        rel = self.relpath(path)
        if rel is None:
            return
        entry = self._entry(rel)
        entry.complete, entry.how, entry.looks = False, "", 0
        entry.stable_since_s, entry.seen_writing = self._clock(), True

    def finished(self, path: str | os.PathLike[str], how: str) -> None:
        """``path`` was renamed into place or closed after writing: it is complete."""
        rel = self.relpath(path)
        if rel is None:
            return
        entry = self._entry(rel)
        entry.complete, entry.how = True, how

    def moved(self, src: str | os.PathLike[str], dest: str | os.PathLike[str]) -> None:
        """``src`` was renamed to ``dest`` (either may be outside the watched tree, or empty)."""
        self.gone(src)
        self.finished(dest, "renamed")

    def gone(self, path: str | os.PathLike[str]) -> None:
        """``path`` was deleted or moved away."""
        rel = self.relpath(path)
        if rel is not None:
            self._files.pop(rel, None)

    def found(self, relpath: str) -> None:
        """A rescan found ``relpath`` not (or not so) in the ingestion ledger: a candidate
        that is taken once it is settled (unless something already says it is complete)."""
        if relpath not in self._files:
            self._entry(relpath).stable_since_s = self._clock()

    # ---------------------------------------------------------------------------------------
    # Settling and taking

    def refresh(self) -> None:
        """Look again at every file not known to be complete: settled ones become complete,
        vanished ones are forgotten."""
        now = self._clock()
        for rel, entry in list(self._files.items()):
            if entry.complete:
                continue
            try:
                stat = (self.fleet_dir / rel).stat()
            except FileNotFoundError:
                del self._files[rel]
                continue
            except OSError:
                continue  # unreadable for now: the ingestion will say so once it is taken
            if (stat.st_size, stat.st_mtime_ns) != (entry.size, entry.mtime_ns):
                entry.size, entry.mtime_ns = stat.st_size, stat.st_mtime_ns
                entry.stable_since_s, entry.looks = now, 1
                continue
            entry.looks += 1
            old_s = (self._wall_ns() - stat.st_mtime_ns) / 1e9
            if now - entry.stable_since_s >= self.settle_s or (
                entry.looks >= 2 and old_s >= self.settle_s and not entry.seen_writing
            ):
                entry.complete, entry.how = True, "settled"

    def complete(self) -> list[Landing]:
        """The files ready to be taken, in path order."""
        return [e for _, e in sorted(self._files.items()) if e.complete]

    def incomplete(self) -> list[Landing]:
        """The files still being written (or not yet settled), in path order."""
        return [e for _, e in sorted(self._files.items()) if not e.complete]

    def get(self, relpath: str) -> Landing | None:
        return self._files.get(relpath)

    def pop(self, relpath: str) -> Landing | None:
        """Forget ``relpath`` (it was processed); what was known of it, if anything."""
        return self._files.pop(relpath, None)

    def __len__(self) -> int:
        return len(self._files)
