"""Braking events: detected from the brake cylinder pressure and the speed of each wagon.

::

    from fleetbrake.ingest.events import EventConfig, detect_events, update_events

    events = detect_events(samples, "SGG-0001")     # pure: one wagon's samples -> events frame
    with open_warehouse(db) as wh:
        update = update_events(wh)                  # incremental, after an ingestion

How an event is found (defaults of :class:`EventConfig`):

1. **Samples.** Of samples with the same time (files that overlap), the one of the earliest
   file counts. Samples without a pressure value are left out of the detection. A data gap of
   more than ``max_gap_s`` (15 s) between two pressure values splits the data into segments:
   an event never bridges such a gap (the pressure in it is unknown); an event cut by a gap
   or by the start or end of the data is kept with ``complete = false``. Shorter gaps are
   bridged (the pressure is taken as linear in between).
2. **Applications** (hysteresis): the brake is applied from a sample at or above ``p_on_bar``
   (0.3 bar) until the first sample below ``p_off_bar`` (0.15 bar).
3. **Edges.** An application is widened to where the pressure leaves and regains its baseline:
   back to the first sample above ``p_edge_bar`` (0.05 bar), forward to the first sample at or
   below it, each by at most ``edge_max_s`` (30 s). ``start_utc`` is the activation (the first
   sample of the rise), ``end_utc`` the release (the first sample back at the baseline).
4. **Merging.** Applications less than ``merge_gap_s`` (20 s) apart (end of one to start of the
   next) are one event; then events shorter than ``min_duration_s`` (10 s) are dropped.
5. **Attributes.** ``event_id`` is ``<wagon_id>-<start as YYYYMMDDTHHMMSS>`` (stable: the same
   data gives the same id). ``duration_s = end - start``. ``distance_m`` from the
   ``distance_m`` column (per file, linearly interpolated at start and end), from the
   integrated speed where a file has none. Speeds are read from the speed after a running
   median over ``speed_median_samples`` (7) samples, which removes GPS jumps of up to 3 s;
   ``v_start_kmh``/``v_end_kmh`` at start and end, null if no speed within ``speed_near_s``.
   ``p_mean_bar`` is the time average of the pressure over [start, end] (paper eq. 1,
   trapezoidal), ``p_max_bar`` its maximum. ``t_block_start_c`` is the valid block temperature
   at the activation; where the reading there is missing (empty cell, dropped row), the latest
   valid one up to ``temp_lookback_s`` (5 s) before; null when the reading at the activation
   is a fault (out of range) or no valid one is that close.
6. **Kind.** ``stop`` when ``v_end_kmh`` <= ``stop_speed_kmh`` (5 km/h); ``drag`` for a long
   low-pressure application at speed: at least ``drag_min_duration_s`` (120 s), ``p_mean_bar``
   <= ``drag_max_p_mean_bar`` (1.2 bar), speed never below ``drag_min_speed_kmh`` (15 km/h);
   otherwise ``slowdown``.

Incremental (:func:`update_events`): each ingested file records its time range in
``event_dirty`` (in the file's transaction). A wagon's files whose time ranges lie within
``max_gap_s`` of each other form a *chain*; since events never bridge larger gaps, a chain's
events depend only on its own samples. Every chain touching a dirty range is detected again,
and the events table is brought in line for a batch of whole wagons (about 1,000 events) in
one transaction: events that are the same are left alone (their ``detected_utc``
unchanged), changed or vanished ones are replaced or deleted, new ones inserted, and the
wagons' dirty ranges removed. A run killed half-way leaves whole wagons done and the others'
dirty ranges in place, so the next run does their work again. Samples are loaded whole
chains at a time, the touched chains of several wagons together (at most about 200,000
rows, unless one chain is longer) with one query, in stored order: a partition, cut into
its wagons' windows and sorted by time and detected by an engine's worker when
``update_events`` is given an engine (:mod:`fleetbrake.engine`), while this process, the
single writer, commits the batches.
"""

from __future__ import annotations

import bisect
import datetime as dt
import itertools
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import duckdb
import numpy as np
import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.engine.writer import WriteBehind
from fleetbrake.warehouse.connection import Warehouse, reader, sql

__all__ = [
    "EVENT_COLUMNS",
    "EventConfig",
    "EventUpdate",
    "detect_events",
    "shrinking_running_median",
    "update_events",
]

EVENT_COLUMNS: dict[str, pl.DataType] = {
    "event_id": pl.String(),
    "wagon_id": pl.String(),
    "start_utc": pl.Datetime("us"),
    "end_utc": pl.Datetime("us"),
    "duration_s": pl.Float64(),
    "distance_m": pl.Float64(),
    "v_start_kmh": pl.Float64(),
    "v_end_kmh": pl.Float64(),
    "p_mean_bar": pl.Float64(),
    "p_max_bar": pl.Float64(),
    "t_block_start_c": pl.Float64(),
    "kind": pl.String(),
    "complete": pl.Boolean(),
}
"""Columns of :func:`detect_events`' frame (the ``events`` table but ``detected_utc``)."""

