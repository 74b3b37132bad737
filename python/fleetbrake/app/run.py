"""``fleetbrake run``: ingest what is new, detect events, simulate every new event with the
current model revision, raise flags; one writer at a time (contract:
``shared/spec/interface.md``)."""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import sys
import time
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from fleetbrake.engine import Engine, make_engine
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.simulation.estimates import EstimationConfig, EstimationReport, estimate_wagons
from fleetbrake.simulation.predictions import (
    SimulationReport,
    current_revision,
    simulate_events,
    store_registry,
)

if TYPE_CHECKING:
    from fleetbrake.flags import Flag, FlagConfig, FlagReport
    from fleetbrake.fleet.registry import Registry
    from fleetbrake.ingest.files import IngestReport
    from fleetbrake.ingest.spans import SpanKey
    from fleetbrake.warehouse.connection import Warehouse

__all__ = [
    "STAGE_MODULES",
    "WRITER_MEMORY_LIMIT",
    "WRITER_THREADS",
    "RunReport",
    "default_db_path",
    "run_fleet",
]

logger = logging.getLogger(__name__)


STAGE_MODULES = (
    "fleetbrake.ingest.files",
    "fleetbrake.simulation.predictions",
    "fleetbrake.simulation.estimates",
    "fleetbrake.flags.judge",
)
"""What the engine's workers run: imported as they start (``run``'s engine, and the one
``fleetbrake watch`` keeps for its life)."""


WRITER_MEMORY_LIMIT = "256MB"
"""DuckDB's buffer pool in the writer during a run (the ingestion lowers it further for its
own stage). The buffer pool keeps the blocks the run writes and reads: at the
connection's 1 GB it grows with the fleet (the writer's peak 448, 619, 1,029 MB at 30, 100,
300 wagon-days); bounded, the writer holds a partition's data and this cache, whatever the
fleet (``docs/decisions/0007-reading-and-writing-in-chunks.md``)."""

WRITER_THREADS = 2
"""DuckDB's threads in the writer: its bulk inserts and per-wagon reads use two; more would
only contend with the engine's workers for the same cores, and each holds its own buffers
under the memory limit."""


def default_db_path() -> Path:
    return Path("warehouse/fleet.duckdb")


@dataclass
class RunReport:
    """Outcome of ``fleetbrake run``."""

    ingest: IngestReport
    simulation: SimulationReport
    revision: str
    flags: FlagReport | None = None
    """The flags stage: the wagons it judged and their flags."""
    fleet_flags: list[Flag] | None = None
    """After a whole run, every flag the fleet has (those judged now and those that stood:
    a second run judges no wagon but still has them); None for a unit of ``watch``."""
    estimation: EstimationReport | None = None
    """The estimation stage (the virtual sensor, ``v_contact_estimates``)."""
    stage_s: dict[str, float] = field(default_factory=dict)
    """Wall-clock seconds of each stage: ``ingest`` (reading and parsing the files, as the
    writer waits for them), ``write`` (the time the ingestion waited for its transactions,
    which run on a writer thread beside the parsing, and its checkpoint), ``events``,
    ``simulate``, ``estimate`` (the virtual sensor), ``flags``; disjoint."""
    engine: str = ""
    """The engine the stages ran on (``LocalEngine(workers=2)``)."""
    estimated_spans: list[tuple[str, dt.datetime, dt.datetime]] = field(default_factory=list)
    """The spans estimated per second in this run, (``wagon_id``, ``span_start_utc``,
    ``span_end_utc``): every span whose flags were judged (with a registry entry), and those
    whose estimates changed. What a compaction of the stored estimates takes."""


class _StageSeconds(dict[str, float]):
    """Seconds per stage, and whom to tell when a stage begins (``run_fleet(on_stage=)``)."""

    def __init__(self, on_stage: Callable[[str], None] | None = None) -> None:
        super().__init__()
        self.on_stage = on_stage


