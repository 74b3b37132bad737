"""The estimator's opinion on a wagon: brakes and sensor judged from the virtual sensor
(:mod:`fleetbrake.model.estimator`: a Kalman filter on the reduced model with the heat the
declared inputs do not explain as an unknown input).

* :func:`find_dragging_estimated`: unexplained heat power into the block whose lower 95 %
  bound stays above ``est_drag_min_power_w`` for ``est_drag_min_s`` with the cylinder
  released, moving.
* :func:`find_weak_estimated`: brakings over which the unexplained energy is below minus
  ``est_weak_fraction`` of the declared braking energy, its upper bound below zero too (in
  proportion to the declared braking energy).
* :func:`find_innovation_faults`: a reading that leaves the model faster than any heat into
  the block could move it: windows of normalised innovations far above their chi-square
  level (``est_nis_max``) while the unexplained power stays within its bounds; they date a
  fault before the temperatures look wrong.

Each takes an :class:`EstimateOnGrid`: the columns of ``v_contact_estimates``
(``shared/spec/interface.md`` v2) on the 1 Hz grid of the wagon's series
(:func:`estimate_on_grid` from the stage's stored rows: the estimation stage,
:mod:`fleetbrake.simulation.estimates`, is the one place a wagon is estimated; a wagon whose
stored estimates are not current with its data is judged without this opinion).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl

from fleetbrake.flags.config import DEFAULT_FLAG_CONFIG, FlagConfig
from fleetbrake.flags.records import Finding
from fleetbrake.flags.text import at_text, duration_text, speeds_text, when_text
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.physics import (
    KMH_TO_M_S,
    block_flux_w_m2,
    block_force_n,
    frictional_flux_w_m2,
)
from fleetbrake.simulation.estimates import reading_noise_k
from fleetbrake.simulation.series import (
    BoolArray,
    FloatArray,
    WagonSeries,
    merge_spans,
    runs,
    seconds_since,
)

__all__ = [
    "ESTIMATE_COLUMNS",
    "EstimateOnGrid",
    "declared_heat_w",
    "estimate_on_grid",
    "find_dragging_estimated",
    "find_innovation_faults",
    "find_weak_estimated",
    "sensor_noise_k",
]

ESTIMATE_COLUMNS: tuple[str, ...] = (
    "contact_mean_c",
    "contact_mean_lo_c",
    "contact_mean_hi_c",
    "contact_max_c",
    "contact_max_hi_c",
    "unexplained_power_w",
    "unexplained_power_lo_w",
    "unexplained_power_hi_w",
    "innovation_k",
)
"""The columns of ``v_contact_estimates`` the detectors read (with ``time_utc``)."""


@dataclass(frozen=True)
class EstimateOnGrid:
    """A wagon span's estimate on its series' 1 Hz grid (NaN where there is none): the
    columns of ``v_contact_estimates`` as arrays, the temperatures and the power after the
    fact (smoothed, where there is a smoothed estimate: the flags judge the past), the
    innovations filtered; and ``settled``, the seconds at which the estimate is judged (the
    filter has converged from its prior)."""

    contact_mean_c: FloatArray
    contact_mean_lo_c: FloatArray
    contact_mean_hi_c: FloatArray
    contact_max_c: FloatArray
    contact_max_hi_c: FloatArray
    unexplained_power_w: FloatArray
    unexplained_power_lo_w: FloatArray
    unexplained_power_hi_w: FloatArray
    innovation_k: FloatArray
    settled: BoolArray


def estimate_on_grid(
    series: WagonSeries, frame: pl.DataFrame, config: FlagConfig = DEFAULT_FLAG_CONFIG
) -> EstimateOnGrid:
    """The rows of ``frame`` (``time_utc`` and :data:`ESTIMATE_COLUMNS`, as
    ``v_contact_estimates`` has them for one wagon and revision) on ``series``' grid; the
    first ``est_settle_s`` seconds after the first estimate are not ``settled``."""
    n = series.n
    out = {name: np.full(n, np.nan) for name in ESTIMATE_COLUMNS}
    has = np.zeros(n, dtype=bool)
    if frame.height:
        k = seconds_since(frame["time_utc"], series.t0)
        inside = (k >= 0) & (k < n)
        at = k[inside]
        whole = bool(inside.all())  # the span holds every row: no copy of them
        for name in ESTIMATE_COLUMNS:  # no polars query: a float column's nulls are NaN
            column = frame[name]
            values = (column if column.dtype == pl.Float64 else column.cast(pl.Float64)).to_numpy()
            out[name][at] = values if whole else values[inside]
        has[at] = True
    settled = has.copy()
    first = np.flatnonzero(has)
    if first.size:
        settled[: first[0] + config.est_settle_s] = False
    return EstimateOnGrid(settled=settled, **out)


# --------------------------------------------------------------------------------------------
# The sensor's noise


def sensor_noise_k(measured_c: FloatArray) -> float:
    """The thermistor's noise from its readings on a 1 Hz grid: the estimation stage's σ_v
    rule (:func:`fleetbrake.simulation.estimates.reading_noise_k`), so that the innovations
    are judged against the noise the estimator ran with."""
    return reading_noise_k(np.arange(measured_c.size, dtype=np.float64), measured_c)


def declared_heat_w(wagon: WagonConfig, series: WagonSeries) -> FloatArray:
    """W: the declared heat input into the block at each second of ``series`` (force chain,
    friction, heat partition of the declared model; 0 where pressure or speed is unknown)."""
    p = np.nan_to_num(series.pressure_bar, nan=0.0)
    v = np.nan_to_num(series.speed_kmh, nan=0.0)
    force = np.asarray(block_force_n(wagon, np.maximum(p, 0.0)), dtype=np.float64)
    power = wagon.friction_coefficient * force * np.maximum(v, 0.0) * KMH_TO_M_S
    flux = np.asarray(block_flux_w_m2(wagon, frictional_flux_w_m2(wagon, power)))
    return np.asarray(flux, dtype=np.float64) * wagon.geometry.contact_area_m2


# --------------------------------------------------------------------------------------------
# Words


def _power_text(mean: float, lo: float, hi: float) -> str:
    return f"{mean:.0f} W (95 %: {lo:.0f} to {hi:.0f} W)"


def _contact_text(est: EstimateOnGrid, a: int, b: int) -> str:
    """'the estimated contact temperature peaked at 93.1 °C (95 %: 90.2-96.0 °C; face
    maximum up to 98.4 °C)' over [a, b)."""
    mean = est.contact_mean_c[a:b]
    if not np.isfinite(mean).any():
        return "no contact temperature was estimated"
    k = a + int(np.nanargmax(mean))
    top = est.contact_max_hi_c[a:b]
    peak_max = float(np.nanmax(est.contact_max_c[a:b]))
    upper = float(np.nanmax(top)) if np.isfinite(top).any() else peak_max
    return (
        f"the estimated contact temperature peaked at {est.contact_mean_c[k]:.1f} °C (95 %: "
        f"{est.contact_mean_lo_c[k]:.1f} to {est.contact_mean_hi_c[k]:.1f} °C; face maximum "
        f"{peak_max:.1f} °C, at most {upper:.1f} °C)"
    )


