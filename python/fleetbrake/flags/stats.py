"""What the detectors measure: per segment of a wagon's timeline (:class:`Segment`, from the
stored timeline and the readings) and per braking (:class:`EventStat`, from the stored
predictions), and where the simulated block is unsure (:func:`unsure_mask`)."""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import NDArray

from fleetbrake.flags.config import DEFAULT_FLAG_CONFIG, FlagConfig
from fleetbrake.simulation.series import (
    BoolArray,
    FloatArray,
    WagonSeries,
    nan_running_mean,
    runs,
)

__all__ = [
    "EventStat",
    "Segment",
    "event_stats",
    "same_readings",
    "segment_stats",
    "unsure_mask",
]

_SAME_VALUE_KMH = 1e-9
"""km/h: logged speeds closer than this are one value repeated (numerical equality)."""


@dataclass(frozen=True)
class Segment:
    """A segment of the stored timeline, with its own anchor: a braking (activation to
    ``ChainParams.quiet_after_release_s`` after release), a quiet window or a gap, as the
    readings and the prediction show it. Start/end values are means over ``edge_s`` of valid
    readings at each end."""

    start: int
    stop: int
    """[start, stop), seconds since the series' t0."""
    kind: str
    """``braking``, ``quiet`` or ``gap`` (no rows)."""
    enough: bool
    """Long enough, with enough valid readings."""
    calm: bool
    """The simulated block is sure (no blind gap or frozen GPS speed within ``settle_s``)."""
    event_id: str | None
    speed_kmh: float
    """Mean speed."""
    pressure_max_bar: float
    ambient_c: float
    m_start: float
    m_end: float
    p_start: float
    p_end: float
    m_rise: float
    """Measured peak (after a running mean over ``smooth_s``) minus ``m_start``."""
    p_rise: float
    slope_k_per_h: float
    """Slope of measured - predicted, least squares."""
    line_rms_k: float
    """rms of measured - predicted about that line."""
    since_release_s: float
    """Seconds from the last release before the segment to its start (inf if none)."""
    m_ambient_k: float
    """Mean |measured - air| over the segment."""

    @property
    def judged(self) -> bool:
        return self.enough and self.calm

    @property
    def excess_k(self) -> float:
        """How much more the reading rose than predicted (negative: less)."""
        return (self.m_end - self.m_start) - (self.p_end - self.p_start)

    @property
    def ratio(self) -> float:
        return self.m_rise / self.p_rise if self.p_rise > 0 else math.nan


def unsure_mask(
    series: WagonSeries, gaps: Sequence[tuple[int, int]], config: FlagConfig = DEFAULT_FLAG_CONFIG
) -> BoolArray:
    """Seconds at which the simulated block is unsure: ``settle_s`` from the start of a data
    gap (``gaps``: the last row before it and the first after, as the timeline's ``gap``
    segments have them) at whose edges the wagon was moving faster than
    ``gap_moving_speed_kmh`` or braking (brakings may be missing), and of a braking over
    frozen GPS speed (its heat input is unknown)."""
    n = series.n
    unsure = np.zeros(n, dtype=bool)
    spans: list[tuple[int, int]] = []
    for a, b in gaps:
        edge = [k for k in (a, b) if 0 <= k < n]
        moving = any(series.speed_kmh[k] > config.gap_moving_speed_kmh for k in edge)
        braking = any(series.pressure_bar[k] > config.p_quiet_bar for k in edge)
        if moving or braking:
            spans.append((a, b))
    spans += frozen_speed_brakings(series, config)
    for a, b in spans:
        unsure[a : min(b + config.settle_s, n)] = True
    return unsure


def frozen_speed_brakings(
    series: WagonSeries, config: FlagConfig = DEFAULT_FLAG_CONFIG
) -> list[tuple[int, int]]:
    """Row spans ``[first, last + 1)`` of ``series`` where the GPS speed is frozen (one value
    above ``speed_frozen_min_kmh`` repeated to the last digit for ``speed_frozen_s`` or more: a
    live GPS jitters) while the brake is applied: the heat input of such a braking is unknown
    (the flags treat its block as unsure; the close loop leaves its event out)."""
    spans: list[tuple[int, int]] = []
    speed = series.speed_raw_kmh
    idx = np.flatnonzero(np.isfinite(speed))
    if idx.size > 1:
        same = (np.abs(np.diff(speed[idx])) < _SAME_VALUE_KMH) & (
            speed[idx][1:] > config.speed_frozen_min_kmh
        )
        for a, b in runs(same):
            first, last = int(idx[a]), int(idx[b])
            if last - first + 1 >= config.speed_frozen_s and np.any(
                series.pressure_bar[first : last + 1] > config.p_quiet_bar
            ):
                spans.append((first, last + 1))
    return spans


