"""Configuration of the ingestion and of the event detection that follows it.

:class:`IngestConfig` governs how the files of a fleet directory are read, judged and written
(:mod:`fleetbrake.ingest.files`); :class:`EventConfig` holds the thresholds of the braking
event detection (:mod:`fleetbrake.ingest.detection`, kept up to date by
:mod:`fleetbrake.ingest.events`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from fleetbrake.fleet.logfile import PLAUSIBLE_RANGES

__all__ = ["EventConfig", "IngestConfig"]


@dataclass(frozen=True)
class IngestConfig:
    """How the ingestion reads, judges and writes the files of a fleet directory.

    Read by: ``fleetbrake ingest``, ``fleetbrake run``, ``fleetbrake watch``, ``fleetbrake demo``.
    """

    workers: int = 2
    """Threads reading, hashing, decompressing and parsing partitions of files ahead of the
    writer when the ingestion runs in this process (no engine, or an engine of one worker);
    with an engine of more workers, its processes do."""
    in_flight_files: int = 16
    """Not read: the files are read by partitions (``partition_files``, and the engine's
    ``in_flight`` partitions); the field remains so that configurations naming it still load."""
    max_session_s: int = 48 * 3600
    """A row timed more than this after the file name's time is not of this session."""
    max_file_bytes: int = 1 << 30
    """A larger file is quarantined unread (a session at 1 Hz is a few MB)."""
    partition_files: int = 8
    """A wagon's new files are read in partitions of at most this many files (a worker's unit
    of work, committed by the writer at once: see :func:`~fleetbrake.ingest.files.ingest_fleet`)."""
    batch_rows: int = 1_000_000
    """Whole partitions are committed together until they hold this many rows: DuckDB's writer
    spends about half the processor time per row on transactions of 0.7 M rows and more as on
    transactions of 0.2 M (``docs/decisions/0007-reading-and-writing-in-chunks.md``)."""
    batch_files: int = 500
    """Whole partitions are also committed once they hold this many files."""
    verify_hashes: bool = False
    """Re-read and hash recorded files even when their size and mtime are unchanged."""
    memory_limit: str = "128MB"
    """DuckDB's buffer pool during the ingestion (restored afterwards): the written blocks it
    caches would otherwise grow with the fleet up to the connection's limit."""
    plausible_ranges: Mapping[str, tuple[float, float]] = field(
        default_factory=lambda: PLAUSIBLE_RANGES
    )
    """Closed range of each numeric channel, in the channel's own unit: a cell outside is
    cleared and counted as unparsable, except ``block_temp_c``, whose readings outside are
    Pt1000 faults."""

    def __reduce__(self) -> tuple[object, ...]:
        """Picklable (it goes to an engine's workers): the ranges as a plain dict."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        values["plausible_ranges"] = dict(self.plausible_ranges)
        return (_ingest_config, (values,))


def _ingest_config(values: dict[str, Any]) -> IngestConfig:
    return IngestConfig(**values)


@dataclass(frozen=True)
class EventConfig:
    """Thresholds of the braking event detection (:mod:`fleetbrake.ingest.detection` says how
    each is used).

    Read by: ``fleetbrake ingest``, ``fleetbrake run``, ``fleetbrake watch``, ``fleetbrake demo``.
    """

    p_on_bar: float = 0.3
    """The brake is applied from a sample at or above this brake cylinder pressure."""
    p_off_bar: float = 0.15
    """An application ends at the first sample below this pressure (hysteresis)."""
    p_edge_bar: float = 0.05
    """The baseline: an application is widened back and forward to where the pressure leaves
    and regains this level."""
    edge_max_s: float = 30.0
    """An application's edges are widened by at most this much on each side."""
    merge_gap_s: float = 20.0
    """Applications closer than this (end of one to start of the next) are one event."""
    min_duration_s: float = 10.0
    """Events shorter than this, after merging, are dropped."""
    max_gap_s: float = 15.0
    """A data gap longer than this between two pressure values splits the data: no event
    bridges it (shorter gaps are bridged, the pressure taken as linear)."""
    speed_median_samples: int = 7
    """Samples of the running median the speed is read through (removes GPS jumps of up to
    3 s)."""
    speed_near_s: float = 5.0
    """An event's start or end speed is null when no speed sample lies this close."""
    temp_lookback_s: float = 5.0
    """Where the block temperature at the activation is missing, the latest valid reading up
    to this much before stands for it."""
    stop_speed_kmh: float = 5.0
    """An event ending at or below this speed is a ``stop``."""
    drag_min_duration_s: float = 120.0
    """A ``drag`` lasts at least this long."""
    drag_max_p_mean_bar: float = 1.2
    """A ``drag``'s time-averaged pressure is at most this."""
    drag_min_speed_kmh: float = 15.0
    """During a ``drag`` the smoothed speed never falls below this."""

    def __post_init__(self) -> None:
        if not 0 <= self.p_edge_bar <= self.p_off_bar < self.p_on_bar:
            raise ValueError(
                "EventConfig: need 0 <= p_edge_bar <= p_off_bar < p_on_bar, got "
                f"{self.p_edge_bar}, {self.p_off_bar}, {self.p_on_bar}"
            )
        for name in ("edge_max_s", "merge_gap_s", "min_duration_s", "max_gap_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"EventConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.speed_median_samples < 1:
            raise ValueError("EventConfig.speed_median_samples must be >= 1")
