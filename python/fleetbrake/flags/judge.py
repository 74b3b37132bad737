"""Judging a wagon and storing its flags: :func:`raise_flags`.

::

    from fleetbrake.flags import FlagConfig, load_flag_config, raise_flags

    config = load_flag_config("flags.toml")            # or FlagConfig() for the defaults
    report = raise_flags(wh, registry, "declared", config)   # every wagon with samples
    report = raise_flags(wh, registry, "declared", wagons=["SGG-0002"])
    report.flags                                        # what was stored in ``flags``

The flags read what the stages before stored: the samples and events, the revision's
``timeline`` (the block re-anchored at every segment, ``fleetbrake.simulation``) and its
``predictions`` of the brakings; they never simulate. How a wagon is judged (each step uses
only readings the steps before found good):

1. **Sensor, from the readings alone** (:mod:`fleetbrake.flags.sensor`): out of range,
   frozen, dropping out.
2. **Sensor, against the timeline**: loose, drifting (segments right after a data gap in
   which the wagon may have braked, or after a braking over frozen GPS speed, are not judged
   for ``settle_s``).
3. **Brakes** (:mod:`fleetbrake.flags.brakes`), with the readings of steps 1 and 2 left out:
   dragging (quiet windows heating while the model cools, brakings heating far more than
   predicted), weak (brakings heating far less than predicted; consecutive ones are one flag).
4. **Overheating** (:mod:`fleetbrake.flags.overheating`): the predicted contact maximum of a
   braking over ``contact_limit_c``.
5. **The virtual sensor's opinion** (:mod:`fleetbrake.flags.estimated`, ``config.estimator``):
   the stored estimates of the revision when current (``contact_estimates``; none otherwise:
   the estimation stage is the one place a wagon is estimated); its dragging and weak brakes combined with steps 3's into one flag per
   anomaly, its innovations dating the sensor faults of steps 1-2.

Every threshold in kelvin a model error could reach is first raised to ``residual_factor`` x
the wagon's residual spread for the revision (:func:`wagon_residual_spread`, computed in its
partition; :meth:`FlagConfig.scaled`).

A wagon without a registry entry, or whose timeline of the revision is missing or older than
its data, is judged on its readings only (step 1; the report's notes say so). Flags are
recomputed per wagon (a partition: the parent reads a chunk of wagons as Arrow, one query
per table, :func:`flag_chunk`; :func:`judge_chunk`, pure and picklable, cuts it into the
wagons' tasks and :func:`judge_task` judges each alone, on an engine's workers with
``engine=``) and the wagons' rows of ``flags`` replaced in one transaction, with when they
were judged, with which revision and thresholds (``flagged_wagons``: :func:`stale_wagons`,
the wagons whose flags are out of date, which ``fleetbrake run`` judges);
``flag_id`` is ``<kind>-<wagon>-<start as YYYYMMDDTHHMMSS>`` (``-2``, ... if taken), so the
same data give the same ids, and a flag found again keeps its ``detected_utc``.
"""

from __future__ import annotations

import datetime as dt
import logging
import statistics
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.errors import FleetbrakeError
from fleetbrake.flags.brakes import find_dragging, find_weak
from fleetbrake.flags.config import DEFAULT_FLAG_CONFIG, FlagConfig
from fleetbrake.flags.estimated import (
    EstimateOnGrid,
    combine_opinions,
    date_sensor_faults,
    declared_heat_w,
    estimate_on_grid,
    find_dragging_estimated,
    find_innovation_faults,
    find_weak_estimated,
    sensor_noise_k,
)
from fleetbrake.flags.overheating import find_overheating
from fleetbrake.flags.records import Finding, Flag, FlagReport
from fleetbrake.flags.sensor import (
    find_drift,
    find_dropouts,
    find_frozen,
    find_loose,
    find_out_of_range,
    heat_flow_corrected,
    merge_sensor_faults,
)
from fleetbrake.flags.series import SpanTimeline, spans_of
from fleetbrake.flags.stats import (
    EventStat,
    Segment,
    event_stats,
    same_readings,
    segment_stats,
    unsure_mask,
)
from fleetbrake.fleet.registry import Registry, WagonConfig
from fleetbrake.simulation.chains import constant_runs
from fleetbrake.simulation.estimates import estimated_wagons, estimation_data_keys
from fleetbrake.simulation.predictions import Mapper, Revision, revision
from fleetbrake.simulation.series import BoolArray, WagonSeries, runs
from fleetbrake.simulation.store import (
    StoredTimeline,
    chunk_table,
    data_keys,
    sample_parts,
    sample_rows,
    simulated_wagons,
    stored_timeline,
    utc_now,
    wagon_chunks,
    wagon_parts,
)
from fleetbrake.warehouse.connection import Warehouse, sql

