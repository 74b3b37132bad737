"""The simulation stage of ``fleetbrake run``: every wagon whose data changed is simulated
with the current model revision, and what the next stages need is stored (contract:
``shared/spec/interface.md``).

::

    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.simulation.predictions import current_revision, simulate_events

    rev = current_revision(wh)
    report = simulate_events(wh, registry, rev, SimulationConfig())

Per wagon, with :mod:`fleetbrake.simulation.chains` (the one chain/re-anchor algorithm, its
numbers in :class:`~fleetbrake.simulation.chains.ChainParams`):

* ``predictions`` (``v_predictions``): each event's window, from activation until 600 s after
  release (the next activation, or a data gap), the chain carried to the activation and
  re-anchored there (``initial_state="carried"``, the default), or from a uniform block at
  the reading at activation (``"uniform"``, the paper's way); ``docs/pipeline.md`` compares;
* ``timeline`` and ``timeline_segments``: the block at every logged second of the wagon,
  re-anchored at the start of every segment, and where and how it was: what the flags judge
  (they do not simulate);
* ``simulated_wagons``: the keys of the wagon's data (files, samples, events) and of what it
  was simulated with (registry entry, revision, parameters). A wagon whose keys are unchanged
  is not simulated again (a second ``run`` adds nothing); one whose data changed (a late or
  replaced file) has all its rows of the revision replaced, in one transaction.

The close loop re-simulates candidates with the same functions (:func:`load_wagon`,
:func:`predict_wagon`), so its fits and the stored predictions agree.

The wagon is the unit of work: the parent reads a chunk of wagons' samples and events as
Arrow, one query per table (:func:`wagon_chunk`; :func:`wagon_task` reads one wagon's, the
same tables), :func:`simulate_chunk` cuts it into the wagons' tasks and
:func:`simulate_wagon` (pure, picklable, no database) turns each into the rows' columns,
each span in one call of the reduced model's chain kernel, and the parent writes them in
bulk, several whole wagons per transaction (``SimulationConfig.batch_rows``), on a writer
thread while it reads the next chunks (the stages' one pipeline,
:func:`~fleetbrake.simulation.store.chunk_pipeline`); ``simulate_events(engine=...)`` runs
the partitions on an engine's workers (:mod:`fleetbrake.engine`), the builtin ``map`` by default.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from collections.abc import Collection, Iterable, Mapping
from dataclasses import asdict, dataclass, field

import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.errors import UnknownKeyError
from fleetbrake.fleet.registry import Registry, WagonConfig
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
    chunk_table,
    data_keys,
    forget_wagon,
    replace_wagons,
    sample_parts,
    simulated_wagons,
    stored_wagon_ids,
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
    """The wagons whose rows were (re)computed."""
    timeline_rows: int = 0


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
    """One wagon's partition of the simulation stage: everything :func:`simulate_wagon`
    reads, as the parent read it from the warehouse (picklable: an engine ships it to a
    worker process)."""

    wagon: WagonConfig
    samples: pa.Table
    """The wagon's samples (``q_simulation_wagon_samples.sql``)."""
    events: pa.Table
    """Its braking events (``q_simulation_wagon_events.sql``)."""
    rev: Revision
    config: SimulationConfig
    data_key: str
    model_key: str
    reference: bool = False
    """Simulate segment by segment in Python (the reference) instead of one kernel call per
    span."""

    def __str__(self) -> str:  # how an engine names the partition in an error
        return f"wagon {self.wagon.wagon_id}"


@dataclass(frozen=True)
class WagonResult:
    """What :func:`simulate_wagon` hands back for the parent to write: the rows of
    ``predictions``, ``timeline`` and ``timeline_segments`` as Arrow tables, and the keys the
    wagon was simulated from."""

    wagon_id: str
    revision: str
    data_key: str
    model_key: str
    predictions: pa.Table
    timeline: pa.Table
    segments: pa.Table
    events: int
    skipped: list[str]

    def rows(self) -> WagonRows:
        """The rows to write, the Arrow tables as they came (DuckDB inserts them as they
        are)."""
        return WagonRows(self.predictions, self.timeline, self.segments, self.events)

    def row_count(self) -> int:
        """Rows it writes, in every table (what a transaction's batch is sized by)."""
        return int(self.predictions.num_rows + self.timeline.num_rows + self.segments.num_rows)


