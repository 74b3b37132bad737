"""Each wagon's samples, held in sessions until a session is over and written as one file.

A wagon's open session takes a sample within ``gap_s`` of its time span as long as the span
stays shorter than ``max_file_s``. A sample more than ``gap_s`` after a session's last one,
or one that would stretch it to ``max_file_s``, ends it (newer data moved past it): the
session is handed back to be written. A late sample (before a session's span) that no open
session takes opens a session of its own, so a wagon may have a few open sessions at once.
:meth:`SessionBuffer.idle` hands back the sessions that received nothing new for a while,
:meth:`SessionBuffer.drain` all of them.

A second already held by one of the wagon's open sessions is a duplicate (a redelivered
message, a unit that sent twice): the first value received is kept, as the ingestion keeps
the first row of a repeated time.

Each session records the keys of the messages whose samples it holds (:attr:`Session.keys`),
so that a message is acknowledged once every session holding its samples is written.
Pure bookkeeping: no I/O, no clock (the caller passes the time).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

from fleetbrake.bridge.payload import Row

__all__ = ["Placed", "Session", "SessionBuffer"]


@dataclass
class Session:
    """One wagon's samples that will make one log file."""

    wagon_id: str
    first_s: int
    last_s: int
    touched_s: float
    """Clock time (the caller's, monotonic) of the last new sample."""
    rows: dict[int, Row] = field(default_factory=dict)
    """Second -> values."""
    keys: set[int] = field(default_factory=set)
    """Keys of the messages with samples here (the caller's numbering)."""

    def takes(self, second: int, gap_s: float, max_file_s: float) -> bool:
        """Whether ``second`` belongs to this session."""
        if not self.first_s - gap_s <= second <= self.last_s + gap_s:
            return False
        return max(self.last_s, second) - min(self.first_s, second) < max_file_s

    def ended_by(self, second: int, gap_s: float, max_file_s: float) -> bool:
        """Whether a sample at ``second`` shows this session is over: it comes more than
        ``gap_s`` after the last sample, or would stretch the span to ``max_file_s``."""
        if second <= self.last_s:
            return False
        return second - self.last_s > gap_s or second - self.first_s >= max_file_s


class Placed(NamedTuple):
    """Where :meth:`SessionBuffer.add` put a sample."""

    new: bool
    """False: the wagon's open sessions hold this second already; the sample is dropped (the
    message is noted on the session that holds the second all the same)."""
    attached: bool
    """The message was not noted on that session before: one more session holds it."""
    ended: list[Session]
    """Sessions the sample showed to be over, removed: the caller writes them."""


class SessionBuffer:
    """The open sessions of every wagon."""

    def __init__(self, gap_s: float, max_file_s: float) -> None:
        self.gap_s = gap_s
        self.max_file_s = max_file_s
        self._open: dict[str, list[Session]] = {}
        self.samples = 0
        """Samples held in open sessions."""

    @property
    def sessions(self) -> int:
        """Open sessions, over all wagons."""
        return sum(len(sessions) for sessions in self._open.values())

    def add(self, wagon_id: str, second: int, row: Row, key: int, now_s: float) -> Placed:
        """Put one sample of message ``key`` into its wagon's session (see :class:`Placed`)."""
        sessions = self._open.setdefault(wagon_id, [])
        for session in sessions:
            if second in session.rows:
                attached = key not in session.keys
                session.keys.add(key)
                return Placed(False, attached, [])
        ended = [s for s in sessions if s.ended_by(second, self.gap_s, self.max_file_s)]
        if ended:
            sessions[:] = [s for s in sessions if s not in ended]
            self.samples -= sum(len(s.rows) for s in ended)
        home = next((s for s in sessions if s.takes(second, self.gap_s, self.max_file_s)), None)
        if home is None:
            home = Session(wagon_id, second, second, now_s)
            sessions.append(home)
        home.rows[second] = row
        attached = key not in home.keys
        home.keys.add(key)
        home.first_s = min(home.first_s, second)
        home.last_s = max(home.last_s, second)
        home.touched_s = now_s
        self.samples += 1
        return Placed(True, attached, ended)

    def idle(self, now_s: float, idle_s: float) -> list[Session]:
        """Remove and return the sessions that got no new sample since ``now_s - idle_s``."""
        return self._take(lambda s: now_s - s.touched_s >= idle_s)

    def drain(self) -> list[Session]:
        """Remove and return every open session."""
        return self._take(lambda s: True)

    def _take(self, done: Callable[[Session], bool]) -> list[Session]:
        taken: list[Session] = []
        for wagon_id in list(self._open):
            sessions = self._open[wagon_id]
            keep: list[Session] = []
            for session in sessions:
                (taken if done(session) else keep).append(session)
            if keep:
                self._open[wagon_id] = keep
            else:
                del self._open[wagon_id]
        self.samples -= sum(len(s.rows) for s in taken)
        return taken
