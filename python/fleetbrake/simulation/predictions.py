"""The simulation stage of ``fleetbrake run``: every span of a wagon's data whose data changed
is simulated with the current model revision, and what the next stages need is stored
(contract: ``shared/spec/interface.md``).

::

    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.simulation.predictions import current_revision, simulate_events

    rev = current_revision(wh)
    report = simulate_events(wh, registry, rev, SimulationConfig())

Per span (:mod:`fleetbrake.ingest.spans`: a stretch of a wagon's samples without a gap
longer than 6 h), with :mod:`fleetbrake.simulation.chains` (the one chain/re-anchor
algorithm, its numbers in :class:`~fleetbrake.simulation.chains.ChainParams`), from a uniform
block at its first trusted reading:

* ``predictions`` (``v_predictions``): each event's window, from activation until 600 s after
  release (the next activation, or a data gap), the chain carried to the activation and
  re-anchored there (``initial_state="carried"``, the default), or from a uniform block at
  the reading at activation (``"uniform"``, the paper's way); ``docs/pipeline.md`` compares;
* ``timeline`` and ``timeline_segments``: the block at every logged second of the span,
  re-anchored at the start of every segment, and where and how it was: what the flags judge
  (they do not simulate);
* ``simulated_spans``: the span's data key (``spans.data_key``: files, samples, events) and
  the key of what it was simulated with (registry entry, revision, parameters). A span whose
  keys are unchanged is not simulated again (a second ``run`` adds nothing); one whose data
  changed (a late or replaced file) has all its rows of the revision replaced, in one
  transaction; the rows of a span that no longer exists are deleted.

The close loop re-simulates candidates with the same functions (:func:`load_wagon`,
:func:`predict_wagon`), so its fits and the stored predictions agree.

The span is the unit of work: the parent reads a chunk of spans' samples and events as
Arrow, one query per table, their time ranges only (:func:`wagon_chunk`; :func:`wagon_task`
reads one span's, the same tables), :func:`simulate_chunk` cuts it into the spans' tasks and
:func:`simulate_wagon` (pure, picklable, no database) turns each into the rows' columns, in
one call of the reduced model's chain kernel, and the parent writes them in bulk, several
whole spans per transaction (``SimulationConfig.batch_rows``), on a writer thread while it
reads the next chunks (the stages' one pipeline,
:func:`~fleetbrake.simulation.store.chunk_pipeline`); ``simulate_events(engine=...)`` runs
the partitions on an engine's workers (:mod:`fleetbrake.engine`), the builtin ``map`` by default.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import json
import logging
import os
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field

import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.errors import UnknownKeyError
from fleetbrake.fleet.registry import Registry, WagonConfig
from fleetbrake.ingest.spans import Span, SpanKey, ranges_of, stale_spans, stored_spans
from fleetbrake.model.effects import EffectSet
from fleetbrake.model.fullmodel import FullModelRunner
from fleetbrake.model.rom import DEFAULT_REFINEMENT, ReducedModel
from fleetbrake.simulation.batched import simulate_span_batched
from fleetbrake.simulation.chains import (
    EventWindow,
    Model,
    SpanResult,
    event_windows,
    simulate_span,
    uniform_windows,
)
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.simulation.frames import prediction_frame, segment_frame, timeline_frame
from fleetbrake.simulation.series import FloatArray, WagonSeries, running_median
from fleetbrake.simulation.store import (
    Mapper,
    WagonRows,
    WagonWrite,
    arrow_frame,
    chunk_name,
    chunk_pipeline,
    forget_spans,
    replace_spans,
    sample_parts,
    simulated_spans,
    span_table,
    utc_now,
    wagon_events,
    wagon_parts,
    wagon_samples,
)
from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = [
    "DECLARED",
    "Mapper",
    "Revision",
    "SimulationReport",
    "UnknownRevisionError",
    "WagonChunk",
    "WagonData",
    "WagonPrediction",
    "WagonResult",
    "WagonTask",
    "chunk_tasks",
    "current_revision",
    "ensure_declared",
    "load_wagon",
    "model_for",
    "predict_wagon",
    "revision",
    "simulate_chunk",
    "simulate_events",
    "simulate_wagon",
    "store_registry",
    "stored_wagons",
    "wagon_chunk",
    "wagon_task",
]

logger = logging.getLogger(__name__)

DECLARED = "declared"


class UnknownRevisionError(UnknownKeyError):
    """A model revision asked for that the warehouse does not hold; names both."""


@dataclass(frozen=True)
class Revision:
    """A model revision: its name and the effects it adds to the declared model."""

    name: str
    effects: EffectSet = field(default_factory=EffectSet)
    solver: str = "rom"
    refinement: float = DEFAULT_REFINEMENT
    """The mesh refinement of its model: a revision's predictions all come from one mesh, and
    a closed loop's child keeps its parent's (as it keeps the solver)."""


@dataclass
class SimulationReport:
    events_simulated: int = 0
    prediction_rows: int = 0
    skipped: list[str] = field(default_factory=list)
    """Events not simulated, each with the reason (naming the event)."""
    wagons_simulated: list[str] = field(default_factory=list)
    """The wagons some of whose spans were (re)computed."""
    timeline_rows: int = 0
    spans_simulated: list[tuple[str, dt.datetime, dt.datetime]] = field(default_factory=list)
    """The spans (re)computed: (``wagon_id``, ``span_start_utc``, ``span_end_utc``)."""


# --------------------------------------------------------------------------------------------
# Revisions and the stored registry


def ensure_declared(
    wh: Warehouse, solver: str = "rom", refinement: float = DEFAULT_REFINEMENT
) -> None:
    """Record the declared model's revision (the current one) if the warehouse has none."""
    ((count,),) = wh.con.execute(sql("q_simulation_revision_count")).fetchall()
    if count == 0:
        wh.con.execute(
            sql("q_simulation_insert_declared"),
            {
                "name": DECLARED,
                "parameters_json": json.dumps({"effects": []}),
                "solver": solver,
                "refinement": refinement,
                "created_utc": utc_now(),
            },
        )