@contextlib.contextmanager
def _clock(stage_s: dict[str, float], stage: str) -> Iterator[None]:
    if isinstance(stage_s, _StageSeconds) and stage_s.on_stage is not None:
        stage_s.on_stage(stage)
    began = time.perf_counter()
    try:
        yield
    finally:
        seconds = time.perf_counter() - began
        stage_s[stage] = stage_s.get(stage, 0.0) + seconds
        logger.info("stage %s: %.2f s", stage, seconds)


def run_fleet(
    fleet_dir: str | Path,
    db_path: str | Path,
    *,
    wait_s: float = 0.0,
    simulation: SimulationConfig | None = None,
    flag_config_path: str | Path | None = None,
    progress: bool | None = None,
    engine: Engine | str = "local",
    workers: int | None = None,
    address: str | None = None,
    files: Collection[str] | None = None,
    on_stage: Callable[[str], None] | None = None,
    estimation: EstimationConfig | None = None,
) -> RunReport:
    """``fleetbrake run``: ingest the files not yet ingested, detect events, simulate every
    new event with the current model revision, raise flags; one writer at a time.

    Raises (before anything is written) what :func:`fleetbrake.ingest.files.run_ingest` raises for
    an unusable fleet directory, registry or database,
    :class:`~fleetbrake.fleet.registry.InvalidRegistryError` when a registry entry of a wagon
    the warehouse holds results of is invalid (:meth:`Registry.check_held
    <fleetbrake.fleet.registry.Registry.check_held>`: every such wagon's entry is checked at
    every run, with or without new files), and
    :class:`~fleetbrake.engine.EngineConfigError` for an unknown ``engine`` name, ``ray``
    without Ray installed, or ``workers < 1``. ``progress``: show progress bars (None: when stdout
    is a terminal).

    ``engine``: an engine's name (:func:`fleetbrake.engine.make_engine`, with ``workers``
    and, for ``ray``, the cluster's ``address``;
    made once here, handed to every stage, closed at the end) or an engine the caller made
    and closes. The tables are the same with any engine.

    ``on_stage``: called with a stage's name as it begins (``bench fleet`` samples the
    memory per stage with it).

    ``estimation``: how the virtual sensor's stage estimates (default: ``EstimationConfig``
    with the simulation's chain numbers; :mod:`fleetbrake.simulation.estimates`).

    ``files``: ingest only these paths (relative to ``fleet_dir``, as ``v_files.path``)
    instead of scanning ``logs/`` (a unit of ``fleetbrake watch``); the later stages are
    the same as without it.

    Each stage computes the spans of the wagons' data (``fleetbrake.ingest.spans``) whose
    keys changed, and the flags judge only the spans whose flags are out of date, each
    estimated again first (:func:`_spans_to_estimate`, the same rule for a whole run and a
    unit of ``watch``): a second run over the same directory computes none, a late file its
    spans alone.
    """
    from fleetbrake.flags import FlagConfig, load_flag_config
    from fleetbrake.ingest.files import load_fleet_registry
    from fleetbrake.warehouse.connection import open_warehouse

    progress = sys.stdout.isatty() if progress is None else progress
    with contextlib.ExitStack() as owned:
        if isinstance(engine, str):  # a bad name or count: refused before anything is read
            engine = owned.enter_context(
                make_engine(engine, workers, preload=STAGE_MODULES, address=address)
            )
            engine.start()  # the workers import the stages while the files are scanned
        registry = load_fleet_registry(fleet_dir)
        flag_config = load_flag_config(flag_config_path) if flag_config_path else FlagConfig()
        logger.info("engine: %r", engine)
        with open_warehouse(
            db_path, wait_s=wait_s, memory_limit=WRITER_MEMORY_LIMIT, threads=WRITER_THREADS
        ) as wh:
            return _stages(
                wh,
                db_path,
                fleet_dir,
                registry,
                simulation,
                flag_config,
                progress,
                engine,
                files,
                on_stage,
                estimation,
            )
    raise AssertionError("unreachable")  # ExitStack may swallow exceptions, for mypy


