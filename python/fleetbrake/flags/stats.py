"""What the detectors measure: per segment of a wagon's timeline (:class:`Segment`, from the
stored timeline and the readings) and per braking (:class:`EventStat`, from the stored
predictions), and where the simulated block is unsure (:func:`unsure_mask`)."""

from __future__ import annotations

import datetime as dt
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl

from fleetbrake.flags.config import DEFAULT_FLAG_CONFIG, FlagConfig
from fleetbrake.simulation.series import (
    BoolArray,
    FloatArray,
    WagonSeries,
    nan_running_mean,
    runs,
)

__all__ = ["EventStat", "Segment", "event_stats", "segment_stats", "unsure_mask"]

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
    # frozen GPS speed over a braking (one value repeated to the last digit: a live GPS
    # jitters)
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
    for a, b in spans:
        unsure[a : min(b + config.settle_s, n)] = True
    return unsure


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
    """The :class:`Segment` of each [bounds[i], bounds[i+1]) of the series and its prediction."""
    measured = series.measured_c.copy()
    if invalid is not None:
        measured[invalid] = np.nan
    releases = sorted(b for _, _, b, _ in series.events)
    event_at = {a: event_id for event_id, a, _, _ in series.events}
    smooth = nan_running_mean(measured, config.smooth_s)
    out = []
    for i, (a, b) in enumerate(itertools.pairwise(bounds)):
        m = measured[a:b]
        p = predicted_c[a:b]
        ok = np.isfinite(m) & np.isfinite(p)
        idx = np.flatnonzero(ok)
        length = b - a
        enough = (
            length >= config.min_segment_s
            and idx.size >= 2 * config.edge_s
            and idx.size >= config.min_valid_fraction * length
        )
        calm = unsure is None or not unsure[a:b].any()
        nan = math.nan
        if idx.size >= 2:
            head, tail = idx[: config.edge_s], idx[-config.edge_s :]
            m_start, m_end = float(m[head].mean()), float(m[tail].mean())
            p_start, p_end = float(p[head].mean()), float(p[tail].mean())
            r = m[idx] - p[idx]
            k = idx.astype(np.float64)
            slope, intercept = np.polyfit(k, r, 1)
            rms = float(np.sqrt(np.mean((r - (slope * k + intercept)) ** 2)))
            sm = smooth[a:b][idx]
            m_rise = float(np.nanmax(sm) - m_start)
            p_rise = float(np.max(p[idx]) - p_start)
            m_ambient = float(np.mean(np.abs(m[idx] - series.ambient_c[a:b][idx])))
        else:
            m_start = m_end = p_start = p_end = m_rise = p_rise = nan
            slope, rms, m_ambient = nan, nan, nan
        j = np.searchsorted(releases, a, side="right") - 1
        since = a - releases[j] if j >= 0 else math.inf
        out.append(
            Segment(
                start=int(a),
                stop=int(b),
                kind=kinds[i],
                enough=bool(enough),
                calm=bool(calm),
                event_id=event_at.get(a) if kinds[i] == "braking" else None,
                speed_kmh=float(series.speed_kmh[a:b].mean()),
                pressure_max_bar=float(series.pressure_bar[a:b].max()),
                ambient_c=float(series.ambient_c[a:b].mean()),
                m_start=m_start,
                m_end=m_end,
                p_start=p_start,
                p_end=p_end,
                m_rise=m_rise,
                p_rise=p_rise,
                slope_k_per_h=float(slope) * 3600.0,
                line_rms_k=rms,
                since_release_s=float(since),
                m_ambient_k=m_ambient,
            )
        )
    return out


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
    out = []
    by_event = {key[0]: group for key, group in predictions.group_by(["event_id"])}
    for row in events.sort("start_utc").iter_rows(named=True):
        group = by_event.get(row["event_id"])
        if group is None or group.height < 2:
            continue
        group = group.sort("time_utc")
        times = group["time_utc"]
        m = group["measured_sensor_c"].cast(pl.Float64).fill_null(np.nan).to_numpy()
        p = group["predicted_sensor_c"].to_numpy().astype(np.float64)
        cmax = group["predicted_contact_max_c"].to_numpy().astype(np.float64)
        w0, w1 = times[0], times[-1]
        valid = np.isfinite(m)
        start_vals = m[: config.rise_start_s][valid[: config.rise_start_s]]
        judged = bool(row.get("complete", True)) and valid.mean() >= config.min_valid_fraction
        judged = judged and start_vals.size > 0
        judged = judged and not any(a < w1 and w0 < b for a, b in excluded)
        lead = dt.timedelta(seconds=config.settle_s)
        judged = judged and not any(
            a < row["end_utc"] and row["start_utc"] - lead < b for a, b in unsure
        )
        m0 = float(start_vals.mean()) if start_vals.size else math.nan
        smooth = nan_running_mean(m, config.smooth_s)
        m_rise = float(np.nanmax(smooth) - m0) if np.isfinite(smooth).any() else math.nan
        p_rise = float(p.max() - p[0])
        k = int(np.argmax(cmax))
        pressure = group["brake_pressure_bar"].cast(pl.Float64).fill_null(0.0).to_numpy()
        speed = group["speed_kmh"].cast(pl.Float64).fill_null(0.0).to_numpy()
        heating = (group["phase"] == "heating").to_numpy()
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
                contact_max_utc=times[k],
                v_start_kmh=float(v_h[0]),
                v_end_kmh=float(v_h[-1]),
                p_max_bar=float(pressure.max()),
            )
        )
    return out
