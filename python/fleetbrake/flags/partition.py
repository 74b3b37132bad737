"""The flags' partitions: one span's tables as the parent reads them (:class:`FlagTask`,
:func:`flag_task`), a chunk of spans read together (:class:`FlagChunk`, :func:`flag_chunk`,
one query per table, the spans' time ranges only) and cut into its spans' tasks
(:func:`chunk_tasks`), and a task judged with no database (:func:`judge_task`,
:func:`judge_chunk`: pure and picklable, so an engine runs them in its workers).

::

    from fleetbrake.flags.partition import flag_chunk, judge_chunk

    outcomes = judge_chunk(flag_chunk(wh, heads, "declared", config, rev))
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information
import pyarrow.compute as pc  # type: ignore[import-untyped]

from fleetbrake.errors import FleetbrakeError
from fleetbrake.flags.config import FlagConfig
from fleetbrake.flags.estimated import EstimateOnGrid, estimate_on_grid
from fleetbrake.flags.records import Flag
from fleetbrake.flags.series import SpanTimeline, spans_of
from fleetbrake.flags.storage import flag_ids
from fleetbrake.flags.wagon import judge_wagon, wagon_residual_spread
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.ingest.spans import Span, ranges_of
from fleetbrake.simulation.predictions import Revision
from fleetbrake.simulation.series import WagonSeries
from fleetbrake.simulation.store import (
    StoredTimeline,
    arrow_frame,
    chunk_name,
    chunk_table,
    sample_parts,
    span_table,
    stored_timeline,
    wagon_parts,
)
from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = [
    "FLAG_CHUNK_ROWS",
    "FlagChunk",
    "FlagHead",
    "FlagOutcome",
    "FlagTask",
    "chunk_tasks",
    "flag_chunk",
    "flag_task",
    "judge_chunk",
    "judge_task",
]


@dataclass(frozen=True)
class FlagTask:
    """One span's partition of the flags: everything :func:`judge_task` reads, as the parent
    read it from the warehouse (Arrow tables; picklable: an engine ships it to a worker)."""

    span: Span
    revision: str
    ambient_c: float
    samples: pa.Table
    """The span's samples (``q_simulation_span_samples.sql``)."""
    events: pa.Table
    """Its braking events (``q_simulation_span_events.sql``)."""
    config: FlagConfig
    note: str | None = None
    """Why the span is judged on its readings only (no timeline given), for the report."""
    data_key: str | None = None
    segments: pa.Table | None = None
    """The revision's ``timeline_segments`` of the span (``q_flags_span_segments.sql``);
    None: no current timeline, the readings alone are judged."""
    timeline: pa.Table | None = None
    """Its ``timeline`` rows, the predicted sensor temperature (``q_flags_span_timeline.sql``)."""
    predictions: pa.Table | None = None
    """Its ``predictions`` of the revision (``q_flags_span_predictions.sql``)."""
    wagon: WagonConfig | None = None
    """Its registry entry (the declared heat of its brakings, the estimator's model)."""
    rev: Revision | None = None
    """The revision (unused by the judge since the estimates are always the stage's)."""
    residual_spread_k: float | None = None
    """A residual spread given by the caller (tests); None: the span's own, computed in the
    partition from its ``predictions`` (:func:`wagon_residual_spread`). The thresholds
    scale with it (:meth:`FlagConfig.scaled`)."""
    estimates: pa.Table | None = None
    """Its stored virtual-sensor estimates of the revision (``q_flags_estimates.sql``, the
    span's seconds), current with its data; None: the span is judged without the virtual
    sensor's opinion."""

    @property
    def wagon_id(self) -> str:
        return self.span.wagon_id

    def __str__(self) -> str:  # how an engine names the partition in an error
        return str(self.span)


@dataclass(frozen=True)
class FlagOutcome:
    """What :func:`judge_task` hands back for the parent to store."""

    span: Span
    flags: list[Flag]
    notes: list[str]
    residual_spread_k: float | None = None
    """The span's residual spread its thresholds were scaled with (None: none)."""

    @property
    def wagon_id(self) -> str:
        return self.span.wagon_id