# --------------------------------------------------------------------------------------------
# Detectors


def find_dragging_estimated(
    series: WagonSeries,
    est: EstimateOnGrid,
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    *,
    excluded: Sequence[tuple[int, int]] = (),
) -> list[Finding]:
    """Unexplained heat power into the block with its lower 95 % bound above
    ``est_drag_min_power_w`` for at least ``est_drag_min_s`` seconds with the cylinder
    released (at most ``p_quiet_bar``) and the wagon moving (``drag_min_speed_kmh``); runs
    closer than ``est_drag_join_s`` are one. Seconds in ``excluded`` ([start, stop): sensor
    faults) and not ``settled`` are not used."""
    released = np.nan_to_num(series.pressure_bar, nan=np.inf) <= config.p_quiet_bar
    moving = np.nan_to_num(series.speed_kmh, nan=0.0) >= config.drag_min_speed_kmh
    lo = np.nan_to_num(est.unexplained_power_lo_w, nan=-np.inf)
    hot = released & moving & est.settled & (lo > config.est_drag_min_power_w)
    for a, b in excluded:
        hot[max(a, 0) : max(b, 0)] = False
    out = []
    for a, b in merge_spans(runs(hot), config.est_drag_join_s):
        seconds = int(hot[a:b].sum())
        if seconds < config.est_drag_min_s:
            continue
        sel = np.flatnonzero(hot[a:b]) + a
        power = float(np.mean(est.unexplained_power_w[sel]))
        p_lo = float(np.mean(est.unexplained_power_lo_w[sel]))
        p_hi = float(np.mean(est.unexplained_power_hi_w[sel]))
        speed = float(np.nanmean(series.speed_kmh[sel]))
        pressure = float(np.nanmax(series.pressure_bar[sel]))
        start, end = series.utc(a), series.utc(b)
        severity = (
            "alarm" if power * seconds / 1000.0 >= config.drag_alarm_excess_k * 100 else "warning"
        )
        out.append(
            Finding(
                "dragging_brake",
                severity,
                start,
                end,
                f"Block of {series.wagon_id} took in {_power_text(power, p_lo, p_hi)} of heat "
                f"the declared inputs do not explain {when_text(start, end)} "
                f"({duration_text(seconds)} at {speed:.0f} km/h on average) with at most "
                f"{max(pressure, 0.0):.2f} bar in the brake cylinder; "
                f"{_contact_text(est, a, b)}: check for a dragging brake (handbrake left on, "
                "stuck distributor or release valve, binding rigging).",
                detail="estimator",
            )
        )
    return out