_US_PER_S = 1_000_000


@dataclass(frozen=True)
class EventConfig:
    """Thresholds of the event detection (see the module docstring for how they are used)."""

    p_on_bar: float = 0.3
    p_off_bar: float = 0.15
    p_edge_bar: float = 0.05
    edge_max_s: float = 30.0
    merge_gap_s: float = 20.0
    min_duration_s: float = 10.0
    max_gap_s: float = 15.0
    speed_median_samples: int = 7
    speed_near_s: float = 5.0
    temp_lookback_s: float = 5.0
    stop_speed_kmh: float = 5.0
    drag_min_duration_s: float = 120.0
    drag_max_p_mean_bar: float = 1.2
    drag_min_speed_kmh: float = 15.0

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


# --------------------------------------------------------------------------------------------
# Detection on one wagon's samples


@dataclass
class _Span:
    """An event as sample indices into the pressure series: [start, end], both inclusive."""

    start: int
    end: int
    complete_start: bool
    complete_end: bool


def _segments(time_s: np.ndarray, max_gap_s: float) -> list[tuple[int, int]]:
    """[a, b) index ranges between data gaps longer than ``max_gap_s``."""
    if len(time_s) == 0:
        return []
    breaks = np.flatnonzero(np.diff(time_s) > max_gap_s) + 1
    bounds = np.concatenate(([0], breaks, [len(time_s)]))
    return [(int(a), int(b)) for a, b in itertools.pairwise(bounds)]