def judge_task(task: FlagTask) -> FlagOutcome:
    """One span judged from its partition's arrays, no database: a pure function of the
    task, so an engine can run it in a worker process. The span stands alone: its residual
    spread, the scale of its thresholds, is its own brakings' (``docs/decisions/0009-spans.md``)."""
    samples, events = arrow_frame(task.samples), arrow_frame(task.events)
    spread = task.residual_spread_k
    if spread is None and task.data_key is not None and task.predictions is not None:
        spread = wagon_residual_spread(arrow_frame(task.predictions))
    config = task.config.scaled(spread)
    stored: StoredTimeline | None = None
    note = task.note
    if task.segments is not None and task.timeline is not None and task.data_key is not None:
        if _timeline_fits(task.timeline, samples):
            stored = stored_timeline(
                task.wagon_id,
                task.revision,
                task.data_key,
                arrow_frame(task.segments),
                arrow_frame(task.timeline),
            )
        else:
            note = (
                f"its data changed since it was simulated with revision {task.revision}; "
                "only its readings were judged (run the simulation first)"
            )
    spans = spans_of(
        task.wagon_id, samples, events, ambient_default_c=task.ambient_c, stored=stored
    )
    if not spans:
        return FlagOutcome(task.span, [], [], spread)
    notes = [] if note is None else [f"wagon {task.wagon_id}: {note}"]
    predictions = None
    if stored is not None and task.predictions is not None:
        predictions = arrow_frame(task.predictions)
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
    return FlagOutcome(task.span, flag_ids(task.wagon_id, findings), notes, spread)


def _timeline_fits(timeline: pa.Table, samples: pl.DataFrame) -> bool:
    """Whether the stored timeline holds the samples' seconds (one row per logged second):
    samples changed other than through their files leave it standing, unfit to judge by."""
    times = samples["time_utc"]
    return bool(timeline.num_rows == times.n_unique())


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
    frame = arrow_frame(task.estimates)
    return [estimate_on_grid(series, frame, config) for series, _ in spans]