if TYPE_CHECKING:
    import duckdb

__all__ = [
    "FLAG_CHUNK_ROWS",
    "FlagChunk",
    "FlagOutcome",
    "FlagTask",
    "chunk_tasks",
    "flag_chunk",
    "flag_ids",
    "flag_task",
    "judge_chunk",
    "judge_task",
    "judge_wagon",
    "raise_flags",
    "stale_wagons",
    "stored_flags",
]

logger = logging.getLogger(__name__)


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
    """Steps 1-2 of the module docstring on one span: the sensor faults (dated by the
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
    """Every finding of one wagon (the steps of the module docstring), from its spans of data
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


def flag_ids(wagon_id: str, findings: Sequence[Finding]) -> list[Flag]:
    """The findings as flags, with their stable ids (see the module docstring)."""
    taken: set[str] = set()
    flags = []
    for f in sorted(findings, key=lambda f: (f.start_utc, f.kind, f.end_utc, f.evidence)):
        base = f"{f.kind}-{wagon_id}-{f.start_utc:%Y%m%dT%H%M%S}"
        flag_id, k = base, 1
        while flag_id in taken:
            k += 1
            flag_id = f"{base}-{k}"
        taken.add(flag_id)
        flags.append(
            Flag(
                flag_id=flag_id,
                wagon_id=wagon_id,
                event_id=f.event_id,
                kind=f.kind,
                severity=f.severity,
                start_utc=f.start_utc,
                end_utc=f.end_utc,
                evidence=f.evidence,
                detail=f.detail,
            )
        )
    return flags


@dataclass(frozen=True)
class FlagTask:
    """One wagon's partition of the flags: everything :func:`judge_task` reads, as the parent
    read it from the warehouse (Arrow tables; picklable: an engine ships it to a worker)."""

    wagon_id: str
    revision: str
    ambient_c: float
    samples: pa.Table
    """The wagon's samples (``q_simulation_wagon_samples.sql``)."""
    events: pa.Table
    """Its braking events (``q_simulation_wagon_events.sql``)."""
    config: FlagConfig
    note: str | None = None
    """Why the wagon is judged on its readings only (no timeline given), for the report."""
    data_key: str | None = None
    segments: pa.Table | None = None
    """The revision's ``timeline_segments`` of the wagon (``q_simulation_timeline_segments``);
    None: no current timeline, the readings alone are judged."""
    timeline: pa.Table | None = None
    """Its ``timeline`` rows, the predicted sensor temperature (``q_flags_timeline.sql``)."""
    predictions: pa.Table | None = None
    """Its ``predictions`` of the revision (``q_flags_predictions.sql``)."""
    wagon: WagonConfig | None = None
    """Its registry entry (the declared heat of its brakings, the estimator's model)."""
    rev: Revision | None = None
    """The revision (unused by the judge since the estimates are always the stage's)."""
    residual_spread_k: float | None = None
    """A residual spread given by the caller (tests); None: the wagon's own, computed in the
    partition from its ``predictions`` (:func:`wagon_residual_spread`). The thresholds
    scale with it (:meth:`FlagConfig.scaled`)."""
    estimates: pa.Table | None = None
    """Its stored virtual-sensor estimates of the revision (``q_flags_estimates.sql``),
    current with its data; None: the wagon is judged without the virtual sensor's opinion."""

    def __str__(self) -> str:  # how an engine names the partition in an error
        return f"wagon {self.wagon_id}"