def _applications(pressure_bar: np.ndarray, config: EventConfig) -> list[tuple[int, int]]:
    """Hysteresis runs [first sample on, first sample off) of one segment (off may be len)."""
    on = pressure_bar >= config.p_on_bar
    off = pressure_bar < config.p_off_bar
    index = np.arange(len(pressure_bar))
    last_trigger = np.maximum.accumulate(np.where(on | off, index, -1))
    applied = np.where(last_trigger >= 0, on[np.maximum(last_trigger, 0)], False)
    change = np.diff(applied.astype(np.int8), prepend=0, append=0)
    starts = np.flatnonzero(change == 1)
    stops = np.flatnonzero(change == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


def _spans(time_s: np.ndarray, pressure_bar: np.ndarray, config: EventConfig) -> list[_Span]:
    """Events of one segment, as index spans, edges widened, merged, short ones dropped."""
    n = len(pressure_bar)
    spans: list[_Span] = []
    for first_on, first_off in _applications(pressure_bar, config):
        start = first_on
        while (
            start > 0
            and pressure_bar[start - 1] > config.p_edge_bar
            and time_s[first_on] - time_s[start - 1] <= config.edge_max_s
        ):
            start -= 1
        complete_start = start > 0 or pressure_bar[0] <= config.p_edge_bar
        if first_off >= n:
            spans.append(_Span(start, n - 1, complete_start, False))
            continue
        end = first_off
        while (
            end < n - 1
            and pressure_bar[end] > config.p_edge_bar
            and time_s[end + 1] - time_s[first_off] <= config.edge_max_s
        ):
            end += 1
        spans.append(_Span(start, end, complete_start, True))
    merged: list[_Span] = []
    for span in spans:
        if merged and time_s[span.start] - time_s[merged[-1].end] < config.merge_gap_s:
            merged[-1].end = max(merged[-1].end, span.end)
            merged[-1].complete_end = span.complete_end
        else:
            merged.append(span)
    return [s for s in merged if time_s[s.end] - time_s[s.start] >= config.min_duration_s]


@dataclass
class _Series:
    """One wagon's samples as arrays (sorted, distinct times), with derived signals."""

    time_s: np.ndarray
    time_us: np.ndarray
    file_id: np.ndarray
    pressure_bar: np.ndarray
    distance_m: np.ndarray
    block_temp_c: np.ndarray
    block_temp_fault: np.ndarray
    """True where the Pt1000 reading was out of range (a broken wire)."""
    speed_time_s: np.ndarray
    """Times of the samples with a speed."""
    speed_kmh: np.ndarray
    """Running median of the speed at ``speed_time_s``."""
    distance_by_file: dict[int, tuple[np.ndarray, np.ndarray]]
    """Per file: times and values of its ``distance_m`` readings."""

    @classmethod
    def of(cls, samples: pl.DataFrame, config: EventConfig) -> _Series:
        # one polars query per chain (the columns), the rest in numpy: each polars call
        # costs about 0.3 ms, and a wagon-day has a few chains
        columns = [
            pl.col("time_utc").cast(pl.Datetime("us")),
            pl.col("speed_kmh").cast(pl.Float64),
            pl.col("distance_m").cast(pl.Float64),
            pl.col("brake_pressure_bar").cast(pl.Float64),
            pl.col("block_temp_c").cast(pl.Float64),
        ]
        if "file_id" in samples.columns:
            columns.append(pl.col("file_id"))
        if "block_temp_fault" in samples.columns:
            columns.append(pl.col("block_temp_fault").fill_null(False))
        frame = samples.select(columns)
        time_us = _physical_us(frame["time_utc"])
        if not np.all(np.diff(time_us) > 0):  # not sorted, or a time repeated
            frame = frame.sort("time_utc", maintain_order=True).unique(
                subset="time_utc", keep="first", maintain_order=True
            )
            time_us = _physical_us(frame["time_utc"])
        time_s = time_us / _US_PER_S
        speed_kmh = frame["speed_kmh"].to_numpy()  # null: NaN
        has_speed = ~np.isnan(speed_kmh)
        file_id = (
            frame["file_id"].to_numpy()
            if "file_id" in frame.columns
            else np.zeros(frame.height, dtype=np.int64)
        )
        distance_m = frame["distance_m"].to_numpy()
        has_distance = ~np.isnan(distance_m)
        distance_by_file = {
            int(f): (
                time_s[(file_id == f) & has_distance],
                distance_m[(file_id == f) & has_distance],
            )
            for f in np.unique(file_id)
        }
        return cls(
            time_s=time_s,
            time_us=time_us,
            file_id=file_id,
            pressure_bar=frame["brake_pressure_bar"].to_numpy(),
            distance_m=distance_m,
            distance_by_file=distance_by_file,
            block_temp_c=frame["block_temp_c"].to_numpy(),
            block_temp_fault=(
                frame["block_temp_fault"].to_numpy()
                if "block_temp_fault" in frame.columns
                else np.zeros(frame.height, dtype=bool)
            ),
            speed_time_s=time_s[has_speed],
            speed_kmh=shrinking_running_median(speed_kmh[has_speed], config.speed_median_samples),
        )

    def speed_at(self, time_s: float, near_s: float) -> float:
        """Smoothed speed of the sample nearest to ``time_s`` within ``near_s``, else NaN."""
        if len(self.speed_time_s) == 0:
            return math.nan
        i = int(np.searchsorted(self.speed_time_s, time_s))
        best, best_dt = math.nan, near_s
        for j in (i - 1, i):
            if 0 <= j < len(self.speed_time_s):
                gap = abs(self.speed_time_s[j] - time_s)
                if gap <= best_dt:
                    best, best_dt = float(self.speed_kmh[j]), gap
        return best

    def min_speed(self, start_s: float, end_s: float) -> float:
        """Lowest smoothed speed in [start_s, end_s], NaN if none."""
        a = np.searchsorted(self.speed_time_s, start_s, side="left")
        b = np.searchsorted(self.speed_time_s, end_s, side="right")
        return float(self.speed_kmh[a:b].min()) if b > a else math.nan

    def speed_distance_m(self, start_s: float, end_s: float) -> float:
        """Distance from the smoothed speed over [start_s, end_s] (trapezoid), NaN if no speed."""
        a = np.searchsorted(self.speed_time_s, start_s, side="left")
        b = np.searchsorted(self.speed_time_s, end_s, side="right")
        if b - a < 2:
            return math.nan
        return float(np.trapezoid(self.speed_kmh[a:b] / 3.6, self.speed_time_s[a:b]))

    def distance(self, start_s: float, end_s: float) -> float:
        """Distance travelled in [start_s, end_s], NaN if unknown.

        ``distance_m`` restarts in every file, so the window is cut into runs of one file:
        within a run, from ``distance_m`` (interpolated) where the file has at least two
        values, else from the speed; between runs, from the speed.
        """
        a = int(np.searchsorted(self.time_s, start_s, side="left"))
        b = int(np.searchsorted(self.time_s, end_s, side="right"))
        if b - a < 2:
            return 0.0 if b > a else math.nan
        files = self.file_id[a:b]
        cuts = np.flatnonzero(files[1:] != files[:-1]) + 1
        bounds = [a, *(a + cuts).tolist(), b]
        total = 0.0
        for first, stop in itertools.pairwise(bounds):
            t0, t1 = float(self.time_s[first]), float(self.time_s[stop - 1])
            times_s, values_m = self.distance_by_file[int(self.file_id[first])]
            if len(times_s) >= 2:
                d0, d1 = np.interp([t0, t1], times_s, values_m)
                total += max(float(d1 - d0), 0.0)
            else:
                total += self.speed_distance_m(t0, t1) if t1 > t0 else 0.0
            if stop < b:  # the junction to the next file
                total += self.speed_distance_m(t1, float(self.time_s[stop]))
        return total

    def block_temp_at(self, time_s: float, lookback_s: float) -> float:
        """Block temperature at ``time_s``: NaN if the sensor is faulty there, else the reading
        there or, where it is missing, the latest one up to ``lookback_s`` before."""
        b = int(np.searchsorted(self.time_s, time_s, side="right"))
        if b > 0 and self.time_s[b - 1] == time_s and self.block_temp_fault[b - 1]:
            return math.nan
        a = np.searchsorted(self.time_s, time_s - lookback_s, side="left")
        window = self.block_temp_c[a:b]
        valid = np.flatnonzero(~np.isnan(window))
        return float(window[valid[-1]]) if len(valid) else math.nan


def detect_events(
    samples: pl.DataFrame, wagon_id: str, config: EventConfig | None = None
) -> pl.DataFrame:
    """The braking events in one wagon's samples (columns :data:`EVENT_COLUMNS`).

    ``samples`` needs ``time_utc``, ``speed_kmh``, ``distance_m``, ``brake_pressure_bar`` and
    ``block_temp_c`` (null where missing or faulty); ``block_temp_fault`` (out of range) if
    known; ``file_id`` if it spans several files
    (``distance_m`` restarts in each). Any order; of repeated times the first row counts.
    """
    config = config or EventConfig()
    series = _Series.of(samples, config)
    has_p = ~np.isnan(series.pressure_bar)
    p_time_s = series.time_s[has_p]
    p_time_us = series.time_us[has_p]
    p_bar = series.pressure_bar[has_p]
    rows: list[dict[str, object]] = []
    for a, b in _segments(p_time_s, config.max_gap_s):
        for span in _spans(p_time_s[a:b], p_bar[a:b], config):
            i0, i1 = a + span.start, a + span.end
            start_s, end_s = float(p_time_s[i0]), float(p_time_s[i1])
            duration_s = end_s - start_s
            p_mean = float(np.trapezoid(p_bar[i0 : i1 + 1], p_time_s[i0 : i1 + 1]) / duration_s)
            v_start = series.speed_at(start_s, config.speed_near_s)
            v_end = series.speed_at(end_s, config.speed_near_s)
            start_utc = _utc(int(p_time_us[i0]))
            rows.append(
                {
                    "event_id": f"{wagon_id}-{start_utc:%Y%m%dT%H%M%S}",
                    "wagon_id": wagon_id,
                    "start_utc": start_utc,
                    "end_utc": _utc(int(p_time_us[i1])),
                    "duration_s": duration_s,
                    "distance_m": _none_if_nan(series.distance(start_s, end_s)),
                    "v_start_kmh": _none_if_nan(v_start),
                    "v_end_kmh": _none_if_nan(v_end),
                    "p_mean_bar": p_mean,
                    "p_max_bar": float(p_bar[i0 : i1 + 1].max()),
                    "t_block_start_c": _none_if_nan(
                        series.block_temp_at(start_s, config.temp_lookback_s)
                    ),
                    "kind": _kind(series, start_s, end_s, duration_s, p_mean, v_end, config),
                    "complete": span.complete_start and span.complete_end,
                }
            )
    return pl.DataFrame(rows, schema=EVENT_COLUMNS)


def _kind(
    series: _Series,
    start_s: float,
    end_s: float,
    duration_s: float,
    p_mean_bar: float,
    v_end_kmh: float,
    config: EventConfig,
) -> str:
    if not math.isnan(v_end_kmh) and v_end_kmh <= config.stop_speed_kmh:
        return "stop"
    if duration_s >= config.drag_min_duration_s and p_mean_bar <= config.drag_max_p_mean_bar:
        lowest = series.min_speed(start_s, end_s)
        if not math.isnan(lowest) and lowest >= config.drag_min_speed_kmh:
            return "drag"
    return "slowdown"


def shrinking_running_median(values: np.ndarray, window: int) -> np.ndarray:
    """The running median of ``values`` (no NaN) over ``window`` samples centred on each,
    fewer at the ends (the windows shrink: not ``simulation.series.running_median``, which
    pads the ends with the end values, as the chain's speed does): polars'
    ``rolling_median(window, center=True, min_samples=1)``, bit for bit, at a third of its
    cost. An odd window's full medians are each window's middle
    value (numpy's partition of the sliding windows: a choice, no arithmetic); the ``window
    // 2`` values at each end, whose shorter windows may average two, and an even window
    are polars' own."""
    n, half = values.size, window // 2
    if window % 2 == 0 or n < 2 * window:
        return _polars_running_median(values, window)
    out = np.empty(n, dtype=np.float64)
    windows = np.lib.stride_tricks.sliding_window_view(values, window)
    out[half : n - half] = np.partition(windows, half, axis=1)[:, half]
    if half:  # an end's windows hold only its first (last) 2 x half values
        out[:half] = _polars_running_median(values[: 2 * half], window)[:half]
        out[n - half :] = _polars_running_median(values[n - 2 * half :], window)[half:]
    return out


def _polars_running_median(values: np.ndarray, window: int) -> np.ndarray:
    series = pl.Series(values, dtype=pl.Float64)
    return series.rolling_median(window_size=window, center=True, min_samples=1).to_numpy()


def _physical_us(times: pl.Series) -> np.ndarray:
    """Microseconds since the epoch of a ``Datetime("us")`` column without nulls."""
    return times.to_numpy().view(np.int64)


def _utc(time_us: int) -> dt.datetime:
    return dt.datetime(1970, 1, 1) + dt.timedelta(microseconds=time_us)


def _none_if_nan(value: float) -> float | None:
    return None if math.isnan(value) else value


# --------------------------------------------------------------------------------------------
# Incremental update of the warehouse


@dataclass
class EventUpdate:
    """What :func:`update_events` changed."""

    wagons: int = 0
    chains: int = 0
    """Chains of files detected again."""
    added: int = 0
    """Events inserted (new, or replacing a changed one)."""
    removed: int = 0
    """Events deleted (vanished, or replaced by a changed one)."""
    unchanged: int = 0
    """Events detected again with the same values, left alone."""
    total: int = 0
    """Events in the table afterwards."""
    changed_ids: list[str] = field(default_factory=list)
    """Ids of the events inserted by this update."""


_LOAD_ROWS = 200_000
"""Samples loaded per query at most (whole chains of one or more wagons, a partition; a
longer chain is loaded alone): about five wagon-days, the size of the other stages' chunks
(a hundred wagon-days make twenty partitions for the workers to share)."""

_COMMIT_EVENTS = 1_000
"""Events brought in line per transaction at most (whole wagons; a wagon with more is
committed alone; a wagon without any counts one): ``BEGIN``/``COMMIT`` and the insert cost
milliseconds whatever their size (``docs/benchmarks.md``, session 9)."""


@dataclass(frozen=True)
class _Chain:
    """Files of one wagon closer than ``max_gap_s`` to each other: their time span, rows."""

    from_utc: dt.datetime
    to_utc: dt.datetime
    rows: int


def _chains(files: list[tuple[dt.datetime, dt.datetime, int]], max_gap_s: float) -> list[_Chain]:
    """Files (first, last sample, rows) sorted by first, grouped where closer than ``max_gap_s``."""
    chains: list[_Chain] = []
    gap = dt.timedelta(seconds=max_gap_s)
    for first, last, rows in files:
        if chains and first - chains[-1].to_utc <= gap:
            before = chains[-1]
            chains[-1] = _Chain(before.from_utc, max(before.to_utc, last), before.rows + rows)
        else:
            chains.append(_Chain(first, last, rows))
    return chains


def _merged(
    ranges: list[tuple[dt.datetime, dt.datetime]], pad: dt.timedelta
) -> list[tuple[dt.datetime, dt.datetime]]:
    """Ranges widened by ``pad`` on both sides, sorted, overlapping ones merged."""
    merged: list[tuple[dt.datetime, dt.datetime]] = []
    for a, b in sorted((a - pad, b + pad) for a, b in ranges):
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged


def _overlaps(
    merged: list[tuple[dt.datetime, dt.datetime]], from_utc: dt.datetime, to_utc: dt.datetime
) -> bool:
    """[from_utc, to_utc] meets one of the sorted disjoint ranges ``merged``."""
    i = bisect.bisect_right(merged, (to_utc, dt.datetime.max))
    return i > 0 and merged[i - 1][1] >= from_utc


def update_events(
    wh: Warehouse, config: EventConfig | None = None, *, engine: Mapper | None = None
) -> EventUpdate:
    """Detect the events of every chain of files touched since the last update (see module).

    This process reads the wagons' touched chains (several wagons' at a time, at most about
    ``_LOAD_ROWS`` samples, one query: a partition, :func:`_detect_tasks`), ``engine.map``
    runs the detection on them (default: the builtin ``map``, here; an engine's workers
    otherwise, which cut and sort the rows: :func:`_window_parts`), and this process brings
    whole wagons' events in line, a batch of wagons (at most about ``_COMMIT_EVENTS``
    events) in one transaction, as their partitions come back. The transactions run on a
    writer thread (:class:`~fleetbrake.engine.writer.WriteBehind`), one batch at a time and
    in order, while the next wagons' samples are read on a second connection
    (:func:`reader`): the reads and the commits overlap instead of adding up."""
    config = config or EventConfig()
    con = wh.con
    update = EventUpdate()
    dirty = con.execute(sql("q_events_dirty")).fetchall()
    by_wagon: dict[str, list[tuple[dt.datetime, dt.datetime]]] = {}
    for wagon_id, from_utc, to_utc in dirty:
        by_wagon.setdefault(wagon_id, []).append((from_utc, to_utc))
    affected_by_wagon: dict[str, list[_Chain]] = {}
    holding = _holding_events(wh, sorted(by_wagon))

    def write(batch: list[_Detected]) -> None:
        _update_wagons(wh, batch, by_wagon, holding, update)

    pending: list[_Detected] = []
    held = 0
    with reader(wh) as source, WriteBehind(write) as writer:
        tasks = _detect_tasks(source, by_wagon, config, affected_by_wagon)
        results = map(_detect_task, tasks) if engine is None else engine.map(_detect_task, tasks)
        found: list[pl.DataFrame] = []
        for task_wagon, events, last in (one for chunk in results for one in chunk):
            found.append(events)
            if not last:
                continue
            new = pl.concat(found)
            found = []
            rows = max(new.height, 1)
            if pending and held + rows > _COMMIT_EVENTS:
                writer.submit(pending)  # whole wagons per transaction, on its thread
                pending, held = [], 0
            pending.append(_Detected(task_wagon, affected_by_wagon.pop(task_wagon), new))
            held += rows
        if pending:
            writer.submit(pending)
    row = con.execute(sql("q_events_count")).fetchone()
    update.total = int(row[0]) if row is not None else 0
    return update


class Mapper(Protocol):
    """What runs the detection's partitions: ``map(fn, items)`` yielding ``fn(item)`` in the
    order of ``items`` (a :class:`fleetbrake.engine.Engine`)."""

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any], /) -> Iterator[Any]: ...


