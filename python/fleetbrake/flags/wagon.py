"""One wagon's spans judged from their arrays (a span, the flags' partition):
:func:`judge_wagon` (the steps of :mod:`fleetbrake.flags.judge`), and the residual spread its
thresholds scale with (:func:`wagon_residual_spread`). No database: the partition's tables,
already read.

::

    from fleetbrake.flags.wagon import judge_wagon, wagon_residual_spread

    spread = wagon_residual_spread(predictions)
    findings = judge_wagon(spans, predictions=predictions, events=events,
                           config=config.scaled(spread), residual_spread_k=spread)
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl

from fleetbrake.flags.brakes import find_dragging, find_weak
from fleetbrake.flags.config import DEFAULT_FLAG_CONFIG, FlagConfig
from fleetbrake.flags.estimated import (
    EstimateOnGrid,
    combine_opinions,
    date_sensor_faults,
    declared_heat_w,
    find_dragging_estimated,
    find_innovation_faults,
    find_weak_estimated,
    sensor_noise_k,
)
from fleetbrake.flags.overheating import find_overheating
from fleetbrake.flags.records import Finding
from fleetbrake.flags.sensor import (
    find_drift,
    find_dropouts,
    find_frozen,
    find_loose,
    find_out_of_range,
    heat_flow_corrected,
    merge_sensor_faults,
)
from fleetbrake.flags.series import SpanTimeline
from fleetbrake.flags.stats import (
    EventStat,
    Segment,
    event_stats,
    same_readings,
    segment_stats,
    unsure_mask,
)
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.simulation.chains import constant_runs
from fleetbrake.simulation.series import BoolArray, WagonSeries, runs

__all__ = [
    "RESIDUAL_MIN_READINGS",
    "RESIDUAL_SPREAD_CAP_K",
    "judge_wagon",
    "wagon_residual_spread",
]


def _spans_utc(series: WagonSeries, mask: BoolArray) -> list[tuple[dt.datetime, dt.datetime]]:
    return [(series.utc(a), series.utc(b)) for a, b in runs(mask)]


def _mask_of(series: WagonSeries, findings: Iterable[Finding]) -> BoolArray:
    mask = np.zeros(series.n, dtype=bool)
    for f in findings:
        a = max(int((f.start_utc - series.t0).total_seconds()), 0)
        b = min(int((f.end_utc - series.t0).total_seconds()), series.n)
        mask[a:b] = True
    return mask


@dataclass
class _SpanVerdict:
    series: WagonSeries
    findings: list[Finding]
    segments: list[Segment]
    """Segments with every sensor fault left out (for the brakes)."""
    faults: list[tuple[int, int]]
    unsure: BoolArray
    estimate: EstimateOnGrid | None = None
    """The virtual sensor's estimate of the span (None: the timeline's detectors alone)."""


def _readings_only(series: WagonSeries, config: FlagConfig) -> list[Finding]:
    """Step 1 without a model: out of range, dropouts, frozen by the readings' scatter."""
    found = find_out_of_range(series, config) + find_dropouts(series, config)
    return merge_sensor_faults(found + find_frozen(series, config), config)


def _judge_span(
    series: WagonSeries,
    timeline: SpanTimeline,
    config: FlagConfig,
    estimate: EstimateOnGrid | None = None,
    residual_spread_k: float | None = None,
) -> _SpanVerdict:
    """Steps 1-2 of :mod:`fleetbrake.flags.judge` on one span: the sensor faults (dated by the
    estimate's innovations when there is one), and the segments of the timeline for the
    brakes."""
    findings = find_out_of_range(series, config) + find_dropouts(series, config)
    broken = _mask_of(series, findings)  # out of range or missing: no readings
    frozen_runs = np.zeros(series.n, dtype=bool)
    for a, b, _ in constant_runs(
        series.measured_c, config.frozen_min_s, config.frozen_resolution_k
    ):
        frozen_runs[a:b] = True
    predicted = timeline.predicted_c
    findings += find_frozen(series, config, predicted)
    unsure = unsure_mask(series, timeline.gaps, config)

    # loose and drifting against the model, frozen readings included (a loose sensor may end
    # up reading a constant air temperature: that is still reading the air)
    def segments_leaving_out(invalid: BoolArray) -> list[Segment]:
        return segment_stats(
            series,
            predicted,
            timeline.bounds,
            timeline.kinds,
            config,
            unsure=unsure,
            invalid=invalid,
        )

    segments = segments_leaving_out(broken)
    loose = find_loose(series, segments, config, predicted)
    loose_mask = _mask_of(series, loose)
    rest = [s for s in segments if not loose_mask[s.start : s.stop].any()]
    drift = find_drift(series, heat_flow_corrected(rest, config), config)
    findings = merge_sensor_faults([*findings, *loose, *drift], config)
    if estimate is not None:
        scale_k = max(sensor_noise_k(series.measured_c), residual_spread_k or 0.0)
        failed = find_innovation_faults(series, estimate, config, scale_k=scale_k)
        findings = date_sensor_faults(series, findings, failed, config)
    fault_mask = _mask_of(series, findings)
    # the segments again with every sensor fault left out (the same ones when that leaves
    # out no further reading: most spans)
    left_out = fault_mask | frozen_runs
    if not same_readings(series, broken, left_out):
        segments = segments_leaving_out(left_out)
    return _SpanVerdict(series, findings, segments, runs(fault_mask), unsure, estimate)