@dataclass(frozen=True)
class _Braking:
    event_id: str
    start: int
    stop: int
    """Window end: ``est_tail_s`` after the release, or the next activation."""
    declared_j: float
    unexplained_j: float
    unexplained_hi_j: float
    """The sum of the power's upper 95 % bounds over the window (an upper bound of the
    unexplained energy: the bounds of the seconds are not independent)."""
    end_hi_w: float
    end_w: float
    end_lo_w: float


def _brakings(
    series: WagonSeries,
    est: EstimateOnGrid,
    heat_w: FloatArray,
    config: FlagConfig,
    excluded: Sequence[tuple[int, int]],
) -> list[_Braking]:
    events = sorted(series.events, key=lambda e: e[1])
    out = []
    for i, (event_id, a, b, complete) in enumerate(events):
        nxt = events[i + 1][1] if i + 1 < len(events) else series.n
        stop = min(b + config.est_tail_s, nxt, series.n)
        if not complete or stop - a < 2 or not est.settled[a:stop].all():
            continue
        if any(x < stop and a < y for x, y in excluded):
            continue
        power = est.unexplained_power_w[a:stop]
        if not np.isfinite(power).all():
            continue
        braking = slice(a, max(b, a + 1))
        declared = float(np.sum(heat_w[braking]))
        out.append(
            _Braking(
                event_id,
                a,
                stop,
                declared,
                float(np.sum(power)),
                float(np.sum(est.unexplained_power_hi_w[a:stop])),
                float(est.unexplained_power_hi_w[stop - 1]),
                float(est.unexplained_power_w[stop - 1]),
                float(est.unexplained_power_lo_w[stop - 1]),
            )
        )
    return out