@dataclass(frozen=True)
class _Window:
    """A time window of one wagon's samples read in one piece: some of its touched chains
    (consecutive ones, with the chains between them) or none."""

    wagon_id: str
    chains: tuple[tuple[dt.datetime, dt.datetime], ...]
    """The touched chains' time spans, in time order (the window runs from the first's start
    to the last's end)."""
    rows: int
    """Samples of the window's files (what chunks are sized by)."""
    last: bool
    """The wagon's last window: its events can be brought in line once it is back."""


@dataclass(frozen=True)
class _DetectTask:
    """A partition of the detection: windows of one or more wagons, in wagon order, and their
    samples read together (``q_events_chunk_samples.sql``: Arrow, each row with its
    window's 1-based ``part_ix``, in stored order)."""

    windows: tuple[_Window, ...]
    samples: pa.Table | None
    """The samples of the windows with chains (``part_ix`` counts those); None: none has."""
    config: EventConfig

    def __str__(self) -> str:  # how an engine names the partition in an error
        wagons = list(dict.fromkeys(w.wagon_id for w in self.windows))
        chains = sum(len(w.chains) for w in self.windows)
        names = f"wagon {wagons[0]}" if len(wagons) == 1 else "wagons " + ", ".join(wagons)
        return f"{names} ({chains} stretches of samples)"