def revision(wh: Warehouse, name: str) -> Revision:
    """The revision ``name``; :class:`UnknownRevisionError` if the warehouse has none such."""
    rows = wh.con.execute(sql("q_simulation_revision"), {"name": name}).fetchall()
    if not rows:
        raise UnknownRevisionError(f"{wh.path}: no model revision {name!r}")
    params = json.loads(rows[0][0])
    refinement = DEFAULT_REFINEMENT if rows[0][2] is None else float(rows[0][2])
    return Revision(name, EffectSet.from_list(params.get("effects", [])), rows[0][1], refinement)


def current_revision(
    wh: Warehouse, solver: str = "rom", refinement: float = DEFAULT_REFINEMENT
) -> Revision:
    """The current revision; the declared one, made with ``solver`` and ``refinement``, if the
    warehouse has none yet."""
    ensure_declared(wh, solver, refinement)
    rows = wh.con.execute(sql("q_simulation_current_revision")).fetchall()
    return revision(wh, rows[0][0] if rows else DECLARED)


def store_registry(wh: Warehouse, registry: Registry) -> None:
    """Keep the registry entries ``run`` used, for commands given only the database."""
    rows = pl.DataFrame(
        {
            "wagon_id": list(registry.wagons),
            "config_json": [json.dumps(asdict(w)) for w in registry.wagons.values()],
            "source": str(registry.path),
            "updated_utc": utc_now(),
        },
        schema_overrides={"updated_utc": pl.Datetime("us")},
    )
    with wh.transaction() as con:
        con.register("registry_batch", rows)
        try:
            con.execute(sql("q_simulation_delete_registry"))
            con.execute(sql("q_simulation_insert_registry"))
        finally:
            con.unregister("registry_batch")


def stored_wagons(wh: Warehouse) -> dict[str, WagonConfig]:
    """The registry entries the last ``run`` stored (checked again on the way in)."""
    rows = wh.con.execute(sql("q_simulation_stored_wagons")).fetchall()
    return {wagon_id: WagonConfig(**json.loads(text)) for wagon_id, text in rows}