def _segment_sums(values: FloatArray, starts: np.ndarray, counts: np.ndarray) -> FloatArray:
    """Per segment the sum of its slice of ``values`` (consecutive slices from ``starts``,
    ``counts`` long; 0 for an empty one)."""
    out = np.zeros(counts.size)
    full = counts > 0
    if full.any():
        out[full] = np.add.reduceat(values, starts[full]) if values.size else 0.0
    return out


def _segment_reduce(
    ufunc: np.ufunc, values: np.ndarray, starts: np.ndarray, counts: np.ndarray, empty: float
) -> FloatArray:
    out = np.full(counts.size, empty)
    full = counts > 0
    if full.any() and values.size:
        out[full] = ufunc.reduceat(values, starts[full])
    return out


def _edge_means(
    values: FloatArray, first: np.ndarray, counts: np.ndarray, width: int
) -> FloatArray:
    """Per segment the mean of ``values[first + j]`` for ``j < min(width, count)``."""
    j = np.arange(width)
    take = j[None, :] < counts[:, None]
    at = np.where(take, first[:, None] + j[None, :], 0)
    picked = values[at] if values.size else np.zeros(at.shape)
    size = np.minimum(counts, width)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(take, picked, 0.0).sum(axis=1) / size


def segment_stats(
    series: WagonSeries,
    predicted_c: FloatArray,
    bounds: Sequence[int],
    kinds: Sequence[str],
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    *,
    unsure: BoolArray | None = None,
    invalid: BoolArray | None = None,
) -> list[Segment]:
    """The :class:`Segment` of each [bounds[i], bounds[i+1]) of the series and its prediction.

    Computed over the series' columns at once: the valid seconds (a reading and a prediction)
    compressed, each segment a consecutive slice of them, its sums taken with ``reduceat``."""
    measured = series.measured_c.copy()
    if invalid is not None:
        measured[invalid] = np.nan
    releases = sorted(b for _, _, b, _ in series.events)
    event_at = {a: event_id for event_id, a, _, _ in series.events}
    smooth = nan_running_mean(measured, config.smooth_s)
    edges = np.asarray(bounds, dtype=np.int64)
    if edges.size < 2:
        return []
    a_all, b_all = edges[:-1], edges[1:]
    ok = np.isfinite(measured) & np.isfinite(predicted_c)
    ranks = np.concatenate([[0], np.cumsum(ok)])
    first = ranks[a_all]
    count = ranks[b_all] - first
    pos = np.flatnonzero(ok)
    mv, pv = measured[pos], predicted_c[pos]
    seg = np.repeat(np.arange(a_all.size), count)
    k = (pos - a_all[seg]).astype(np.float64)  # seconds since the segment's start
    r = mv - pv
    size = np.maximum(count, 1).astype(np.float64)
    has = count >= 2
    # the least-squares line of measured - predicted against k, as np.polyfit has it
    k_mean = _segment_sums(k, first, count) / size
    r_mean = _segment_sums(r, first, count) / size
    dk = k - k_mean[seg]
    dr = r - r_mean[seg]
    s_kk = _segment_sums(dk * dk, first, count)
    s_kr = _segment_sums(dk * dr, first, count)
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = np.where(has, s_kr / s_kk, math.nan)
    intercept = r_mean - slope * k_mean
    line = r - (slope[seg] * k + intercept[seg])
    rms = np.sqrt(_segment_sums(line * line, first, count) / size)
    m_start = _edge_means(mv, first, count, config.edge_s)
    p_start = _edge_means(pv, first, count, config.edge_s)
    last = ranks[b_all] - np.minimum(count, config.edge_s)
    m_end = _edge_means(mv, last, count, config.edge_s)
    p_end = _edge_means(pv, last, count, config.edge_s)
    m_peak = _segment_reduce(np.fmax, smooth[pos], first, count, math.nan)
    p_peak = _segment_reduce(np.maximum, pv, first, count, math.nan)
    m_ambient = _segment_sums(np.abs(mv - series.ambient_c[pos]), first, count) / size
    length = b_all - a_all
    speed = _segment_sums(series.speed_kmh, a_all, length) / np.maximum(length, 1)
    pressure = _segment_reduce(np.maximum, series.pressure_bar, a_all, length, math.nan)
    ambient = _segment_sums(series.ambient_c, a_all, length) / np.maximum(length, 1)
    if unsure is not None:
        shaky = np.concatenate([[0], np.cumsum(unsure)])
        calm = shaky[b_all] - shaky[a_all] == 0
    else:
        calm = np.ones(a_all.size, dtype=bool)
    enough = (
        (length >= config.min_segment_s)
        & (count >= 2 * config.edge_s)
        & (count >= config.min_valid_fraction * length)
    )
    since_j = np.searchsorted(np.asarray(releases, dtype=np.int64), a_all, side="right") - 1
    nan = math.nan
    out = []
    for i in range(a_all.size):
        a, b = int(a_all[i]), int(b_all[i])
        j = int(since_j[i])
        since = a - releases[j] if j >= 0 else math.inf
        full = bool(has[i])
        out.append(
            Segment(
                start=a,
                stop=b,
                kind=kinds[i],
                enough=bool(enough[i]),
                calm=bool(calm[i]),
                event_id=event_at.get(a) if kinds[i] == "braking" else None,
                speed_kmh=float(speed[i]) if b > a else nan,
                pressure_max_bar=float(pressure[i]),
                ambient_c=float(ambient[i]) if b > a else nan,
                m_start=float(m_start[i]) if full else nan,
                m_end=float(m_end[i]) if full else nan,
                p_start=float(p_start[i]) if full else nan,
                p_end=float(p_end[i]) if full else nan,
                m_rise=float(m_peak[i] - m_start[i]) if full else nan,
                p_rise=float(p_peak[i] - p_start[i]) if full else nan,
                slope_k_per_h=float(slope[i]) * 3600.0 if full else nan,
                line_rms_k=float(rms[i]) if full else nan,
                since_release_s=float(since),
                m_ambient_k=float(m_ambient[i]) if full else nan,
            )
        )
    return out