def _detect_task(task: _DetectTask) -> list[tuple[str, pl.DataFrame, bool]]:
    """The events of each window's chains, in the task's order (pure: runs in an engine's
    worker): the chunk cut into the windows it read (:func:`_window_parts`), each sorted as
    ``q_event_samples.sql`` sorts one, each chain's slice detected alone."""
    parts = iter(_window_parts(task.samples, sum(1 for w in task.windows if w.chains)))
    out = []
    for window in task.windows:
        found = [pl.DataFrame(schema=EVENT_COLUMNS)]
        if window.chains:
            samples = next(parts)
            times = samples["time_utc"].to_numpy()  # sorted; numpy: no Series per lookup
            for from_utc, to_utc in window.chains:
                lo = int(np.searchsorted(times, np.datetime64(from_utc, "us"), "left"))
                hi = int(np.searchsorted(times, np.datetime64(to_utc, "us"), "right"))
                chain = samples.slice(lo, hi - lo)
                found.append(detect_events(chain, window.wagon_id, task.config))
        out.append((window.wagon_id, pl.concat(found), window.last))
    return out


_SAMPLE_COLUMNS: dict[str, pl.DataType] = {
    "time_utc": pl.Datetime("us"),
    "file_id": pl.Int64(),
    "speed_kmh": pl.Float64(),
    "distance_m": pl.Float64(),
    "brake_pressure_bar": pl.Float64(),
    "block_temp_c": pl.Float64(),
    "block_temp_fault": pl.Boolean(),
}
"""The columns of ``q_event_samples.sql`` (a window's samples as the detection reads them)."""