def model_for(wagon: WagonConfig, solver: str, refinement: float = DEFAULT_REFINEMENT) -> Model:
    """The model a revision predicts with: the wagon's reduced model, or the full one."""
    if solver == "full":
        return FullModelRunner.for_wagon(wagon, refinement=refinement)
    return ReducedModel.for_wagon(wagon, refinement=refinement)


_MODELS: dict[tuple[object, ...], Model] = {}
"""The models this process made for :func:`simulate_wagon` (a worker simulates many wagons
of few block types)."""

_MODELS_KEPT = 16


def _process_model(wagon: WagonConfig, solver: str, refinement: float) -> Model:
    key = (wagon.geometry, wagon.block, wagon.sensor_point_m, solver, refinement)
    model = _MODELS.get(key)
    if model is None:
        if len(_MODELS) >= _MODELS_KEPT:
            _MODELS.clear()
        model = _MODELS[key] = model_for(wagon, solver, refinement)
    return model


# --------------------------------------------------------------------------------------------
# One wagon


@dataclass
class WagonData:
    """What one wagon's simulation reads: its registry entry and its spans of samples (each
    with the events whose activation it holds)."""

    wagon: WagonConfig
    spans: list[WagonSeries]

    @property
    def event_ids(self) -> list[str]:
        return [e[0] for series in self.spans for e in series.events]


def load_wagon(wh: Warehouse, wagon: WagonConfig, config: SimulationConfig) -> WagonData:
    """The wagon's samples and events, cut into spans at gaps longer than
    ``config.chain.bridge_max_s``."""
    spans = WagonSeries.spans_from_frame(
        wagon.wagon_id,
        wagon_samples(wh, wagon.wagon_id),
        ambient_default_c=float(wagon.ambient_temp_c),
        bridge_max_s=config.chain.bridge_max_s,
        events=wagon_events(wh, wagon.wagon_id),
    )
    return WagonData(wagon, spans)


@dataclass
class WagonPrediction:
    """One wagon simulated: frames with the columns of ``predictions``, ``timeline`` and
    ``timeline_segments`` (the last two empty when not asked for)."""

    predictions: pl.DataFrame
    timeline: pl.DataFrame
    segments: pl.DataFrame
    events: int
    """Event windows in ``predictions``."""
    skipped: list[str]

    def rows(self) -> WagonRows:
        return WagonRows(self.predictions, self.timeline, self.segments, self.events)


def predict_wagon(
    data: WagonData,
    model: Model,
    rev: Revision,
    config: SimulationConfig,
    *,
    event_ids: Collection[str] | None = None,
    timeline: bool = True,
    reference: bool = False,
) -> WagonPrediction:
    """Simulate the wagon with the revision's effects: the windows of ``event_ids`` (None:
    every event) and, with ``timeline``, the timeline of every span. Without ``timeline`` only
    the spans holding wanted events are simulated, each up to its last wanted window (what a
    close loop's candidate needs). Each span is one call of the reduced model's chain kernel
    (:mod:`~fleetbrake.simulation.batched`); ``reference``: segment by segment in Python
    instead (:func:`~fleetbrake.simulation.chains.simulate_span`, the same result to
    rounding: the reference the batched path is tested against)."""
    chain = config.chain
    span = simulate_span if reference else simulate_span_batched
    wanted = None if event_ids is None else set(event_ids)
    windows: list[tuple[WagonSeries, EventWindow, FloatArray]] = []
    spans: list[tuple[WagonSeries, SpanResult]] = []
    reasons: dict[str, str] = {}
    for series in data.spans:
        mine = [w for w in event_windows(series, chain) if wanted is None or w.event_id in wanted]
        if not timeline and not mine:
            continue
        speed: FloatArray | None = None
        if timeline or config.initial_state == "carried":
            until = None if timeline else max(w.stop for w in mine)
            result = span(
                series, data.wagon, model, rev.effects, chain, event_ids=wanted, until=until
            )
            if timeline:
                spans.append((series, result))
            speed = result.speed_kmh
            if config.initial_state == "carried":
                windows += [(series, w, speed) for w in result.windows]
        if config.initial_state == "uniform":
            if speed is None:
                speed = running_median(series.speed_kmh, chain.speed_median_samples)
            done, missed = uniform_windows(
                series, data.wagon, model, rev.effects, chain, event_ids=wanted
            )
            windows += [(series, w, speed) for w in done]
            reasons.update(missed)
    predicted = {w.event_id for _, w, _ in windows}
    held = set(data.event_ids)
    skipped = [
        f"event {e}: "
        + reasons.get(
            e,
            "fewer than 3 samples from its activation to its window's end"
            if e in held
            else f"no samples of wagon {data.wagon.wagon_id} at its activation",
        )
        for e in sorted((held if wanted is None else wanted) - predicted)
    ]
    return WagonPrediction(
        predictions=prediction_frame(data.wagon.wagon_id, rev.name, windows),
        timeline=timeline_frame(data.wagon.wagon_id, rev.name, spans),
        segments=segment_frame(data.wagon.wagon_id, rev.name, spans),
        events=len(windows),
        skipped=skipped,
    )


