"""The simulation stage's configuration: :class:`SimulationConfig`.

::

    from fleetbrake.simulation.config import SimulationConfig

    config = SimulationConfig(solver="full", batch_rows=1)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from fleetbrake.model.rom import DEFAULT_REFINEMENT
from fleetbrake.simulation.chains import ChainParams

__all__ = ["SimulationConfig"]


@dataclass(frozen=True)
class SimulationConfig:
    """How the simulation stage predicts: the start of an event window, the chain/re-anchor
    algorithm's numbers, the model a new ``declared`` revision is made with, and how the stage
    reads and writes its rows.

    Read by: ``fleetbrake run``, ``fleetbrake watch``, ``fleetbrake close-loop``.
    """

    initial_state: Literal["carried", "uniform"] = "carried"
    """How an event window starts: the chain carried to the activation and re-anchored
    there, or a uniform block at the reading at activation (the paper's)."""
    chain: ChainParams = field(default_factory=ChainParams)
    """The chain/re-anchor algorithm's numbers (shared with the flags' timeline and the
    close loop)."""
    refinement: float = DEFAULT_REFINEMENT
    """Mesh refinement of a new ``declared`` revision's model (1.0: the default mesh). A
    revision keeps the refinement it was made with (``model_revisions.refinement``)."""
    solver: Literal["rom", "full"] = "rom"
    """What a new ``declared`` revision predicts with: the reduced model (default), or the
    full finite-element model (the reference; a thousand times slower). A revision keeps the
    solver it was made with."""
    batch_rows: int = 1_000_000
    """The stage writes several wagons per transaction, up to about this many rows (of
    ``predictions``, ``timeline`` and ``timeline_segments``) in each; a wagon is never split
    (a larger one is written alone), so each stays whole-old or whole-new. 1: one wagon per
    transaction. Changes no row. DuckDB's writer spends about half the processor time per
    row on transactions of 0.7 M rows and more as on transactions of 0.2 M
    (``docs/decisions/0007-reading-and-writing-in-chunks.md``)."""
    chunk_rows: int = 200_000
    """The parent reads the wagons' samples and events a chunk of wagons at a time, about
    this many samples (one query per table and chunk,
    :class:`~fleetbrake.simulation.predictions.WagonChunk`), and a worker simulates the
    chunk's wagons one by one. Changes no row."""