def _window_parts(samples: pa.Table | None, windows: int) -> list[pl.DataFrame]:
    """Each of ``windows`` windows' samples of a chunk read by ``q_events_chunk_samples.sql``
    (by ``part_ix``), sorted by ``time_utc`` then ``file_id`` as ``q_event_samples.sql`` sorts
    one window (a file holds one sample per time: the order is total, so any sort gives the
    same rows), without ``part_ix``. The stored order holds each window's rows in a few runs
    (its files were written together), mostly in time order: each window is its runs'
    slices joined without a copy, sorted only when its times do not strictly increase."""
    empty = pl.DataFrame(schema=_SAMPLE_COLUMNS)
    if samples is None or samples.num_rows == 0:
        return [empty] * windows
    frame = pl.from_arrow(samples)
    assert isinstance(frame, pl.DataFrame)  # a table converts to a frame
    ix = frame["part_ix"].to_numpy()
    frame = frame.select(list(_SAMPLE_COLUMNS))
    runs: list[list[pl.DataFrame]] = [[] for _ in range(windows)]
    starts = [0, *(np.flatnonzero(ix[1:] != ix[:-1]) + 1).tolist(), ix.size]
    for a, b in itertools.pairwise(starts):
        runs[int(ix[a]) - 1].append(frame.slice(a, b - a))
    parts = []
    for pieces in runs:
        part = pl.concat(pieces, rechunk=False) if pieces else empty
        if not np.all(np.diff(_physical_us(part["time_utc"])) > 0):  # or a time repeated
            part = part.sort(["time_utc", "file_id"])
        parts.append(part)
    return parts


