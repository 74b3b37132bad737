"""Braking events: detected from the brake cylinder pressure and the speed of each wagon.

::

    from fleetbrake.ingest.detection import detect_events

    events = detect_events(samples, "SGG-0001")     # pure: one wagon's samples -> events frame

How an event is found (defaults of :class:`~fleetbrake.ingest.config.EventConfig`):

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

:mod:`fleetbrake.ingest.events` keeps the warehouse's ``events`` table up to date with it.
"""

from __future__ import annotations

import datetime as dt
import itertools
import math
from dataclasses import dataclass

import numpy as np
import polars as pl

from fleetbrake.ingest.config import EventConfig

__all__ = ["EVENT_COLUMNS", "detect_events", "physical_us", "shrinking_running_median"]

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
        time_us = physical_us(frame["time_utc"])
        if not np.all(np.diff(time_us) > 0):  # not sorted, or a time repeated
            frame = frame.sort("time_utc", maintain_order=True).unique(
                subset="time_utc", keep="first", maintain_order=True
            )
            time_us = physical_us(frame["time_utc"])
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


def physical_us(times: pl.Series) -> np.ndarray:
    """Microseconds since the epoch of a ``Datetime("us")`` column without nulls."""
    return times.to_numpy().view(np.int64)


def _utc(time_us: int) -> dt.datetime:
    return dt.datetime(1970, 1, 1) + dt.timedelta(microseconds=time_us)


def _none_if_nan(value: float) -> float | None:
    return None if math.isnan(value) else value
