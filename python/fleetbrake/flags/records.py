"""What the detectors find and what is stored: a :class:`Finding` of one wagon's data, a
:class:`Flag` (a row of ``flags``) and the :class:`FlagReport` of a call of ``raise_flags``."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field

__all__ = ["Finding", "Flag", "FlagReport"]


@dataclass(frozen=True)
class Finding:
    """One anomaly found in one wagon's series, before it becomes a stored :class:`Flag`."""

    kind: str
    severity: str
    start_utc: dt.datetime
    end_utc: dt.datetime
    evidence: str
    event_id: str | None = None
    detail: str | None = None
    """What exactly: for a sensor fault ``out_of_range``, ``frozen``, ``dropout``, ``loose``,
    ``drift``; for a dragging brake ``no_pressure`` or ``braking``."""
    summary: str | None = None
    """A few words for a sensor fault merged into another's flag ("was frozen at 8.04 °C")."""


@dataclass(frozen=True)
class Flag:
    """A row of ``flags``."""

    flag_id: str
    wagon_id: str
    event_id: str | None
    kind: str
    severity: str
    start_utc: dt.datetime
    end_utc: dt.datetime
    evidence: str
    detail: str | None = None


@dataclass
class FlagReport:
    """What :func:`raise_flags` did."""

    wagons: list[str] = field(default_factory=list)
    """The wagons whose flags were recomputed."""
    flags: list[Flag] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    """Wagons judged only in part (no registry entry, no predictions), naming the wagon."""
    residual_spread_k: float | None = None
    """The median of the judged wagons' residual spreads (each wagon's thresholds were
    scaled with its own; None: none known)."""

    def count(self, kind: str | None = None) -> int:
        return sum(1 for f in self.flags if kind is None or f.kind == kind)