def _detect_tasks(
    wh: Warehouse,
    by_wagon: dict[str, list[tuple[dt.datetime, dt.datetime]]],
    config: EventConfig,
    affected_by_wagon: dict[str, list[_Chain]],
) -> Iterator[_DetectTask]:
    """The dirty wagons' touched chains as windows (:func:`_load_groups`), in wagon order,
    packed into chunks of at most about ``_LOAD_ROWS`` samples (whole windows; a longer one
    alone), each chunk's samples read with one query (``q_events_chunk_samples.sql``); the
    wagons' files are read with one query (``q_events_files.sql``). Records each wagon's
    touched chains in ``affected_by_wagon``. Read lazily, between the wagons' transactions."""
    wagon_ids = sorted(by_wagon)
    files_by_wagon: dict[str, list[tuple[dt.datetime, dt.datetime, int]]] = {}
    if wagon_ids:
        rows = wh.con.execute(sql("q_events_files"), {"wagon_ids": wagon_ids}).fetchall()
        for wagon_id, first, last, n in rows:
            files_by_wagon.setdefault(wagon_id, []).append((first, last, n))
    chunk: list[_Window] = []
    held = 0
    for wagon_id in wagon_ids:
        chains = _chains(files_by_wagon.get(wagon_id, []), config.max_gap_s)
        touched = _merged(by_wagon[wagon_id], dt.timedelta(seconds=config.max_gap_s))
        affected = [c for c in chains if _overlaps(touched, c.from_utc, c.to_utc)]
        affected_by_wagon[wagon_id] = affected
        groups = _load_groups(chains, affected)
        windows = [
            _Window(
                wagon_id,
                tuple((c.from_utc, c.to_utc) for c in group),
                _span_rows(chains, group),
                last=i == len(groups) - 1,
            )
            for i, group in enumerate(groups)
        ] or [_Window(wagon_id, (), 0, last=True)]
        for window in windows:
            if chunk and held + window.rows > _LOAD_ROWS:
                yield _chunk_task(wh, chunk, config)
                chunk, held = [], 0
            chunk.append(window)
            held += window.rows
    if chunk:
        yield _chunk_task(wh, chunk, config)


def _chunk_task(wh: Warehouse, windows: list[_Window], config: EventConfig) -> _DetectTask:
    """A chunk of windows with the samples of those with chains, read with one query (their
    ``part_ix`` counts them in order; none read when no window has chains)."""
    reading = [w for w in windows if w.chains]
    samples = None
    if reading:
        params = {
            "wagon_ids": [w.wagon_id for w in reading],
            "from_utc": [w.chains[0][0] for w in reading],
            "to_utc": [w.chains[-1][1] for w in reading],
        }
        samples = wh.con.sql(sql("q_events_chunk_samples"), params=params).to_arrow_table()
    return _DetectTask(tuple(windows), samples, config)


def _span_rows(chains: list[_Chain], group: list[_Chain]) -> int:
    """Samples of the chains from ``group``'s first to its last (those between included)."""
    first, last = chains.index(group[0]), chains.index(group[-1])
    return sum(c.rows for c in chains[first : last + 1])


def _load_groups(chains: list[_Chain], affected: list[_Chain]) -> list[list[_Chain]]:
    """The ``affected`` chains in groups read by one query: consecutive ones spanning at
    most ``_LOAD_ROWS`` samples (the chains between them included), or one longer chain."""
    position = {chain: i for i, chain in enumerate(chains)}
    rows_before = list(itertools.accumulate((c.rows for c in chains), initial=0))
    groups: list[list[_Chain]] = []
    group: list[_Chain] = []
    for chain in [*affected, None]:
        if group and (
            chain is None
            or rows_before[position[chain] + 1] - rows_before[position[group[0]]] > _LOAD_ROWS
        ):
            groups.append(group)
            group = []
        if chain is not None:
            group.append(chain)
    return groups


