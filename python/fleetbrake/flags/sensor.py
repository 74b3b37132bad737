"""Sensor faults of a wagon's block temperature reading (``sensor_fault``).

From the readings alone: out of range (:func:`find_out_of_range`, the ingestion's
``block_temp_fault``), frozen (:func:`find_frozen`: unchanged for minutes while the sensor is
noisy elsewhere, or while the model has the block change), dropping out
(:func:`find_dropouts`). Against the stored timeline's segments: loose (:func:`find_loose`:
the reading falls towards the air much faster than the block can cool, or stays at the air in
a braking) and drifting (:func:`find_drift`: measured - predicted changing steadily, of one
sign, in a way no braking's aftermath and no heat flow of the block explains,
:func:`heat_flow_corrected`, and not again at the same hours on other days). Faults close together are one flag
(:func:`merge_sensor_faults`).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from collections.abc import Sequence

import numpy as np

from fleetbrake.flags.config import DEFAULT_FLAG_CONFIG, SEVERITIES, FlagConfig
from fleetbrake.flags.records import Finding
from fleetbrake.flags.stats import Segment
from fleetbrake.flags.text import (
    at_text,
    duration_text,
    severity_by_duration,
    signed_text,
    when_text,
)
from fleetbrake.fleet.logfile import BLOCK_TEMP_VALID_C
from fleetbrake.simulation.chains import constant_runs
from fleetbrake.simulation.series import (
    FloatArray,
    WagonSeries,
    merge_spans,
    nan_running_mean,
    runs,
)

__all__ = [
    "find_drift",
    "find_dropouts",
    "find_frozen",
    "find_loose",
    "find_out_of_range",
    "heat_flow_corrected",
    "merge_sensor_faults",
]


def find_out_of_range(
    series: WagonSeries, config: FlagConfig = DEFAULT_FLAG_CONFIG
) -> list[Finding]:
    """Runs of out-of-range readings (``block_temp_fault``), merged across short breaks."""
    lo, hi = BLOCK_TEMP_VALID_C
    out = []
    for a, b in merge_spans(runs(series.fault), config.fault_merge_gap_s):
        raw = series.raw_c[a:b][series.fault[a:b]]
        raw = raw[np.isfinite(raw)]
        count = int(series.fault[a:b].sum())
        if raw.size and np.all(raw > hi):
            what = f"read {np.median(raw):.1f} °C, above the {hi:g} °C a Pt1000 can read"
            cause = "an open circuit (broken wire or connector)"
        elif raw.size and np.all(raw < lo):
            what = f"read {np.median(raw):.1f} °C, below the {lo:g} °C a Pt1000 can read"
            cause = "a short circuit in the sensor cable"
        else:
            what = f"read out of the {lo:g}…{hi:g} °C range"
            cause = "a broken sensor circuit"
        start, end = series.utc(a), series.utc(b)
        out.append(
            Finding(
                "sensor_fault",
                severity_by_duration(b - a, config),
                start,
                end,
                f"Block temperature sensor of {series.wagon_id} {what} {when_text(start, end)} "
                f"({count} readings over {duration_text(b - a)}): {cause}; check the Pt1000, its "
                "cable and connector.",
                detail="out_of_range",
                summary=f"out of range for {duration_text(b - a)}",
            )
        )
    return out


def find_frozen(
    series: WagonSeries,
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    predicted_c: FloatArray | None = None,
) -> list[Finding]:
    """Readings unchanged (to within ``frozen_resolution_k``) for ``frozen_min_s`` or more,
    while the same sensor is noisy elsewhere or ``predicted_c`` (the model's sensor
    temperature on the series' grid) changes by ``frozen_min_change_k`` meanwhile."""
    out = []
    for a, b, value in constant_runs(
        series.measured_c, config.frozen_min_s, config.frozen_resolution_k
    ):
        change, signed = None, 0.0
        if predicted_c is not None:
            seg = predicted_c[a:b]
            seg = seg[np.isfinite(seg)]
            if seg.size:
                change = float(seg.max() - seg.min())
                signed = float(seg[-1] - seg[0])
        noise = _scatter_around(series.measured_c, a, b, config)
        by_model = change is not None and change >= config.frozen_min_change_k
        by_noise = noise is not None and noise >= config.frozen_noise_k
        if not (by_model or by_noise):
            continue
        start, end = series.utc(a), series.utc(b)
        reasons = []
        if by_model:
            reasons.append(f"the model has the block change by {signed_text(signed)} meanwhile")
        if by_noise:
            reasons.append(f"its readings scatter by ±{noise:.2f} K elsewhere")
        out.append(
            Finding(
                "sensor_fault",
                severity_by_duration(b - a, config),
                start,
                end,
                f"Block temperature reading of {series.wagon_id} stuck at {value:.2f} °C for "
                f"{duration_text(b - a)} {when_text(start, end)} while {' and '.join(reasons)}: the "
                "reading is frozen; check the sensor and its logger channel.",
                detail="frozen",
                summary=f"frozen at {value:.2f} °C for {duration_text(b - a)}",
            )
        )
    return out


def _scatter_around(values: FloatArray, a: int, b: int, config: FlagConfig) -> float | None:
    """The noise of the valid readings within ``frozen_noise_window_s`` around [a, b), as
    the standard deviation a Gaussian noise would have given their median reading-to-reading
    difference (robust to the block's own changes); None with fewer than
    ``frozen_noise_min_pairs`` pairs."""
    lo = max(a - config.frozen_noise_window_s, 0)
    hi = min(b + config.frozen_noise_window_s, values.size)
    window = values[lo:hi].copy()
    window[a - lo : b - lo] = np.nan
    pairs = np.isfinite(window[1:]) & np.isfinite(window[:-1])
    if pairs.sum() < config.frozen_noise_min_pairs:
        return None
    # median |x1 - x0| of two samples of N(0, s^2) is 0.6745 sqrt(2) s
    return float(np.median(np.abs(np.diff(window))[pairs])) / (0.6745 * math.sqrt(2.0))


def find_dropouts(series: WagonSeries, config: FlagConfig = DEFAULT_FLAG_CONFIG) -> list[Finding]:
    """Runs of rows with no reading (not out of range, just missing) for ``dropout_min_s``
    or more while the logger wrote the rest of the row (a second with no row at all ends a
    run: that is a gap of the logger, not of the sensor)."""
    missing = series.present & ~np.isfinite(series.measured_c) & ~series.fault
    out = []
    for a, b in runs(missing):
        rows = b - a
        if rows < config.dropout_min_s:
            continue
        start, end = series.utc(a), series.utc(b)
        out.append(
            Finding(
                "sensor_fault",
                severity_by_duration(b - a, config),
                start,
                end,
                f"Block temperature readings of {series.wagon_id} missing for {duration_text(b - a)} "
                f"{when_text(start, end)} ({rows} rows) while speed and pressure were logged: the "
                "sensor drops out; check its connector and cable.",
                detail="dropout",
                summary=f"missing for {duration_text(b - a)}",
            )
        )
    return out


def _is_loose_window(s: Segment, config: FlagConfig) -> bool:
    if s.kind != "quiet" or not s.judged:
        return False
    contrast = s.m_start - s.ambient_c
    model_contrast = s.p_start - s.ambient_c
    if contrast < config.loose_min_contrast_k or model_contrast <= 0:
        return False
    towards_m = (s.m_start - s.m_end) / contrast
    towards_p = (s.p_start - s.p_end) / model_contrast
    return (
        s.m_start - s.m_end >= config.loose_min_drop_k
        and s.excess_k <= -config.loose_min_drop_k
        and towards_m - towards_p >= config.loose_min_fraction
    )


def _is_detached_braking(s: Segment, config: FlagConfig) -> bool:
    return (
        s.kind == "braking"
        and s.judged
        and s.p_rise >= max(config.loose_min_predicted_rise_k, config.weak_min_predicted_rise_k)
        and s.ratio < config.detached_ratio
        and s.m_ambient_k <= config.loose_ambient_k
    )


def find_loose(
    series: WagonSeries,
    segments: Sequence[Segment],
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    predicted_c: FloatArray | None = None,
) -> list[Finding]:
    """A sensor come loose: its reading falls towards the air much faster than the block can
    cool (a quiet window), or it reads the air and does not rise in a braking. The flag goes
    on over the following segments while the reading keeps reading the air or stays flat in
    brakings (segments not judged are passed over), and ends before a braking it follows
    again or a quiet window where it reads neither the air nor falls towards it. With
    ``predicted_c`` (the stored timeline) the start is moved back to where the reading left
    the model in the segment before."""
    out = []
    i = 0
    while i < len(segments):
        s = segments[i]
        if not (_is_loose_window(s, config) or _is_detached_braking(s, config)):
            i += 1
            continue
        first = last = i
        brakings: list[Segment] = []
        j = i + 1
        while j < len(segments):
            t = segments[j]
            if t.kind == "braking":
                if not t.judged or not t.p_rise >= config.loose_min_predicted_rise_k:
                    pass
                elif t.ratio >= config.responsive_ratio:
                    break
                elif t.ratio < config.detached_ratio:
                    brakings.append(t)
                    last = j
            elif t.judged and math.isfinite(t.m_ambient_k):
                if not (_is_loose_window(t, config) or t.m_ambient_k <= config.loose_ambient_k):
                    break
                last = j
            j += 1
        head = segments[first]
        onset = head.start
        if predicted_c is not None:
            onset = _departure(series, predicted_c, head, head.start, config)
            if first > 0:
                onset = _departure(series, predicted_c, segments[first - 1], onset, config)
        start, end = series.utc(onset), series.utc(segments[last].stop)
        if head.kind == "quiet":
            seen = (
                f"fell from {head.m_start:.1f} °C to {head.m_end:.1f} °C "
                f"{when_text(series.utc(head.start), series.utc(head.stop))}, towards the "
                f"{head.ambient_c:.1f} °C air, while the model has the block at "
                f"{head.p_end:.1f} °C"
            )
        else:
            seen = (
                f"stayed at {head.m_start:.1f} °C, the air's {head.ambient_c:.1f} °C, in the "
                f"braking {at_text(series.utc(head.start))} where a rise of {head.p_rise:.1f} K "
                "was predicted"
            )
        if brakings:
            rises = [f"{b.m_rise:.1f} K instead of {b.p_rise:.1f} K" for b in brakings[:3]]
            more = f" (and in {len(brakings) - 3} more)" if len(brakings) > 3 else ""
            seen += f"; in the brakings after that it rose {', '.join(rises)}{more}"
        out.append(
            Finding(
                "sensor_fault",
                severity_by_duration((end - start).total_seconds(), config),
                start,
                end,
                f"Block temperature reading of {series.wagon_id} {seen}: the sensor is no longer "
                "in contact with the block (loose); reseat and fix it.",
                detail="loose",
                summary=f"read the air ({when_text(start, end)})",
            )
        )
        i = j
    return out


def _departure(
    series: WagonSeries,
    predicted_c: FloatArray,
    before: Segment,
    default: int,
    config: FlagConfig,
) -> int:
    """Where, in the segment ``before``, measured - predicted fell below -loose_min_drop_k
    for good (the reading left the model), or ``default``."""
    r = series.measured_c[before.start : before.stop] - predicted_c[before.start : before.stop]
    r = nan_running_mean(r, config.edge_s)
    below = np.isfinite(r) & (r < -config.loose_min_drop_k)
    if r.size == 0 or not below[-config.edge_s :].any():
        return default
    above = np.flatnonzero(np.isfinite(r) & ~below)
    return before.start + (int(above[-1]) + 1 if above.size else 0)


def _diverges_while_unsure(s: Segment) -> bool:
    """A quiet window with enough readings, not judged only because the simulated block is
    unsure (after a data gap in which the wagon may have braked: :func:`~fleetbrake.flags.stats.unsure_mask`),
    whose measured - predicted moves *away* from the model: the heat a gap may have hidden
    leaves the reading above the model and falling back to it (the excess converges), so a
    reading that keeps leaving the model at one sign in a quiet window is not that heat."""
    if s.kind != "quiet" or not s.enough or s.calm:
        return False
    start, end = s.m_start - s.p_start, s.m_end - s.p_end
    if not (math.isfinite(start) and math.isfinite(end) and math.isfinite(s.slope_k_per_h)):
        return False
    return bool(np.sign(s.slope_k_per_h) == np.sign(end) != 0 and abs(end) > abs(start))


def _counts_for_drift(s: Segment) -> bool:
    """Whether a segment counts in a drift's run: judged, or a quiet window after a data gap
    that leaves the model (:func:`_diverges_while_unsure`)."""
    return s.judged or _diverges_while_unsure(s)


def _is_drifting(s: Segment, config: FlagConfig) -> bool:
    """A counted segment (:func:`_counts_for_drift`) whose measured - predicted changes
    steadily at a drift's rate."""
    rate = abs(s.slope_k_per_h)
    return (
        _counts_for_drift(s)
        and config.drift_min_rate_k_per_h <= rate <= config.drift_max_rate_k_per_h
        and s.line_rms_k <= config.drift_max_rms_k
        and s.excess_k < config.drag_min_excess_k
    )


def heat_flow_corrected(
    segments: Sequence[Segment], config: FlagConfig = DEFAULT_FLAG_CONFIG
) -> list[Segment]:
    """The quiet windows with what the model's heat flow has wrong for this wagon taken out.

    The rate at which measured - predicted changes in the quiet windows long after a braking
    (``settle_after_braking_s``) is fitted, robustly, as e (k0 + k1 v / 100 km/h), e the
    block's excess over the air, v the speed: a cooling the model has too slow or too fast
    (a convection coefficient, one growing with speed) is in every window of the wagon and is
    fitted; a drifting sensor is in a minority of them and is trimmed away. The fit is taken
    out of the quiet windows' rates (and end values), within the range of e and v it was made
    on, when it matters: when it explains ``heat_flow_min_explained`` of the windows' rates and its rates reach half
    ``drift_min_rate_k_per_h`` (rms). With fewer than ``heat_flow_min_windows`` such windows
    nothing is changed."""
    rows = [
        s
        for s in segments
        if s.kind == "quiet"
        and s.judged
        and s.since_release_s >= config.settle_after_braking_s
        and math.isfinite(s.slope_k_per_h)
        and math.isfinite(s.p_start)
    ]
    if len(rows) < config.heat_flow_min_windows:
        return list(segments)

    def columns(items: Sequence[Segment]) -> tuple[FloatArray, FloatArray]:
        excess = np.array([0.5 * (s.p_start + s.p_end) - s.ambient_c for s in items])
        return excess, np.array([s.speed_kmh for s in items]) / 100.0

    excess, speed = columns(rows)
    x = np.column_stack([excess, excess * speed])
    y = np.array([s.slope_k_per_h for s in rows])
    keep = np.ones(y.size, dtype=bool)
    for _ in range(3):  # least squares, trimming the windows far from the fit
        coef = np.linalg.lstsq(x[keep], y[keep], rcond=None)[0]
        residual = y - x @ coef
        spread = 1.4826 * float(np.median(np.abs(residual[keep])))
        keep = np.abs(residual) <= max(3.0 * spread, config.drift_min_rate_k_per_h / 2)
        if keep.sum() < config.heat_flow_min_windows:
            return list(segments)
    fitted = x[keep] @ coef
    explained = 1.0 - float(np.sum((y[keep] - fitted) ** 2)) / max(
        float(np.sum(y[keep] ** 2)), 1e-12
    )
    if (
        explained < config.heat_flow_min_explained
        or float(np.sqrt(np.mean(fitted**2))) < config.drift_min_rate_k_per_h / 2
    ):
        return list(segments)
    (e_lo, e_hi), (v_lo, v_hi) = (excess.min(), excess.max()), (speed.min(), speed.max())
    out = []
    for s in segments:
        if s.kind != "quiet" or not math.isfinite(s.p_start):
            out.append(s)
            continue
        (e,), (v,) = columns([s])
        e, v = float(np.clip(e, e_lo, e_hi)), float(np.clip(v, v_lo, v_hi))
        rate = float(coef[0] * e + coef[1] * e * v)
        hours = (s.stop - s.start) / 3600.0
        out.append(
            dataclasses.replace(
                s, slope_k_per_h=s.slope_k_per_h - rate, p_end=s.p_end + rate * hours
            )
        )
    return out


def _explained_by_heat_flow(run: Sequence[Segment], config: FlagConfig) -> bool:
    """Whether the quiet windows' rates follow the block's excess over the air (rate = k x
    excess) much better than they are constant (``drift_heat_flow_ratio``), over a wide
    enough range of excess (``drift_heat_flow_min_spread``): a heat flow the model has wrong
    (convection, holder), not a sensor drifting; unless they follow a rate growing steadily
    in time better still: a drifting offset, which the timeline, re-anchored at every
    segment, relaxes away at a rate that grows with the offset (when the block warms over
    the run as the offset grows, the excess follows the time and both fit)."""
    rates = np.array([s.slope_k_per_h for s in run])
    excess = np.array([0.5 * (s.p_start + s.p_end) - s.ambient_c for s in run])
    if not np.all(np.isfinite(excess)) or excess.min() <= 0:
        return False
    if excess.max() < config.drift_heat_flow_min_spread * excess.min():
        return False  # too narrow a range of block temperatures to tell
    k = float(rates @ excess) / float(excess @ excess)
    proportional = float(np.sum((rates - k * excess) ** 2))
    constant = float(np.sum((rates - rates.mean()) ** 2))
    if not proportional < config.drift_heat_flow_ratio * constant:
        return False
    hours = np.array([0.5 * (s.start + s.stop) for s in run]) / 3600.0
    line = np.column_stack([np.ones_like(hours), hours - hours[0]])
    coef = np.linalg.lstsq(line, rates, rcond=None)[0]
    growing = float(coef[1]) * float(np.sign(rates.mean())) > 0
    in_time = float(np.sum((rates - line @ coef) ** 2))
    return not (growing and in_time < proportional)


DRIFT_HOUR_MARGIN_H = 1.5
"""h: the hours of day of a run's quiet windows, widened by this on each side, are where
:func:`_recurs_daily` looks on the wagon's other days."""


def _recurs_daily(
    series: WagonSeries, run: Sequence[Segment], segments: Sequence[Segment], config: FlagConfig
) -> bool:
    """Whether the run's misfit comes back with the hour of day: on the wagon's other days
    (windows at least 12 h from the run), its quiet windows at the same hours of day (those
    of the run's quiet windows, ``DRIFT_HOUR_MARGIN_H`` wider) change at the run's sign too,
    by at least a quarter of ``drift_min_rate_k_per_h`` (median of at least
    ``drift_min_windows`` windows), and by that much more than its quiet windows at the other
    hours of the day (the misfit comes and goes with the hour). A calibration drift happens
    once and does not return at the same hour the next day; a heat input the model lacks
    that follows the hour of day (sunshine) does: a model error, not a sensor fault. A
    function of the wagon's own segments only (with a single day of data it cannot tell, and
    a drift stays a drift)."""
    sign = float(np.sign(run[-1].slope_k_per_h))

    def hour(s: Segment) -> float:
        t = series.utc((s.start + s.stop) // 2)
        return t.hour + t.minute / 60.0 + t.second / 3600.0

    def quiet(s: Segment) -> bool:
        return s.kind == "quiet" and s.judged and math.isfinite(s.slope_k_per_h)

    hours = [hour(s) for s in run if quiet(s)]
    if not hours:
        return False
    lo, hi = min(hours) - DRIFT_HOUR_MARGIN_H, max(hours) + DRIFT_HOUR_MARGIN_H
    first, last = run[0].start, run[-1].stop
    same: list[float] = []
    other: list[float] = []
    for s in segments:
        if not quiet(s) or first - 12 * 3600 < s.start < last + 12 * 3600:
            continue
        h = hour(s)
        at_hours = any(lo <= h + turn <= hi for turn in (-24.0, 0.0, 24.0))
        (same if at_hours else other).append(sign * s.slope_k_per_h)
    if len(same) < config.drift_min_windows or len(other) < config.drift_min_windows:
        return False
    then, elsewhen = float(np.median(same)), float(np.median(other))
    return (
        then >= config.drift_min_rate_k_per_h / 4
        and then - elsewhen >= config.drift_min_rate_k_per_h / 4
    )


def find_drift(
    series: WagonSeries, segments: Sequence[Segment], config: FlagConfig = DEFAULT_FLAG_CONFIG
) -> list[Finding]:
    """A drifting reading: measured - predicted changes steadily, at one sign, segment after
    segment, whatever the block does: in quiet windows and brakings alike.

    A run collects the drifting segments of one sign; brakings, segments not judged and
    windows right after a braking (``settle_after_braking_s``) that do not drift are passed
    over; any other quiet window that does not drift ends it. A quiet window after a data gap
    (the block unsure) counts when the reading leaves the model in it
    (:func:`_diverges_while_unsure`), else it is passed over too. A run of at least
    ``drift_min_windows`` segments, one of them a quiet window, is a drift when no braking's
    aftermath explains it (one of its windows starts long after a braking, or every braking in
    it drifts along: a weak brake's do not, they fall far behind the model) and no heat flow
    does (:func:`_explained_by_heat_flow`), and it does not come back at the same hours on the
    wagon's other days (:func:`_recurs_daily`: a heat input by the hour of day)."""
    out = []
    run: list[Segment] = []

    def close() -> None:
        quiet = [s for s in run if s.kind == "quiet"]
        if len(run) < config.drift_min_windows or not quiet:
            return
        span = run[-1].stop - run[0].start
        total = sum(s.excess_k for s in run)
        if span < config.drift_min_duration_s or abs(total) < config.drift_min_change_k:
            return
        rate = float(np.median([s.slope_k_per_h for s in run]))
        settled = any(s.since_release_s >= config.settle_after_braking_s for s in quiet)
        members = {id(s) for s in run}
        brakings = [
            s
            for s in segments
            if s.kind == "braking" and s.judged and run[0].start <= s.start < run[-1].stop
        ]
        along = bool(brakings) and all(id(s) in members for s in brakings)
        if not (settled or along) or _explained_by_heat_flow(quiet, config):
            return
        if _recurs_daily(series, run, segments, config):
            return
        start, end = series.utc(run[0].start), series.utc(run[-1].stop)
        where = (
            "long after brakings as much as right after them"
            if settled
            else f"in the {len(brakings)} braking{'s' if len(brakings) > 1 else ''} as much "
            "as between them"
        )
        out.append(
            Finding(
                "sensor_fault",
                severity_by_duration(span, config),
                start,
                end,
                f"Block temperature reading of {series.wagon_id} drifted away from the model at "
                f"{signed_text(rate, 'K/h')} ({signed_text(total)} over {duration_text(span)}) "
                f"{when_text(start, end)}, {where}, which no heat flow of the block explains: the "
                "sensor is drifting; check its seating and calibration.",
                detail="drift",
                summary=f"drifted at {signed_text(rate, 'K/h')}",
            )
        )

    for s in segments:
        if not _counts_for_drift(s):
            continue  # neither counts nor ends a run
        if _is_drifting(s, config) and (
            not run or np.sign(s.slope_k_per_h) == np.sign(run[-1].slope_k_per_h)
        ):
            run.append(s)
            continue
        if s.kind == "braking" or s.since_release_s < config.settle_after_braking_s:
            continue  # a braking, or right after one: its own heat may hide a drift
        close()
        run = [s] if _is_drifting(s, config) else []
    close()
    return out


def merge_sensor_faults(
    findings: Sequence[Finding], config: FlagConfig = DEFAULT_FLAG_CONFIG
) -> list[Finding]:
    """Sensor faults that overlap or follow each other within ``fault_merge_gap_s`` are one
    flag: the first one's evidence, the others summed up after it (a loose sensor that ends
    up reading a constant air temperature is one fault, not a loose one and six frozen)."""
    faults = sorted(
        (f for f in findings if f.kind == "sensor_fault"), key=lambda f: (f.start_utc, f.end_utc)
    )
    others = [f for f in findings if f.kind != "sensor_fault"]
    gap = dt.timedelta(seconds=config.fault_merge_gap_s)
    groups: list[list[Finding]] = []
    for f in faults:
        if groups and f.start_utc <= max(g.end_utc for g in groups[-1]) + gap:
            groups[-1].append(f)
        else:
            groups.append([f])
    merged = []
    for group in groups:
        head = group[0]
        if len(group) == 1:
            merged.append(head)
            continue
        end = max(f.end_utc for f in group)
        by_detail: dict[str, list[Finding]] = {}
        for f in group[1:]:
            by_detail.setdefault(f.detail or "faulty", []).append(f)
        parts = []
        for detail, items in by_detail.items():
            if len(items) == 1:
                parts.append(items[0].summary or detail)
            else:
                seconds = sum((f.end_utc - f.start_utc).total_seconds() for f in items)
                parts.append(
                    f"{detail.replace('_', ' ')} {len(items)} times ({duration_text(seconds)})"
                )
        seconds = (end - head.start_utc).total_seconds()
        rank = {name: k for k, name in enumerate(SEVERITIES)}
        severity = max(
            [severity_by_duration(seconds, config), *(f.severity for f in group)],
            key=rank.__getitem__,
        )
        merged.append(
            dataclasses.replace(
                head,
                end_utc=end,
                severity=severity,
                evidence=f"{head.evidence} Until {end:%Y-%m-%d %H:%M:%S} UTC its reading was "
                f"also {'; '.join(parts)}.",
            )
        )
    return merged + others