@dataclass(frozen=True)
class FlagOutcome:
    """What :func:`judge_task` hands back for the parent to store."""

    wagon_id: str
    flags: list[Flag]
    notes: list[str]
    residual_spread_k: float | None = None
    """The wagon's residual spread its thresholds were scaled with (None: none)."""


def _frame(table: pa.Table) -> pl.DataFrame:
    frame = pl.from_arrow(table)
    assert isinstance(frame, pl.DataFrame)
    return frame


def judge_task(task: FlagTask) -> FlagOutcome:
    """One wagon judged from its partition's arrays, no database: a pure function of the
    task, so an engine can run it in a worker process."""
    samples, events = _frame(task.samples), _frame(task.events)
    spread = task.residual_spread_k
    if spread is None and task.data_key is not None and task.predictions is not None:
        spread = wagon_residual_spread(_frame(task.predictions))
    config = task.config.scaled(spread)
    stored: StoredTimeline | None = None
    if task.segments is not None and task.timeline is not None and task.data_key is not None:
        stored = stored_timeline(
            task.wagon_id,
            task.revision,
            task.data_key,
            _frame(task.segments),
            _frame(task.timeline),
        )
    spans = spans_of(
        task.wagon_id, samples, events, ambient_default_c=task.ambient_c, stored=stored
    )
    if not spans:
        return FlagOutcome(task.wagon_id, [], [], spread)
    notes = [] if task.note is None else [f"wagon {task.wagon_id}: {task.note}"]
    predictions = None
    if stored is not None and task.predictions is not None:
        predictions = _frame(task.predictions)
        if predictions.height == 0 and events.height:
            notes.append(
                f"wagon {task.wagon_id}: no predictions of revision {task.revision}; brakings "
                "not judged for weak brakes, dragging in brakings or overheating"
            )
    estimates = None
    if stored is not None:
        try:
            estimates = _estimates(task, spans, config)
        except FleetbrakeError as error:  # the timeline's detectors still judge the wagon
            notes.append(f"wagon {task.wagon_id}: no virtual-sensor opinion: {error}")
    findings = judge_wagon(
        spans,
        predictions=predictions,
        events=events if stored is not None else None,
        config=config,
        estimates=estimates,
        wagon=task.wagon,
        residual_spread_k=spread,
    )
    return FlagOutcome(task.wagon_id, flag_ids(task.wagon_id, findings), notes, spread)


def _estimates(
    task: FlagTask,
    spans: Sequence[tuple[WagonSeries, SpanTimeline | None]],
    config: FlagConfig,
) -> list[EstimateOnGrid | None] | None:
    """The virtual sensor's estimate of each span: the stored one (the estimation stage's,
    :mod:`fleetbrake.simulation.estimates`) when the task has it; None when it has none
    current, ``config.estimator`` is off or the wagon has no registry entry."""
    if not config.estimator or task.wagon is None or task.estimates is None:
        return None
    frame = _frame(task.estimates)
    return [estimate_on_grid(series, frame, config) for series, _ in spans]