def _spans_to_estimate(
    wh: Warehouse, revision_name: str, flag_config: FlagConfig, sim: SimulationReport
) -> set[SpanKey]:
    """The spans a run (a whole ``run`` or a unit of ``fleetbrake watch``) estimates again
    besides those whose own keys changed: every span whose flags it will judge. The flags of
    a span are always judged on per-second estimates computed in the same run (the stored
    estimates are made per minute outside their estimate windows after the flags), so the
    spans to estimate are a superset of the spans to judge (:func:`_spans_to_judge`): those
    the simulation recomputed and any whose stored flags are out of date otherwise
    (:func:`fleetbrake.flags.storage.stale_spans`: never judged, judged before their data,
    timeline or estimates were last written (a run stopped before its flags), with another
    revision or other thresholds than ``flag_config``, or their flags removed since). A
    span's flags depend only on its own data, its wagon's registry entry (a changed one
    re-simulates the wagon's spans; a removed one is not seen), the revision and the
    thresholds: no detector compares spans, so the others' stored flags stand."""
    from fleetbrake.flags.storage import stale_spans

    simulated = {(wagon_id, start) for wagon_id, start, _ in sim.spans_simulated}
    return simulated | set(stale_spans(wh, revision_name, flag_config))


def _spans_to_judge(to_estimate: set[SpanKey], estimated: EstimationReport) -> set[SpanKey]:
    """The spans whose flags a run judges: those :func:`_spans_to_estimate` gave (estimated
    again in this run, unless their wagon has no registry entry: judged on their readings
    only) and those the estimation found changed (their estimates newer than their flags).
    Every one of them with an entry was estimated in this run."""
    return to_estimate | {(wagon_id, start) for wagon_id, start, _ in estimated.spans_estimated}


def _stages(
    wh: Warehouse,
    db_path: str | Path,
    fleet_dir: str | Path,
    registry: Registry,
    simulation: SimulationConfig | None,
    flag_config: FlagConfig,
    progress: bool,
    engine: Engine,
    files: Collection[str] | None = None,
    on_stage: Callable[[str], None] | None = None,
    estimation: EstimationConfig | None = None,
) -> RunReport:
    """The stages of :func:`run_fleet` on an open warehouse, each on ``engine``."""
    import duckdb

    from fleetbrake.flags import raise_flags
    from fleetbrake.flags.storage import stored_flags
    from fleetbrake.ingest.events import update_events
    from fleetbrake.ingest.files import ingest_fleet
    from fleetbrake.warehouse.connection import WarehouseError

    stage_s: dict[str, float] = _StageSeconds(on_stage)
    try:
        with _clock(stage_s, "ingest"):
            ingest = ingest_fleet(
                fleet_dir, wh, registry=registry, progress=progress, engine=engine, files=files
            )
        stage_s["ingest"] -= ingest.write_s  # the writer's share, apart
        stage_s["write"] = ingest.write_s
        with _clock(stage_s, "events"):
            ingest.events = update_events(wh, engine=engine)
        with _clock(stage_s, "simulate"):
            store_registry(wh, registry)
            declared = simulation or SimulationConfig()
            rev = current_revision(wh, declared.solver, declared.refinement)
            sim = simulate_events(wh, registry, rev, simulation, progress=progress, engine=engine)
        with _clock(stage_s, "estimate"):
            to_estimate = _spans_to_estimate(wh, rev.name, flag_config, sim)
            estimated = estimate_wagons(
                wh,
                registry,
                rev,
                estimation or EstimationConfig(chain=declared.chain),
                spans=to_estimate,
                progress=progress,
                engine=engine,
            )
        with _clock(stage_s, "flags"):
            flags = raise_flags(
                wh,
                registry,
                rev.name,
                flag_config,
                engine=engine,
                spans=_spans_to_judge(to_estimate, estimated),
            )
    except duckdb.Error as error:
        raise WarehouseError(f"{db_path}: {error}") from error
    return RunReport(
        ingest=ingest,
        simulation=sim,
        revision=rev.name,
        flags=flags,
        fleet_flags=stored_flags(wh) if files is None else None,
        estimation=estimated,
        stage_s=dict(stage_s),
        engine=repr(engine),
        estimated_spans=list(estimated.spans_estimated),
    )