# --------------------------------------------------------------------------------------------
# The stage


def _model_key(wagon: WagonConfig, rev: Revision, config: SimulationConfig) -> str:
    """What a wagon's stored rows depend on besides its data."""
    text = json.dumps(
        {
            "wagon": asdict(wagon),
            "effects": rev.effects.to_list(),
            "solver": rev.solver,
            "initial_state": config.initial_state,
            "chain": dataclasses.asdict(config.chain),
            "refinement": rev.refinement,
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class WagonTask:
    """One span's partition of the simulation stage: everything :func:`simulate_wagon`
    reads, as the parent read it from the warehouse (picklable: an engine ships it to a
    worker process)."""

    wagon: WagonConfig
    span: Span
    samples: pa.Table
    """The span's samples (``q_simulation_span_samples.sql``)."""
    events: pa.Table
    """Its braking events (``q_simulation_span_events.sql``)."""
    rev: Revision
    config: SimulationConfig
    model_key: str
    reference: bool = False
    """Simulate segment by segment in Python (the reference) instead of one kernel call per
    span."""

    def __str__(self) -> str:  # how an engine names the partition in an error
        return str(self.span)


@dataclass(frozen=True)
class WagonResult:
    """What :func:`simulate_wagon` hands back for the parent to write: the span's rows of
    ``predictions``, ``timeline`` and ``timeline_segments`` as Arrow tables, and the keys it
    was simulated from."""

    span: Span
    revision: str
    model_key: str
    predictions: pa.Table
    timeline: pa.Table
    segments: pa.Table
    events: int
    skipped: list[str]

    @property
    def wagon_id(self) -> str:
        return self.span.wagon_id

    def write(self) -> WagonWrite:
        """The rows to write, the Arrow tables as they came (DuckDB inserts them as they
        are), with the span's keys."""
        rows = WagonRows(self.predictions, self.timeline, self.segments, self.events)
        span = self.span
        return WagonWrite(
            span.wagon_id, rows, span.data_key, self.model_key, span.start_utc, span.end_utc
        )

    def row_count(self) -> int:
        """Rows it writes, in every table (what a transaction's batch is sized by)."""
        return int(self.predictions.num_rows + self.timeline.num_rows + self.segments.num_rows)


def wagon_task(
    wh: Warehouse,
    wagon: WagonConfig,
    span: Span,
    rev: Revision,
    config: SimulationConfig,
    *,
    model_key: str,
    reference: bool = False,
) -> WagonTask:
    """The span's partition, read from the warehouse (by the parent: workers never open
    it)."""
    params = {"wagon_id": wagon.wagon_id, "from_utc": span.start_utc, "to_utc": span.end_utc}
    return WagonTask(
        wagon=wagon,
        span=span,
        samples=wh.con.sql(sql("q_simulation_span_samples"), params=params).to_arrow_table(),
        events=wh.con.sql(sql("q_simulation_span_events"), params=params).to_arrow_table(),
        rev=rev,
        config=config,
        model_key=model_key,
        reference=reference,
    )


def simulate_wagon(task: WagonTask) -> WagonResult:
    """One span simulated from its partition's arrays, no database: a pure function of the
    task (the model is made, or read from the reduced-model cache, once per process), so an
    engine can run it in a worker process. The span starts from a uniform block at its first
    trusted reading: it stands alone."""
    wagon, config = task.wagon, task.config
    spans = WagonSeries.spans_from_frame(
        wagon.wagon_id,
        arrow_frame(task.samples),
        ambient_default_c=float(wagon.ambient_temp_c),
        bridge_max_s=config.chain.bridge_max_s,
        events=arrow_frame(task.events),
    )
    model = _process_model(wagon, task.rev.solver, task.rev.refinement)
    result = predict_wagon(
        WagonData(wagon, spans), model, task.rev, config, reference=task.reference
    )
    return WagonResult(
        span=task.span,
        revision=task.rev.name,
        model_key=task.model_key,
        predictions=result.predictions.to_arrow(),
        timeline=result.timeline.to_arrow(),
        segments=result.segments.to_arrow(),
        events=result.events,
        skipped=result.skipped,
    )


@dataclass(frozen=True)
class WagonChunk:
    """Several spans' partitions of the simulation stage read together: the chunk's samples
    and events as one Arrow table each, with ``part_ix`` (``q_simulation_chunk_span_*``, only the
    spans' time ranges, in stored order), and each span's entry and model key.
    :func:`chunk_tasks` cuts it into the spans' :class:`WagonTask` (the tables
    :func:`wagon_task` reads: a test compares them), which :func:`simulate_chunk` simulates
    one by one. Picklable."""

    units: tuple[tuple[WagonConfig, Span, str], ...]
    """(entry, span, model key) of each span, in order."""
    samples: pa.Table
    events: pa.Table
    rev: Revision
    config: SimulationConfig
    reference: bool = False

    def __str__(self) -> str:  # how an engine names the partition in an error
        return chunk_name([span.label for _, span, _ in self.units])


def wagon_chunk(
    wh: Warehouse,
    units: Iterable[tuple[WagonConfig, Span, str]],
    rev: Revision,
    config: SimulationConfig,
    *,
    reference: bool = False,
) -> WagonChunk:
    """The chunk's partitions, read from the warehouse with one query per table, the spans'
    time ranges only (by the parent: workers never open it)."""
    todo = tuple(units)
    ranges = ranges_of(span for _, span, _ in todo)
    return WagonChunk(
        units=todo,
        samples=span_table(wh, "q_simulation_chunk_span_samples", ranges),
        events=span_table(wh, "q_simulation_chunk_span_events", ranges),
        rev=rev,
        config=config,
        reference=reference,
    )


def chunk_tasks(chunk: WagonChunk) -> list[WagonTask]:
    """The chunk cut into its spans' tasks, each span's rows sorted as the per-span queries
    sort them (:func:`fleetbrake.simulation.store.wagon_parts`)."""
    labels = [span.label for _, span, _ in chunk.units]
    samples = sample_parts(chunk.samples, labels, "part_ix")
    events = wagon_parts(chunk.events, labels, ["start_utc"], positions_of=labels, index="part_ix")
    return [
        WagonTask(
            wagon=wagon,
            span=span,
            samples=samples[span.label],
            events=events[span.label],
            rev=chunk.rev,
            config=chunk.config,
            model_key=model_key,
            reference=chunk.reference,
        )
        for wagon, span, model_key in chunk.units
    ]


def simulate_chunk(chunk: WagonChunk) -> list[WagonResult]:
    """Each span of the chunk simulated (:func:`simulate_wagon`), in order: a pure function
    of the chunk, so an engine can run it in a worker process."""
    return [simulate_wagon(task) for task in chunk_tasks(chunk)]


def _forced_spans(
    wh: Warehouse,
    spans: Sequence[Span],
    wagons: Iterable[str] | None,
    event_ids: Iterable[str] | None,
) -> set[SpanKey] | None:
    """The spans a caller forces (those of ``wagons``, those holding ``event_ids``); None:
    none forced, the stale spans are simulated."""
    if wagons is None and event_ids is None:
        return None
    forced = set(wagons or ())
    keys = {s.key for s in spans if s.wagon_id in forced}
    if event_ids is not None:
        ids = sorted(set(event_ids))
        rows = wh.con.execute(sql("q_simulation_event_spans"), {"event_ids": ids}).fetchall()
        held = {(str(w), t) for w, t in rows}
        keys |= {
            s.key
            for s in spans
            for w, t in held
            if s.wagon_id == w and s.start_utc <= t <= s.end_utc
        }
    return keys


def simulate_events(
    wh: Warehouse,
    registry: Registry | Mapping[str, WagonConfig],
    rev: Revision,
    config: SimulationConfig | None = None,
    *,
    event_ids: Iterable[str] | None = None,
    wagons: Iterable[str] | None = None,
    progress: bool | None = None,
    engine: Mapper | None = None,
    reference: bool = False,
) -> SimulationReport:
    """Simulate with ``rev`` every span (:mod:`fleetbrake.ingest.spans`) whose data,
    registry entry or simulation parameters changed since it was last simulated with it (or,
    forced, the spans of ``wagons`` and those holding ``event_ids``), storing its event
    windows and timeline; each span whole in one transaction. The results of spans that no
    longer exist (merged by a file landing between them) are deleted first.

    Each span is a partition: the parent reads a chunk of spans with one query per table,
    their time ranges only (:func:`wagon_chunk`), ``engine.map`` runs :func:`simulate_chunk`
    on it (default: the builtin ``map``, in this process; an engine's workers otherwise), and
    the parent writes the results in bulk as they come back, several whole spans per
    transaction (up to ``config.batch_rows`` rows), committed on a writer thread while it
    reads and hands out the next chunks (:func:`~fleetbrake.simulation.store.chunk_pipeline`).
    ``reference``: the segment-by-segment simulation instead of one kernel call per span (the
    same rows, to rounding)."""
    config = config or SimulationConfig()
    wagons_by_id = registry.wagons if isinstance(registry, Registry) else registry
    report = SimulationReport()
    spans = stored_spans(wh)
    forced = _forced_spans(wh, spans, wagons, event_ids)
    ledger = simulated_spans(wh, rev.name)
    model_keys = {w: _model_key(c, rev, config) for w, c in wagons_by_id.items()}
    unregistered = sorted({s.wagon_id for s in spans} - set(wagons_by_id))
    for wagon_id in unregistered:
        if forced is None or any(k[0] == wagon_id for k in forced):
            events = wagon_events(wh, wagon_id)["event_id"].to_list()
            report.skipped += [
                f"event {e}: wagon {wagon_id} has no valid registry entry" for e in events
            ]
    wanted = spans if forced is None else [s for s in spans if s.key in forced]
    todo, orphans = stale_spans(wanted, ledger, lambda s: model_keys.get(s.wagon_id), forced or ())
    if forced is None:
        forget_spans(wh, rev.name, ranges_of(orphans))
    if not todo:
        return report
    show = progress if progress is not None else os.isatty(1)
    from rich.progress import Progress

    units = [(wagons_by_id[span.wagon_id], span, key) for span, key in todo]

    def read(source: Warehouse, part: list[tuple[WagonConfig, Span, str]]) -> WagonChunk:
        return wagon_chunk(source, part, rev, config, reference=reference)

    def write(batch: list[WagonResult]) -> None:
        replace_spans(wh, rev.name, [r.write() for r in batch])

    results = chunk_pipeline(
        wh,
        units,
        unit_rows=lambda unit: unit[1].sample_rows,
        read=read,
        compute=simulate_chunk,
        write=write,
        result_rows=WagonResult.row_count,
        chunk_rows=config.chunk_rows,
        batch_rows=config.batch_rows,
        engine=engine,
    )
    with Progress(disable=not show, transient=True) as bar:
        task = bar.add_task("simulating spans", total=len(units))
        for result in results:
            logger.info(
                "%s: %d events and %d timeline seconds simulated with revision %s",
                result.span,
                result.events,
                result.timeline.num_rows,
                result.revision,
            )
            if result.wagon_id not in report.wagons_simulated:
                report.wagons_simulated.append(result.wagon_id)
            span = result.span
            report.spans_simulated.append((span.wagon_id, span.start_utc, span.end_utc))
            report.events_simulated += result.events
            report.prediction_rows += result.predictions.num_rows
            report.timeline_rows += result.timeline.num_rows
            report.skipped += result.skipped
            bar.advance(task)
    return report