def same_readings(series: WagonSeries, invalid_a: BoolArray, invalid_b: BoolArray) -> bool:
    """Whether leaving out the readings at ``invalid_a`` or at ``invalid_b`` leaves the same
    readings: they differ only at seconds without a finite reading, which
    :func:`segment_stats` ignores either way, so it gives the same segments for both (a
    span's second call is then skipped: most spans have no sensor fault)."""
    differ = invalid_a != invalid_b
    return not bool(np.isfinite(series.measured_c[differ]).any())


@dataclass(frozen=True)
class EventStat:
    """One braking as the revision's predictions show it."""

    event_id: str
    start_utc: dt.datetime
    end_utc: dt.datetime
    window_end_utc: dt.datetime
    judged: bool
    m_rise: float
    p_rise: float
    contact_max_c: float
    contact_max_utc: dt.datetime
    v_start_kmh: float
    v_end_kmh: float
    p_max_bar: float

    @property
    def ratio(self) -> float:
        return self.m_rise / self.p_rise if self.p_rise > 0 else math.nan


class _Times:
    """A naive ``Datetime("us")`` column's values as :class:`datetime.datetime`, made only
    for the rows asked for (``to_list`` made one per prediction row: 3 ms a wagon-day)."""

    def __init__(self, us: NDArray[np.datetime64]) -> None:
        self._us = us

    def __getitem__(self, i: int) -> dt.datetime:
        value = self._us[i].item()
        assert isinstance(value, dt.datetime)
        return value


def _times(column: pl.Series) -> _Times | list[dt.datetime]:
    if column.dtype == pl.Datetime("us", None) and not column.has_nulls():
        return _Times(column.to_numpy())
    return column.to_list()


def _by_event_and_time(predictions: pl.DataFrame) -> bool:
    """Whether ``predictions`` is already sorted by ``event_id``, then ``time_utc`` (no nulls
    in either): its stable sort on them would change nothing, and is not computed."""
    ids, times = predictions["event_id"], predictions["time_utc"]
    if ids.has_nulls() or times.has_nulls() or not ids.is_sorted():
        return False
    later = (times >= times.shift(1)) | (ids != ids.shift(1))
    return bool(later.slice(1).all())