@dataclass(frozen=True)
class _Detected:
    """A wagon's touched chains and their events, detected again: what its transaction
    brings in line."""

    wagon_id: str
    affected: list[_Chain]
    events: pl.DataFrame


def _update_wagons(
    wh: Warehouse,
    batch: list[_Detected],
    dirty: dict[str, list[tuple[dt.datetime, dt.datetime]]],
    holding: set[str],
    update: EventUpdate,
) -> None:
    """Whole wagons, one transaction: each wagon's touched chains' events (detected again)
    brought in line with the stored ones (:func:`_line_up`), then one delete, one insert and
    the wagons' dirty ranges (``dirty``) removed. A wagon not in ``holding`` holds no events
    (:func:`_holding_events`): none are read to compare. ``update`` counts them once
    committed."""
    con = wh.con
    with wh.transaction():
        lined = [
            _line_up(wh, wagon, dirty[wagon.wagon_id], wagon.wagon_id in holding) for wagon in batch
        ]
        gone = [i for wagon_gone, _, _ in lined for i in wagon_gone]
        fresh = [frame for _, frame, _ in lined if frame.height]
        if gone:
            con.execute(sql("q_events_delete"), {"ids": gone})
        if fresh:
            _insert_events(con, pl.concat(fresh))
        con.execute(sql("q_events_clear_dirty"), {"wagon_ids": [w.wagon_id for w in batch]})
    for wagon, (wagon_gone, frame, unchanged) in zip(batch, lined, strict=True):
        update.wagons += 1
        update.chains += len(wagon.affected)
        update.added += frame.height
        update.removed += len(wagon_gone)
        update.unchanged += unchanged
        update.changed_ids.extend(sorted(frame["event_id"].to_list()))


def _line_up(
    wh: Warehouse, wagon: _Detected, dirty: list[tuple[dt.datetime, dt.datetime]], stored: bool
) -> tuple[list[str], pl.DataFrame, int]:
    """A wagon's stored events to delete (changed or vanished), its new events to insert
    (new or changed), how many are unchanged. ``stored=False``: it holds none to read."""
    windows = _merged([(c.from_utc, c.to_utc) for c in wagon.affected] + dirty, dt.timedelta(0))
    new = wagon.events
    old = _events_in(wh, wagon.wagon_id, windows) if stored else _NO_EVENTS
    new_rows = {row["event_id"]: row for row in new.iter_rows(named=True)}
    old_rows = {row["event_id"]: row for row in old.iter_rows(named=True)}
    gone = [i for i, row in old_rows.items() if new_rows.get(i) != row]
    fresh = [i for i, row in new_rows.items() if old_rows.get(i) != row]
    frame = new if len(fresh) == new.height else new.filter(pl.col("event_id").is_in(fresh))
    return gone, frame, len(new_rows) - len(fresh)


def _insert_events(con: duckdb.DuckDBPyConnection, events: pl.DataFrame) -> None:
    """Insert ``events`` (the detection's columns), stamped with ``detected_utc`` now."""
    batch = events.with_columns(pl.lit(_utc_now()).alias("detected_utc"))
    con.register("event_batch", batch)
    try:
        con.execute(sql("q_insert_events"))
    finally:
        con.unregister("event_batch")


_NO_EVENTS = pl.DataFrame(schema=EVENT_COLUMNS)


def _holding_events(wh: Warehouse, wagon_ids: list[str]) -> set[str]:
    """Which of ``wagon_ids`` hold stored events, in one query: the others' (every wagon of
    a first run) have none to compare with, and are not read again one by one."""
    if not wagon_ids:
        return set()
    rows = wh.con.execute(sql("q_events_holding_wagons"), {"wagon_ids": wagon_ids}).fetchall()
    return {str(r[0]) for r in rows}


def _events_in(
    wh: Warehouse, wagon_id: str, windows: list[tuple[dt.datetime, dt.datetime]]
) -> pl.DataFrame:
    """The stored events of a wagon overlapping one of the sorted disjoint ``windows``."""
    if not windows:
        return pl.DataFrame(schema=EVENT_COLUMNS)
    stored = wh.con.sql(
        sql("q_events_stored"),
        params={"wagon_id": wagon_id, "from_utc": windows[0][0], "to_utc": windows[-1][1]},
    ).pl()
    keep = [
        _overlaps(windows, start, end)
        for start, end in zip(stored["start_utc"], stored["end_utc"], strict=True)
    ]
    return stored.filter(pl.Series(keep, dtype=pl.Boolean)).cast(EVENT_COLUMNS)


def _utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(tzinfo=None)