def flag_task(
    wh: Warehouse,
    wagon_id: str,
    revision_name: str,
    config: FlagConfig,
    *,
    ambient_c: float,
    note: str | None,
    data_key: str | None,
    wagon: WagonConfig | None = None,
    rev: Revision | None = None,
    residual_spread_k: float | None = None,
    estimated: bool = False,
) -> FlagTask:
    """The wagon's partition, read from the warehouse (by the parent: workers never open
    it); with ``data_key`` (the wagon's timeline of the revision is current) its timeline,
    segments and predictions too, and with ``estimated`` (its stored estimates of the
    revision are current) those."""
    params = {"wagon_id": wagon_id}
    timed = {"wagon_id": wagon_id, "revision": revision_name}

    def arrow(name: str, values: Mapping[str, str]) -> pa.Table:
        return wh.con.sql(sql(name), params=dict(values)).to_arrow_table()

    current = data_key is not None
    return FlagTask(
        wagon_id=wagon_id,
        revision=revision_name,
        ambient_c=ambient_c,
        samples=arrow("q_simulation_wagon_samples", params),
        events=arrow("q_simulation_wagon_events", params),
        config=config,
        note=note,
        data_key=data_key,
        segments=arrow("q_simulation_timeline_segments", timed) if current else None,
        timeline=arrow("q_flags_timeline", timed) if current else None,
        predictions=arrow("q_flags_predictions", timed) if current else None,
        wagon=wagon,
        rev=rev,
        residual_spread_k=residual_spread_k,
        estimates=arrow("q_flags_estimates", timed) if current and estimated else None,
    )


FLAG_CHUNK_ROWS = 200_000
"""Samples per chunk of wagons the flags read together (:class:`FlagChunk`): one query per
table and chunk instead of one per table and wagon (the per-wagon queries decompressed the
stored row groups a wagon shares with its neighbours once per wagon: 35 ms of the writer's
processor time per wagon-day, against about 10 ms per chunk's share)."""


@dataclass(frozen=True)
class _FlagHead:
    """What a wagon's task holds besides its tables (:func:`flag_task`'s arguments)."""

    wagon_id: str
    ambient_c: float
    note: str | None
    data_key: str | None
    wagon: WagonConfig | None
    estimated: bool


@dataclass(frozen=True)
class FlagChunk:
    """Several wagons' partitions of the flags read together, one Arrow table per table with
    a ``wagon_id`` column, or for the four large ones ``wagon_ix`` (``q_*_chunk_*.sql``, in
    stored order; :func:`~fleetbrake.simulation.store.wagon_parts`): :func:`chunk_tasks` cuts
    it into the wagons' :class:`FlagTask` (the same tables :func:`flag_task` reads), which
    :func:`judge_chunk` judges one by one. Picklable: an engine ships it to a worker."""

    heads: tuple[_FlagHead, ...]
    revision: str
    config: FlagConfig
    rev: Revision | None
    samples: pa.Table
    events: pa.Table
    segments: pa.Table
    timeline: pa.Table
    predictions: pa.Table
    estimates: pa.Table | None

    def __str__(self) -> str:  # how an engine names the partition in an error
        ids = [h.wagon_id for h in self.heads]
        return f"wagon {ids[0]}" if len(ids) == 1 else "wagons " + ", ".join(ids)


def flag_chunk(
    wh: Warehouse,
    heads: Sequence[_FlagHead],
    revision_name: str,
    config: FlagConfig,
    rev: Revision | None,
) -> FlagChunk:
    """The chunk's partitions, read from the warehouse with one query per table (by the
    parent: workers never open it); the timelines, segments and predictions of the wagons
    whose timeline is current, the estimates of those whose stored estimates are too."""
    ids, current, estimated = _read_wagons(heads)
    timed = {"revision": revision_name}
    return FlagChunk(
        heads=tuple(heads),
        revision=revision_name,
        config=config,
        rev=rev,
        samples=chunk_table(wh, "q_simulation_chunk_samples", ids),
        events=chunk_table(wh, "q_simulation_chunk_events", ids),
        segments=chunk_table(wh, "q_simulation_chunk_timeline_segments", current, **timed),
        timeline=chunk_table(wh, "q_flags_chunk_timeline", current, **timed),
        predictions=chunk_table(wh, "q_flags_chunk_predictions", current, **timed),
        estimates=(
            chunk_table(wh, "q_flags_chunk_estimates", estimated, **timed) if estimated else None
        ),
    )


def _read_wagons(heads: Sequence[_FlagHead]) -> tuple[list[str], list[str], list[str]]:
    """The wagons whose rows :func:`flag_chunk` reads: every wagon's samples and events, the
    timelines, segments and predictions of those whose timeline is current, the estimates
    of those whose stored estimates are too (the lists the chunk queries' ``wagon_ix``
    counts in)."""
    ids = [h.wagon_id for h in heads]
    current = [h.wagon_id for h in heads if h.data_key is not None]
    estimated = [h.wagon_id for h in heads if h.data_key is not None and h.estimated]
    return ids, current, estimated