def find_weak_estimated(
    series: WagonSeries,
    est: EstimateOnGrid,
    heat_w: FloatArray,
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    *,
    excluded: Sequence[tuple[int, int]] = (),
    predicted_rise_k: Mapping[str, float] | None = None,
) -> list[Finding]:
    """Runs of weak brakings (at least ``weak_min_events``, no normal braking between them):
    over a braking's window (activation to ``event_tail_s`` after release) the unexplained
    energy is below minus ``est_weak_fraction`` of the declared braking energy (``heat_w``,
    :func:`declared_heat_w`), and its upper bound (the power's upper 95 % bounds summed over
    the window) below minus ``est_weak_bound_fraction`` of it: the upper bound below zero, in
    proportion to the declared braking energy.
    Brakings declaring less than ``est_weak_min_kj`` are not judged. With
    ``predicted_rise_k`` (the revision's predicted sensor rise per event id), the missing
    share times the predicted rise must reach ``weak_min_deficit_k`` too (scaled with the
    residual spread: a shortfall within the model's error is neither weak nor normal), and a
    braking without a prediction is not judged."""
    out: list[Finding] = []
    run: list[_Braking] = []

    def close() -> None:
        if len(run) < config.weak_min_events:
            return
        shares = np.array([-x.unexplained_j / x.declared_j for x in run])
        median = float(np.median(shares))
        worst = max(run, key=lambda x: -x.unexplained_j / x.declared_j)
        start, end = series.utc(run[0].start), series.utc(run[-1].stop)
        what = (
            f"the braking {at_text(start)}"
            if len(run) == 1
            else f"{len(run)} brakings {when_text(start, end)}"
        )
        v = series.speed_kmh[worst.start : worst.stop]
        v = v[np.isfinite(v)]
        speeds = speeds_text(float(v[0]), float(v[-1])) if v.size else "at unknown speed"
        out.append(
            Finding(
                "weak_brake",
                "alarm" if median > 1.0 - config.weak_alarm_ratio else "warning",
                start,
                end,
                f"Block of {series.wagon_id} received {100 * median:.0f} % less heat than "
                f"declared in {what} (e.g. {-worst.unexplained_j / 1000:.0f} kJ of "
                f"{worst.declared_j / 1000:.0f} kJ missing {at_text(series.utc(worst.start))}, "
                f"{speeds}; unexplained power {_power_text(worst.end_w, worst.end_lo_w, worst.end_hi_w)} "
                f"after it; {_contact_text(est, worst.start, worst.stop)}): the block presses "
                "with too little force; check the brake cylinder, rigging, slack adjuster and the "
                "blocks.",
                event_id=run[0].event_id if len(run) == 1 else None,
                detail="estimator",
            )
        )

    for x in _brakings(series, est, heat_w, config, excluded):
        if x.declared_j < 1000.0 * config.est_weak_min_kj:
            continue
        share = -x.unexplained_j / x.declared_j
        if predicted_rise_k is not None:
            rise = predicted_rise_k.get(x.event_id)
            if rise is None or not math.isfinite(rise):
                continue
            if share >= config.est_weak_fraction and share * rise < config.weak_min_deficit_k:
                continue  # within the model's error: neither weak nor normal
        weak = (
            x.unexplained_j < -config.est_weak_fraction * x.declared_j
            and x.unexplained_hi_j < -config.est_weak_bound_fraction * x.declared_j
        )
        if weak:
            run.append(x)
        else:
            close()
            run = []
    close()
    return out


def find_innovation_faults(
    series: WagonSeries,
    est: EstimateOnGrid,
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    *,
    scale_k: float,
) -> list[tuple[int, int]]:
    """Where the readings leave the model faster than any heat could move the block: windows
    of ``est_nis_window_s`` valid innovations whose mean squared value, in units of
    ``scale_k`` squared (the innovations' spread where the model holds: the sensor's noise or
    the revision's residual spread, whichever is larger), exceeds ``est_nis_max``; as
    [start, stop) seconds, overlapping windows joined."""
    nu = est.innovation_k
    ok = np.isfinite(nu) & est.settled
    idx = np.flatnonzero(ok)
    w = config.est_nis_window_s
    if idx.size < w or scale_k <= 0:
        return []
    z2 = (nu[idx] / scale_k) ** 2
    csum = np.concatenate([[0.0], np.cumsum(z2)])
    mean = (csum[w:] - csum[:-w]) / w
    bad = np.flatnonzero(mean > config.est_nis_max)
    spans = [(int(idx[k]), int(idx[k + w - 1]) + 1) for k in bad]
    return merge_spans(spans, w) if spans else []


