"""``fleetbrake run``: ingest what is new, detect events, simulate every new event with the
current model revision, raise flags; one writer at a time (contract:
``shared/spec/interface.md``)."""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from fleetbrake.simulation.predictions import (
    SimulationConfig,
    SimulationReport,
    current_revision,
    simulate_events,
    store_registry,
)

if TYPE_CHECKING:
    from fleetbrake.flags import FlagReport
    from fleetbrake.ingest.files import IngestReport

__all__ = ["RunReport", "default_db_path", "run_fleet"]

logger = logging.getLogger(__name__)


def default_db_path() -> Path:
    return Path("warehouse/fleet.duckdb")


@dataclass
class RunReport:
    """Outcome of ``fleetbrake run``."""

    ingest: IngestReport
    simulation: SimulationReport
    revision: str
    flags: FlagReport | None = None
    stage_s: dict[str, float] = field(default_factory=dict)
    """Wall-clock seconds of each stage: ``ingest``, ``events``, ``simulate``, ``flags``."""


@contextlib.contextmanager
def _clock(stage_s: dict[str, float], stage: str) -> Iterator[None]:
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
) -> RunReport:
    """``fleetbrake run``: ingest the files not yet ingested, detect events, simulate every
    new event with the current model revision, raise flags; one writer at a time.

    Raises (before anything is written) what :func:`fleetbrake.ingest.files.run_ingest` raises for
    an unusable fleet directory, registry or database. ``progress``: show progress bars
    (None: when stdout is a terminal).
    """
    import duckdb

    from fleetbrake.flags import FlagConfig, load_flag_config, raise_flags
    from fleetbrake.ingest.events import update_events
    from fleetbrake.ingest.files import ingest_fleet, load_fleet_registry
    from fleetbrake.warehouse.connection import WarehouseError, open_warehouse

    progress = sys.stdout.isatty() if progress is None else progress
    registry = load_fleet_registry(fleet_dir)
    flag_config = load_flag_config(flag_config_path) if flag_config_path else FlagConfig()
    stage_s: dict[str, float] = {}
    with open_warehouse(db_path, wait_s=wait_s) as wh:
        try:
            with _clock(stage_s, "ingest"):
                ingest = ingest_fleet(fleet_dir, wh, registry=registry, progress=progress)
            with _clock(stage_s, "events"):
                ingest.events = update_events(wh)
            with _clock(stage_s, "simulate"):
                store_registry(wh, registry)
                rev = current_revision(wh, (simulation or SimulationConfig()).solver)
                sim = simulate_events(wh, registry, rev, simulation, progress=progress)
            with _clock(stage_s, "flags"):
                flags = raise_flags(wh, registry, rev.name, flag_config)
        except duckdb.Error as error:
            raise WarehouseError(f"{db_path}: {error}") from error
    return RunReport(ingest=ingest, simulation=sim, revision=rev.name, flags=flags, stage_s=stage_s)