def wagon_task(
    wh: Warehouse,
    wagon: WagonConfig,
    rev: Revision,
    config: SimulationConfig,
    *,
    data_key: str,
    model_key: str,
    reference: bool = False,
) -> WagonTask:
    """The wagon's partition, read from the warehouse (by the parent: workers never open
    it)."""
    params = {"wagon_id": wagon.wagon_id}
    return WagonTask(
        wagon=wagon,
        samples=wh.con.sql(sql("q_simulation_wagon_samples"), params=params).to_arrow_table(),
        events=wh.con.sql(sql("q_simulation_wagon_events"), params=params).to_arrow_table(),
        rev=rev,
        config=config,
        data_key=data_key,
        model_key=model_key,
        reference=reference,
    )


def simulate_wagon(task: WagonTask) -> WagonResult:
    """One wagon simulated from its partition's arrays, no database: a pure function of the
    task (the model is made, or read from the reduced-model cache, once per process), so an
    engine can run it in a worker process."""
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
        wagon_id=wagon.wagon_id,
        revision=task.rev.name,
        data_key=task.data_key,
        model_key=task.model_key,
        predictions=result.predictions.to_arrow(),
        timeline=result.timeline.to_arrow(),
        segments=result.segments.to_arrow(),
        events=result.events,
        skipped=result.skipped,
    )


@dataclass(frozen=True)
class WagonChunk:
    """Several wagons' partitions of the simulation stage read together: the chunk's
    samples and events as one Arrow table each, with ``wagon_id`` (``q_simulation_chunk_*``,
    in stored order), and each wagon's entry and keys. :func:`chunk_tasks` cuts it into the
    wagons' :class:`WagonTask` (the tables :func:`wagon_task` reads: a test compares them),
    which :func:`simulate_chunk` simulates one by one. Picklable."""

    wagons: tuple[tuple[WagonConfig, str, str], ...]
    """(entry, data key, model key) of each wagon, in order."""
    samples: pa.Table
    events: pa.Table
    rev: Revision
    config: SimulationConfig
    reference: bool = False

    def __str__(self) -> str:  # how an engine names the partition in an error
        return chunk_name([w.wagon_id for w, _, _ in self.wagons])


def wagon_chunk(
    wh: Warehouse,
    wagons: Iterable[tuple[WagonConfig, str, str]],
    rev: Revision,
    config: SimulationConfig,
    *,
    reference: bool = False,
) -> WagonChunk:
    """The chunk's partitions, read from the warehouse with one query per table (by the
    parent: workers never open it)."""
    todo = tuple(wagons)
    ids = [w.wagon_id for w, _, _ in todo]
    return WagonChunk(
        wagons=todo,
        samples=chunk_table(wh, "q_simulation_chunk_samples", ids),
        events=chunk_table(wh, "q_simulation_chunk_events", ids),
        rev=rev,
        config=config,
        reference=reference,
    )


def chunk_tasks(chunk: WagonChunk) -> list[WagonTask]:
    """The chunk cut into its wagons' tasks, each wagon's rows sorted as the per-wagon
    queries sort them (:func:`fleetbrake.simulation.store.wagon_parts`)."""
    ids = [wagon.wagon_id for wagon, _, _ in chunk.wagons]
    samples = sample_parts(chunk.samples, ids)
    events = wagon_parts(chunk.events, ids, ["start_utc"])
    return [
        WagonTask(
            wagon=wagon,
            samples=samples[wagon.wagon_id],
            events=events[wagon.wagon_id],
            rev=chunk.rev,
            config=chunk.config,
            data_key=data_key,
            model_key=model_key,
            reference=chunk.reference,
        )
        for wagon, data_key, model_key in chunk.wagons
    ]