def judge_wagon(
    spans: Sequence[tuple[WagonSeries, SpanTimeline | None]],
    *,
    predictions: pl.DataFrame | None = None,
    events: pl.DataFrame | None = None,
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    estimates: Sequence[EstimateOnGrid | None] | None = None,
    wagon: WagonConfig | None = None,
    residual_spread_k: float | None = None,
) -> list[Finding]:
    """Every finding of one wagon (the steps of :mod:`fleetbrake.flags.judge`), from its spans of data
    with their stored timelines (:func:`fleetbrake.flags.series.load_spans`), the revision's
    ``predictions`` of its brakings and its ``events``. A span without a timeline is judged
    on its readings only, and the brakings only when every span has one. ``estimates`` (one
    per span, on its grid) and ``wagon`` (its registry entry, for the declared heat) add the
    virtual sensor's opinion (:mod:`fleetbrake.flags.estimated`); ``residual_spread_k`` sets
    the innovations' scale where it exceeds the sensor's noise (``config`` is expected
    already scaled by it: :meth:`FlagConfig.scaled`)."""
    if not spans:
        return []
    if any(timeline is None for _, timeline in spans):
        return [f for series, _ in spans for f in _readings_only(series, config)]
    own = list(estimates) if estimates is not None else [None] * len(spans)
    verdicts = [
        _judge_span(series, timeline, config, est, residual_spread_k)
        for (series, timeline), est in zip(spans, own, strict=True)
        if timeline is not None
    ]
    wagon_id = spans[0][0].wagon_id
    findings = [f for v in verdicts for f in v.findings]
    stats: list[EventStat] = []
    if predictions is not None and events is not None and predictions.height:
        excluded = [(v.series.utc(a), v.series.utc(b)) for v in verdicts for a, b in v.faults]
        unsure = [span for v in verdicts for span in _spans_utc(v.series, v.unsure)]
        stats = event_stats(predictions, events, config, excluded=excluded, unsure=unsure)
    brakes = find_weak(wagon_id, stats, config)
    theirs: list[Finding] = []
    for v in verdicts:
        t0, t1 = v.series.t0, v.series.utc(v.series.n)
        in_span = [e for e in stats if t0 <= e.start_utc < t1]
        brakes += find_dragging(v.series, v.segments, in_span, config, excluded=v.faults)
        if v.estimate is not None and wagon is not None:
            rises = {e.event_id: e.p_rise for e in in_span} if stats else None
            theirs += _estimator_brakes(v, wagon, config, rises)
    findings += combine_opinions(brakes, theirs, config.drag_merge_gap_s)
    findings += find_overheating(wagon_id, stats, config)
    return findings


def _estimator_brakes(
    v: _SpanVerdict,
    wagon: WagonConfig,
    config: FlagConfig,
    predicted_rise_k: Mapping[str, float] | None,
) -> list[Finding]:
    """The estimator's dragging and weak brakes of one span: sensor faults and the
    ``est_settle_s`` after each (the unexplained power recovering from readings that were not
    the block's) and the unsure seconds (heat a data gap may have hidden) left out."""
    assert v.estimate is not None
    n = v.series.n
    excluded = [(a, min(b + config.est_settle_s, n)) for a, b in v.faults]
    excluded += runs(v.unsure)
    found = find_dragging_estimated(v.series, v.estimate, config, excluded=excluded)
    heat = declared_heat_w(wagon, v.series)
    found += find_weak_estimated(
        v.series, v.estimate, heat, config, excluded=excluded, predicted_rise_k=predicted_rise_k
    )
    return found


RESIDUAL_MIN_READINGS = 30
"""Brakings with fewer valid readings in their window do not count in the residual spread."""


RESIDUAL_SPREAD_CAP_K = 0.5
"""K: a wagon's residual spread is at most this (5 x the sensor noise), so that a fault
spanning the whole wagon (a drift over most of its brakings) cannot raise its own thresholds
out of reach."""


def wagon_residual_spread(predictions: pl.DataFrame) -> float | None:
    """A span's residual spread for a revision, K: the median over its brakings (with at
    least :data:`RESIDUAL_MIN_READINGS` valid readings) of the rms of measured - predicted
    over each window of its ``predictions``; None without any. A function of the span's
    own data and the revision only, so a late file elsewhere cannot move its flags."""
    if predictions.height == 0:
        return None
    spread = (  # one polars query
        predictions.lazy()
        .filter(
            pl.col("measured_sensor_c").is_not_null() & pl.col("predicted_sensor_c").is_not_null()
        )
        .with_columns(
            ((pl.col("measured_sensor_c") - pl.col("predicted_sensor_c")) ** 2).alias("sq")
        )
        .group_by("event_id")
        .agg(pl.col("sq").mean().sqrt().alias("rms_k"), pl.len().alias("readings"))
        .filter(pl.col("readings") >= RESIDUAL_MIN_READINGS)
        .select(pl.col("rms_k").median())
        .collect(engine="in-memory")  # the engine eager calls run on
    )
    value = spread.item() if spread.height else None
    if value is None:
        return None
    return min(float(value), RESIDUAL_SPREAD_CAP_K)