# --------------------------------------------------------------------------------------------
# Two opinions, one flag


_RANK = {"info": 0, "warning": 1, "alarm": 2}


def combine_opinions(
    timeline: Sequence[Finding], estimator: Sequence[Finding], gap_s: float
) -> list[Finding]:
    """The brake findings of the timeline's detectors and of the estimator's, one flag per
    anomaly: findings of one kind that overlap or lie within ``gap_s`` of each other are one,
    spanning them all, with the highest severity; its evidence is the timeline's (what the
    reading did against the prediction) followed by the estimator's (the power and the contact
    temperature), or the estimator's alone when only it saw the anomaly. Other kinds pass
    through."""
    out: list[Finding] = []
    for kind in ("dragging_brake", "weak_brake"):
        items = sorted(
            [(f, 0) for f in timeline if f.kind == kind]
            + [(f, 1) for f in estimator if f.kind == kind],
            key=lambda x: (x[0].start_utc, x[0].end_utc),
        )
        groups: list[list[tuple[Finding, int]]] = []
        for item in items:
            if groups:
                end = max(f.end_utc for f, _ in groups[-1])
                if (item[0].start_utc - end).total_seconds() <= gap_s:
                    groups[-1].append(item)
                    continue
            groups.append([item])
        for group in groups:
            own = [f for f, source in group if source == 0]
            theirs = [f for f, source in group if source == 1]
            if not theirs or len(group) == 1:
                out += [f for f, _ in group]  # one opinion alone: as it found them
                continue
            head = own[0] if own else theirs[0]
            evidence = " ".join(f.evidence for f in own)
            if own and theirs:
                words = theirs[0].evidence.split(" ", 3)[-1]  # after "Block of <wagon>"
                cut = words.rfind("): ")  # its advice: the timeline's sentence gave it
                words = words[: cut + 1] + "." if cut >= 0 else words
                evidence += f" The virtual sensor agrees: the block {words}"
            elif theirs:
                evidence = " ".join(f.evidence for f in theirs)
            event_ids = {f.event_id for f, _ in group}
            out.append(
                dataclasses.replace(
                    head,
                    start_utc=min(f.start_utc for f, _ in group),
                    end_utc=max(f.end_utc for f, _ in group),
                    severity=max((f.severity for f, _ in group), key=_RANK.__getitem__),
                    evidence=evidence,
                    event_id=head.event_id if len(event_ids) == 1 else None,
                    detail=head.detail if own else "estimator",
                )
            )
    out += [f for f in [*timeline, *estimator] if f.kind not in ("dragging_brake", "weak_brake")]
    return out


def date_sensor_faults(
    series: WagonSeries,
    findings: Sequence[Finding],
    failed: Sequence[tuple[int, int]],
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
) -> list[Finding]:
    """Sensor faults dated by the innovations: when a run of failed innovation windows
    (``failed``, :func:`find_innovation_faults`) begins before a sensor fault the readings
    showed (at most ``est_settle_s`` before) and lasts into it (or ends within
    ``fault_merge_gap_s`` of its start), the flag starts where the innovations failed, and its
    evidence says so. Other findings pass through."""
    out = []
    for f in findings:
        if f.kind != "sensor_fault" or not failed:
            out.append(f)
            continue
        start = max(int((f.start_utc - series.t0).total_seconds()), 0)
        stop = int((f.end_utc - series.t0).total_seconds())
        if start >= series.n or stop <= 0:
            out.append(f)
            continue
        onsets = [
            a
            for a, b in failed
            if start - config.est_settle_s <= a < start
            and start - config.fault_merge_gap_s <= b <= stop + 1
        ]
        if not onsets:
            out.append(f)
            continue
        a = min(onsets)
        ahead = start - a
        out.append(
            dataclasses.replace(
                f,
                start_utc=series.utc(a),
                evidence=f"{f.evidence} The virtual sensor's innovations had already failed "
                f"their test {at_text(series.utc(a))}, {duration_text(ahead)} before the "
                "reading looked wrong.",
            )
        )
    return out