def _runs_of(ids: pl.Series) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Starts and stops of the runs of equal values of ``ids`` (a string column; a null
    equals a null, as numpy's ``!=`` on the column's objects had it)."""
    if ids.len() == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    changes = ids.slice(1).ne_missing(ids.slice(0, ids.len() - 1)).to_numpy()
    cut = np.flatnonzero(changes) + 1
    starts = np.concatenate([[0], cut]).astype(np.int64)
    stops = np.concatenate([cut, [ids.len()]]).astype(np.int64)
    return starts, stops


def event_stats(
    predictions: pl.DataFrame,
    events: pl.DataFrame,
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    *,
    excluded: Sequence[tuple[dt.datetime, dt.datetime]] = (),
    unsure: Sequence[tuple[dt.datetime, dt.datetime]] = (),
) -> list[EventStat]:
    """Per braking (``events``: ``event_id``, ``start_utc``, ``end_utc``, optional
    ``complete``) the measured and predicted rise from activation to the peak of its window in
    ``predictions`` (rows of one wagon and revision). A braking is not judged when incomplete,
    when its window overlaps ``excluded`` (sensor faults), when [activation - settle_s,
    release] overlaps ``unsure``, or with too few valid readings."""
    out: list[EventStat] = []
    if predictions.height == 0:
        return out
    # the wagon's windows as columns, sorted by event and time once (not again when they
    # come sorted: the stage's reads hand them so); each event a slice (one polars query for
    # every column: each call costs about as much as its arithmetic)
    windows = predictions.lazy()
    if not _by_event_and_time(predictions):
        windows = windows.sort(["event_id", "time_utc"], maintain_order=True)
    rows = (
        windows.select(
            "event_id",
            "time_utc",
            pl.col("measured_sensor_c").cast(pl.Float64).fill_null(np.nan),
            pl.col("predicted_sensor_c").cast(pl.Float64),
            pl.col("predicted_contact_max_c").cast(pl.Float64),
            pl.col("brake_pressure_bar").cast(pl.Float64).fill_null(0.0),
            pl.col("speed_kmh").cast(pl.Float64).fill_null(0.0),
            (pl.col("phase") == "heating").fill_null(False).alias("heating"),
        ).collect(engine="in-memory")  # the engine eager calls run on
    )
    ids = rows["event_id"]
    times = _times(rows["time_utc"])
    m_all = rows["measured_sensor_c"].to_numpy()
    p_all = rows["predicted_sensor_c"].to_numpy()
    cmax_all = rows["predicted_contact_max_c"].to_numpy()
    pressure_all = rows["brake_pressure_bar"].to_numpy()
    speed_all = rows["speed_kmh"].to_numpy()
    heating_all = rows["heating"].to_numpy()
    starts, stops = _runs_of(ids)
    by_event = {
        str(event_id): (int(a), int(b))
        for event_id, a, b in zip(ids.gather(starts).to_list(), starts, stops, strict=True)
    }
    lead = dt.timedelta(seconds=config.settle_s)
    for row in events.sort("start_utc").iter_rows(named=True):
        where = by_event.get(row["event_id"])
        if where is None or where[1] - where[0] < 2:
            continue
        a, b = where
        m, p, cmax = m_all[a:b], p_all[a:b], cmax_all[a:b]
        w0, w1 = times[a], times[b - 1]
        valid = np.isfinite(m)
        start_vals = m[: config.rise_start_s][valid[: config.rise_start_s]]
        judged = bool(row.get("complete", True)) and valid.mean() >= config.min_valid_fraction
        judged = judged and start_vals.size > 0
        judged = judged and not any(x < w1 and w0 < y for x, y in excluded)
        judged = judged and not any(
            x < row["end_utc"] and row["start_utc"] - lead < y for x, y in unsure
        )
        m0 = float(start_vals.mean()) if start_vals.size else math.nan
        smooth = nan_running_mean(m, config.smooth_s)
        m_rise = float(np.nanmax(smooth) - m0) if np.isfinite(smooth).any() else math.nan
        p_rise = float(p.max() - p[0])
        k = int(np.argmax(cmax))
        speed, heating = speed_all[a:b], heating_all[a:b]
        v_h = speed[heating] if heating.any() else speed
        out.append(
            EventStat(
                event_id=row["event_id"],
                start_utc=row["start_utc"],
                end_utc=row["end_utc"],
                window_end_utc=w1,
                judged=judged and math.isfinite(m_rise),
                m_rise=m_rise,
                p_rise=p_rise,
                contact_max_c=float(cmax[k]),
                contact_max_utc=times[a + k],
                v_start_kmh=float(v_h[0]),
                v_end_kmh=float(v_h[-1]),
                p_max_bar=float(pressure_all[a:b].max()),
            )
        )
    return out