def chunk_tasks(chunk: FlagChunk) -> list[FlagTask]:
    """The chunk cut into its wagons' tasks: each wagon's rows sorted as the per-wagon
    queries sort them (:func:`fleetbrake.simulation.store.wagon_parts`), so each task is the
    one :func:`flag_task` reads (a test compares them)."""
    ids, simulated, estimated = _read_wagons(chunk.heads)
    samples = sample_parts(chunk.samples, ids)
    events = wagon_parts(chunk.events, ids, ["start_utc"])
    segments = wagon_parts(chunk.segments, ids, ["start_utc"])
    timeline = wagon_parts(chunk.timeline, ids, ["time_utc"], positions_of=simulated)
    predictions = wagon_parts(
        chunk.predictions, ids, ["event_id", "time_utc"], positions_of=simulated
    )
    estimates = (
        wagon_parts(chunk.estimates, ids, ["time_utc"], positions_of=estimated)
        if chunk.estimates is not None
        else {}
    )
    tasks = []
    for head in chunk.heads:
        w = head.wagon_id
        current = head.data_key is not None
        tasks.append(
            FlagTask(
                wagon_id=w,
                revision=chunk.revision,
                ambient_c=head.ambient_c,
                samples=samples[w],
                events=events[w],
                config=chunk.config,
                note=head.note,
                data_key=head.data_key,
                segments=segments[w] if current else None,
                timeline=timeline[w] if current else None,
                predictions=predictions[w] if current else None,
                wagon=head.wagon,
                rev=chunk.rev,
                estimates=estimates.get(w) if current and head.estimated else None,
            )
        )
    return tasks


def judge_chunk(chunk: FlagChunk) -> list[FlagOutcome]:
    """Each wagon of the chunk judged (:func:`judge_task`), in the chunk's order: a pure
    function of the chunk, so an engine can run it in a worker process."""
    return [judge_task(task) for task in chunk_tasks(chunk)]


