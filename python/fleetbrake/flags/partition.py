"""The flags' partitions: one wagon's tables as the parent reads them (:class:`FlagTask`,
:func:`flag_task`), a chunk of wagons read together (:class:`FlagChunk`, :func:`flag_chunk`,
one query per table) and cut into its wagons' tasks (:func:`chunk_tasks`), and a task judged
with no database (:func:`judge_task`, :func:`judge_chunk`: pure and picklable, so an engine
runs them in its workers).

::

    from fleetbrake.flags.partition import flag_chunk, judge_chunk

    outcomes = judge_chunk(flag_chunk(wh, heads, "declared", config, rev))
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.errors import FleetbrakeError
from fleetbrake.flags.config import FlagConfig
from fleetbrake.flags.estimated import EstimateOnGrid, estimate_on_grid
from fleetbrake.flags.records import Flag
from fleetbrake.flags.series import SpanTimeline, spans_of
from fleetbrake.flags.storage import flag_ids
from fleetbrake.flags.wagon import judge_wagon, wagon_residual_spread
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.simulation.predictions import Revision
from fleetbrake.simulation.series import WagonSeries
from fleetbrake.simulation.store import (
    StoredTimeline,
    arrow_frame,
    chunk_table,
    sample_parts,
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


def judge_task(task: FlagTask) -> FlagOutcome:
    """One wagon judged from its partition's arrays, no database: a pure function of the
    task, so an engine can run it in a worker process."""
    samples, events = arrow_frame(task.samples), arrow_frame(task.events)
    spread = task.residual_spread_k
    if spread is None and task.data_key is not None and task.predictions is not None:
        spread = wagon_residual_spread(arrow_frame(task.predictions))
    config = task.config.scaled(spread)
    stored: StoredTimeline | None = None
    if task.segments is not None and task.timeline is not None and task.data_key is not None:
        stored = stored_timeline(
            task.wagon_id,
            task.revision,
            task.data_key,
            arrow_frame(task.segments),
            arrow_frame(task.timeline),
        )
    spans = spans_of(
        task.wagon_id, samples, events, ambient_default_c=task.ambient_c, stored=stored
    )
    if not spans:
        return FlagOutcome(task.wagon_id, [], [], spread)
    notes = [] if task.note is None else [f"wagon {task.wagon_id}: {task.note}"]
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
    frame = arrow_frame(task.estimates)
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
table and chunk instead of one per table and wagon (per-wagon queries decompress the stored
row groups a wagon shares with its neighbours once per wagon: 35 ms of the writer's processor
time per wagon-day, against about 10 ms per chunk's share)."""


@dataclass(frozen=True)
class FlagHead:
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
        ids = [h.wagon_id for h in self.heads]
        return f"wagon {ids[0]}" if len(ids) == 1 else "wagons " + ", ".join(ids)


def flag_chunk(
    wh: Warehouse,
    heads: Sequence[FlagHead],
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


def _read_wagons(heads: Sequence[FlagHead]) -> tuple[list[str], list[str], list[str]]:
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