def flag_task(
    wh: Warehouse,
    span: Span,
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
    """The span's partition, read from the warehouse (by the parent: workers never open
    it); with ``data_key`` (the span's timeline of the revision is current) its timeline,
    segments and predictions too, and with ``estimated`` (its stored estimates of the
    revision are current) those."""
    ranged = {"wagon_id": span.wagon_id, "from_utc": span.start_utc, "to_utc": span.end_utc}
    timed = {**ranged, "revision": revision_name}

    def arrow(name: str, values: Mapping[str, object]) -> pa.Table:
        return wh.con.sql(sql(name), params=dict(values)).to_arrow_table()

    current = data_key is not None
    estimates = None
    if current and estimated:
        whole = arrow("q_flags_estimates", {"wagon_id": span.wagon_id, "revision": revision_name})
        estimates = _in_span(whole, span)
    return FlagTask(
        span=span,
        revision=revision_name,
        ambient_c=ambient_c,
        samples=arrow("q_simulation_span_samples", ranged),
        events=arrow("q_simulation_span_events", ranged),
        config=config,
        note=note,
        data_key=data_key,
        segments=arrow("q_flags_span_segments", timed) if current else None,
        timeline=arrow("q_flags_span_timeline", timed) if current else None,
        predictions=arrow("q_flags_span_predictions", timed) if current else None,
        wagon=wagon,
        rev=rev,
        residual_spread_k=residual_spread_k,
        estimates=estimates,
    )


def _in_span(table: pa.Table, span: Span) -> pa.Table:
    """The rows of ``table`` (by ``time_utc``) in the span's time range."""
    times = table.column("time_utc")
    start = pa.scalar(span.start_utc, times.type)
    end = pa.scalar(span.end_utc, times.type)
    keep = pc.and_(pc.greater_equal(times, start), pc.less_equal(times, end))
    return table.filter(keep)


FLAG_CHUNK_ROWS = 200_000
"""Samples per chunk of spans the flags read together (:class:`FlagChunk`): one query per
table and chunk instead of one per table and span (per-span queries decompress the stored
row groups a span shares with its neighbours once per span: 35 ms of the writer's processor
time per wagon-day, against about 10 ms per chunk's share)."""


@dataclass(frozen=True)
class FlagHead:
    """What a span's task holds besides its tables (:func:`flag_task`'s arguments)."""

    span: Span
    ambient_c: float
    note: str | None
    data_key: str | None
    wagon: WagonConfig | None
    estimated: bool


@dataclass(frozen=True)
class FlagChunk:
    """Several spans' partitions of the flags read together, one Arrow table per table with
    ``part_ix`` (the span's position in the list its query was given; the estimates:
    ``wagon_ix``, the wagon's, cut to each span's seconds), in stored order
    (:func:`~fleetbrake.simulation.store.wagon_parts`): :func:`chunk_tasks` cuts it into the
    spans' :class:`FlagTask` (the same tables :func:`flag_task` reads), which
    :func:`judge_chunk` judges one by one. Picklable: an engine ships it to a worker."""

    heads: tuple[FlagHead, ...]
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
        return chunk_name([h.span.label for h in self.heads])


def flag_chunk(
    wh: Warehouse,
    heads: Sequence[FlagHead],
    revision_name: str,
    config: FlagConfig,
    rev: Revision | None,
) -> FlagChunk:
    """The chunk's partitions, read from the warehouse with one query per table, the spans'
    time ranges only (by the parent: workers never open it); the timelines, segments and
    predictions of the spans whose timeline is current, the estimates of those whose stored
    estimates are too."""
    every, current, estimated = _read_spans(heads)
    timed = {"revision": revision_name}
    return FlagChunk(
        heads=tuple(heads),
        revision=revision_name,
        config=config,
        rev=rev,
        samples=span_table(wh, "q_simulation_chunk_span_samples", ranges_of(every)),
        events=span_table(wh, "q_simulation_chunk_span_events", ranges_of(every)),
        segments=span_table(wh, "q_flags_chunk_span_segments", ranges_of(current), **timed),
        timeline=span_table(wh, "q_flags_chunk_span_timeline", ranges_of(current), **timed),
        predictions=span_table(wh, "q_flags_chunk_span_predictions", ranges_of(current), **timed),
        estimates=(
            chunk_table(wh, "q_flags_chunk_estimates", _wagons(estimated), **timed)
            if estimated
            else None
        ),
    )


def _wagons(spans: Sequence[Span]) -> list[str]:
    """The wagons of ``spans``, each once, in order (the list the estimates' ``wagon_ix``
    counts in)."""
    return list(dict.fromkeys(s.wagon_id for s in spans))


def _read_spans(heads: Sequence[FlagHead]) -> tuple[list[Span], list[Span], list[Span]]:
    """The spans whose rows :func:`flag_chunk` reads: every span's samples and events, the
    timelines, segments and predictions of those whose timeline is current, the estimates
    of those whose stored estimates are too (the lists the chunk queries' ``part_ix``
    counts in)."""
    every = [h.span for h in heads]
    current = [h.span for h in heads if h.data_key is not None]
    estimated = [h.span for h in heads if h.data_key is not None and h.estimated]
    return every, current, estimated


def chunk_tasks(chunk: FlagChunk) -> list[FlagTask]:
    """The chunk cut into its spans' tasks: each span's rows sorted as the per-span
    queries sort them (:func:`fleetbrake.simulation.store.wagon_parts`), so each task is the
    one :func:`flag_task` reads (a test compares them)."""
    every, current, estimated = _read_spans(chunk.heads)
    labels = [s.label for s in every]
    simulated = [s.label for s in current]

    def parts(table: pa.Table, order: list[str], of: list[str]) -> dict[str, pa.Table]:
        return wagon_parts(table, labels, order, positions_of=of, index="part_ix")

    samples = sample_parts(chunk.samples, labels, "part_ix")
    events = parts(chunk.events, ["start_utc"], labels)
    segments = parts(chunk.segments, ["start_utc"], simulated)
    timeline = parts(chunk.timeline, ["time_utc"], simulated)
    predictions = parts(chunk.predictions, ["event_id", "time_utc"], simulated)
    wagons = _wagons(estimated)
    estimates = (
        wagon_parts(chunk.estimates, wagons, ["time_utc"], positions_of=wagons)
        if chunk.estimates is not None
        else {}
    )
    tasks = []
    for head in chunk.heads:
        label = head.span.label
        current_span = head.data_key is not None
        own = estimates.get(head.span.wagon_id) if current_span and head.estimated else None
        tasks.append(
            FlagTask(
                span=head.span,
                revision=chunk.revision,
                ambient_c=head.ambient_c,
                samples=samples[label],
                events=events[label],
                config=chunk.config,
                note=head.note,
                data_key=head.data_key,
                segments=segments[label] if current_span else None,
                timeline=timeline[label] if current_span else None,
                predictions=predictions[label] if current_span else None,
                wagon=head.wagon,
                rev=chunk.rev,
                estimates=None if own is None else _in_span(own, head.span),
            )
        )
    return tasks


def judge_chunk(chunk: FlagChunk) -> list[FlagOutcome]:
    """Each span of the chunk judged (:func:`judge_task`), in the chunk's order: a pure
    function of the chunk, so an engine can run it in a worker process."""
    return [judge_task(task) for task in chunk_tasks(chunk)]