def raise_flags(
    wh: Warehouse,
    registry: Registry | Mapping[str, WagonConfig],
    revision_name: str,
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    *,
    wagons: Iterable[str] | None = None,
    engine: Mapper | None = None,
    chunk_rows: int = FLAG_CHUNK_ROWS,
) -> FlagReport:
    """Recompute the flags of ``wagons`` (default: every wagon with samples) from their
    samples, events and what the simulation stored for ``revision_name`` (its timeline and
    predictions), and replace their rows of ``flags`` in one transaction. A wagon without a
    registry entry, or without a current timeline of the revision, is judged on its readings
    only (a note in the report names it). Raises
    :class:`fleetbrake.simulation.predictions.UnknownRevisionError` for an unknown revision.

    Each wagon is judged alone, from its own partition. The parent reads the partitions a
    chunk of wagons at a time (about ``chunk_rows`` samples: :func:`flag_chunk`, one query
    per table), ``engine.map`` runs :func:`judge_chunk` on each chunk (default: the builtin
    ``map``, in this process; an engine's workers otherwise), and the parent stores every
    wagon's flags at the end, in bulk. The flags are the same with any engine and chunk
    size."""
    rev = revision(wh, revision_name)  # the revision must exist
    if isinstance(registry, Registry):
        wagons_by_id: Mapping[str, WagonConfig] = registry.wagons
        default_ambient_c = float(registry.defaults["ambient_temp_c"])
    else:  # the entries a run stored (simulation.predictions.stored_wagons)
        wagons_by_id = registry
        default_ambient_c = WagonConfig(wagon_id="-").ambient_temp_c
    if wagons is None:
        wanted = [str(r[0]) for r in wh.con.execute(sql("q_flags_wagons")).fetchall()]
    else:
        wanted = sorted(set(wagons))
    report = FlagReport(wagons=wanted)
    if not wanted:  # nothing to judge: nothing read, nothing stored
        return report
    keys = data_keys(wh)
    done = simulated_wagons(wh, revision_name)
    current_estimates = _current_estimates(wh, revision_name)

    def head(wagon_id: str) -> _FlagHead:
        wagon = wagons_by_id.get(wagon_id)
        ambient = float(wagon.ambient_temp_c if wagon else default_ambient_c)
        simulated = done.get(wagon_id) if wagon is not None else None
        data_key: str | None = None
        if wagon is None:
            note: str | None = "no valid registry entry; only its readings were judged"
        elif simulated is None:
            note = (
                f"not simulated with revision {revision_name}; only its readings were "
                "judged (the flags read the simulation's timeline: run the simulation first)"
            )
        elif simulated.data_key != keys.get(wagon_id):
            note = (
                f"its data changed since it was simulated with revision {revision_name}; "
                "only its readings were judged (run the simulation first)"
            )
        else:
            note, data_key = None, simulated.data_key
        return _FlagHead(wagon_id, ambient, note, data_key, wagon, wagon_id in current_estimates)

    def chunks() -> Iterator[FlagChunk]:
        for ids in wagon_chunks(wanted, sample_rows(wh), chunk_rows):
            yield flag_chunk(wh, [head(w) for w in ids], revision_name, config, rev)

    outcomes = map(judge_chunk, chunks()) if engine is None else engine.map(judge_chunk, chunks())
    new: list[Flag] = []
    spreads: list[float] = []
    for outcome in (one for chunk in outcomes for one in chunk):
        report.notes += outcome.notes
        new += outcome.flags
        if outcome.residual_spread_k is not None:
            spreads.append(outcome.residual_spread_k)
    if spreads:  # for the report only: each wagon was judged with its own
        report.residual_spread_k = float(statistics.median(spreads))
    _store(wh, report.wagons, new, revision_name, config.key())
    report.flags = new
    logger.info("flags of %d wagons judged: %d flags", len(report.wagons), len(new))
    return report


RESIDUAL_MIN_READINGS = 30
"""Brakings with fewer valid readings in their window do not count in the residual spread."""


RESIDUAL_SPREAD_CAP_K = 0.5
"""K: a wagon's residual spread is at most this (5 x the sensor noise), so that a fault
spanning the whole wagon (a drift over most of its brakings) cannot raise its own thresholds
out of reach."""


def wagon_residual_spread(predictions: pl.DataFrame) -> float | None:
    """One wagon's residual spread for a revision, K: the median over its brakings (with at
    least :data:`RESIDUAL_MIN_READINGS` valid readings) of the rms of measured - predicted
    over each window of its ``predictions``; None without any. A function of the wagon's
    own data and the revision only, so another wagon's late file cannot move its flags."""
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
        .collect(engine="in-memory")  # the engine of the eager calls it replaces
    )
    value = spread.item() if spread.height else None
    if value is None:
        return None
    return min(float(value), RESIDUAL_SPREAD_CAP_K)


def _current_estimates(wh: Warehouse, revision_name: str) -> set[str]:
    """The wagons whose stored virtual-sensor estimates of the revision are current with
    their data (none when the warehouse has no estimation tables)."""
    present = wh.con.execute(sql("q_flags_has_estimates")).fetchone()
    if present is None or int(present[0]) < 2:
        return set()
    keys = estimation_data_keys(wh)
    return {
        wagon_id
        for wagon_id, stored in estimated_wagons(wh, revision_name).items()
        if keys.get(wagon_id) == stored.data_key
    }


_FLAG_SCHEMA = pl.Schema(
    {
        "flag_id": pl.String(),
        "wagon_id": pl.String(),
        "event_id": pl.String(),
        "kind": pl.String(),
        "severity": pl.String(),
        "start_utc": pl.Datetime("us"),
        "end_utc": pl.Datetime("us"),
        "evidence": pl.String(),
        "detected_utc": pl.Datetime("us"),
    }
)