def simulate_chunk(chunk: WagonChunk) -> list[WagonResult]:
    """Each wagon of the chunk simulated (:func:`simulate_wagon`), in order: a pure function
    of the chunk, so an engine can run it in a worker process."""
    return [simulate_wagon(task) for task in chunk_tasks(chunk)]


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
    """Simulate with ``rev`` every wagon whose data, registry entry or simulation parameters
    changed since it was last simulated with it (or, forced, the wagons of ``event_ids`` and
    ``wagons``), storing its event windows and timeline; each wagon whole in one transaction.

    Each wagon is a partition: the parent reads a chunk of wagons with one query per table
    (:func:`wagon_chunk`), ``engine.map`` runs :func:`simulate_chunk` on it (default: the
    builtin ``map``, in this process; an engine's workers otherwise), and the parent writes the
    results in bulk as they come back, several whole wagons per transaction (up to
    ``config.batch_rows`` rows), committed on a writer thread while it reads and hands out the
    next chunks (:func:`~fleetbrake.simulation.store.chunk_pipeline`). ``reference``: the
    segment-by-segment simulation instead of one kernel call per span (the same rows, to
    rounding)."""
    config = config or SimulationConfig()
    wagons_by_id = registry.wagons if isinstance(registry, Registry) else registry
    report = SimulationReport()
    keys = data_keys(wh)
    done = simulated_wagons(wh, rev.name)
    only = wagons is not None or event_ids is not None
    forced: set[str] = set(wagons or ())
    if event_ids is not None:
        ids = sorted(set(event_ids))
        rows = wh.con.execute(sql("q_simulation_event_wagons"), {"event_ids": ids}).fetchall()
        forced |= {r[0] for r in rows}
    if not only:
        for wagon_id in sorted(set(done) - set(keys)):  # its samples are gone
            forget_wagon(wh, wagon_id, rev.name)
    todo = []
    for wagon_id, data_key in keys.items():
        wagon = wagons_by_id.get(wagon_id)
        if only and wagon_id not in forced:
            continue
        if wagon is None:
            events = wagon_events(wh, wagon_id)["event_id"].to_list()
            report.skipped += [
                f"event {e}: wagon {wagon_id} has no valid registry entry" for e in events
            ]
            continue
        model_key = _model_key(wagon, rev, config)
        stored = done.get(wagon_id)
        if (
            wagon_id in forced
            or stored is None
            or (stored.data_key, stored.model_key)
            != (
                data_key,
                model_key,
            )
        ):
            todo.append((wagon, data_key, model_key))
    if not todo:
        return report
    show = progress if progress is not None else os.isatty(1)
    from rich.progress import Progress

    by_id = {wagon.wagon_id: (wagon, data_key, model_key) for wagon, data_key, model_key in todo}
    holding = stored_wagon_ids(wh, rev.name)  # the others' rows are only inserted

    def read(source: Warehouse, ids: list[str]) -> WagonChunk:
        return wagon_chunk(source, [by_id[w] for w in ids], rev, config, reference=reference)

    def write(batch: list[WagonResult]) -> None:
        writes = [WagonWrite(r.wagon_id, r.rows(), r.data_key, r.model_key) for r in batch]
        replace_wagons(wh, rev.name, writes, delete=any(w.wagon_id in holding for w in batch))

    results = chunk_pipeline(
        wh,
        list(by_id),
        read=read,
        compute=simulate_chunk,
        write=write,
        result_rows=WagonResult.row_count,
        chunk_rows=config.chunk_rows,
        batch_rows=config.batch_rows,
        engine=engine,
    )
    with Progress(disable=not show, transient=True) as bar:
        task = bar.add_task("simulating wagons", total=len(todo))
        for result in results:
            logger.info(
                "wagon %s: %d events and %d timeline seconds simulated with revision %s",
                result.wagon_id,
                result.events,
                result.timeline.num_rows,
                result.revision,
            )
            report.wagons_simulated.append(result.wagon_id)
            report.events_simulated += result.events
            report.prediction_rows += result.predictions.num_rows
            report.timeline_rows += result.timeline.num_rows
            report.skipped += result.skipped
            bar.advance(task)
    return report