def stale_wagons(wh: Warehouse, revision_name: str, config: FlagConfig) -> list[str]:
    """The wagons with samples whose stored flags are out of date for ``revision_name`` and
    ``config`` (``q_flags_stale_wagons.sql``; ``flagged_wagons`` records each judgement):
    never judged with the revision, judged before a file of theirs was ingested or their
    timeline or estimates of the revision were written, judged with other thresholds
    (:meth:`FlagConfig.key`; or before the key was recorded), or whose rows of ``flags``
    are not the ones their judgement stored. What a run must judge besides the wagons its
    stages changed, so that a run that stopped between its simulation and its flags leaves
    nothing stale behind (``fleetbrake.app.run``)."""
    rows = wh.con.execute(
        sql("q_flags_stale_wagons"), {"revision": revision_name, "config_key": config.key()}
    ).fetchall()
    return [str(r[0]) for r in rows]


def stored_flags(wh: Warehouse) -> list[Flag]:
    """Every flag stored (``q_flags_all.sql``), by wagon, start and kind: the fleet's flags
    after a whole ``run``, those it judged and those that stood."""
    rows = wh.con.execute(sql("q_flags_all")).fetchall()
    return [
        Flag(
            flag_id=str(flag_id),
            wagon_id=str(wagon_id),
            event_id=None if event_id is None else str(event_id),
            kind=str(kind),
            severity=str(severity),
            start_utc=start_utc,
            end_utc=end_utc,
            evidence=str(evidence),
        )
        for flag_id, wagon_id, event_id, kind, severity, start_utc, end_utc, evidence in rows
    ]


def _store(
    wh: Warehouse,
    wagons: Sequence[str],
    flags: Sequence[Flag],
    revision_name: str,
    config_key: str,
) -> None:
    """Replace the flags of ``wagons`` in one transaction, recording that they were judged
    with ``revision_name`` and the thresholds of ``config_key``, and how many flags each
    has (``flagged_wagons``); a flag identical to a stored one keeps its ``detected_utc``."""
    now = utc_now()
    wagon_ids = list(wagons)
    with wh.transaction() as con:
        old = con.execute(sql("q_flags_stored"), {"wagon_ids": wagon_ids}).fetchall()
        kept = {tuple(r[:7]): r[7] for r in old}
        con.execute(sql("q_flags_delete"), {"wagon_ids": wagon_ids})
        con.execute(sql("q_flags_delete_flagged_wagons"), {"wagon_ids": wagon_ids})
        if flags:
            _insert_flags(con, flags, kept, now)
        judged = {
            "wagon_ids": wagon_ids,
            "revision": revision_name,
            "updated_utc": now,
            "config_key": config_key,
        }
        if wagon_ids:  # after the flags: each wagon's count of them is recorded
            con.execute(sql("q_flags_insert_flagged_wagons"), judged)


def _insert_flags(
    con: duckdb.DuckDBPyConnection,
    flags: Sequence[Flag],
    kept: Mapping[tuple[object, ...], dt.datetime],
    now: dt.datetime,
) -> None:
    """Insert ``flags``; one identical to a stored one (``kept``) keeps its
    ``detected_utc``, the others are detected ``now``."""
    rows = pl.DataFrame(
        [
            {
                "flag_id": f.flag_id,
                "wagon_id": f.wagon_id,
                "event_id": f.event_id,
                "kind": f.kind,
                "severity": f.severity,
                "start_utc": f.start_utc,
                "end_utc": f.end_utc,
                "evidence": f.evidence,
                "detected_utc": kept.get(
                    (
                        f.flag_id,
                        f.event_id,
                        f.kind,
                        f.severity,
                        f.start_utc,
                        f.end_utc,
                        f.evidence,
                    ),
                    now,
                ),
            }
            for f in flags
        ],
        schema=_FLAG_SCHEMA,
    )
    con.register("flag_batch", rows)
    try:
        con.execute(sql("q_flags_insert"))
    finally:
        con.unregister("flag_batch")
