"""What a span's chain hands to the reduced model's chain kernel and gets back:
:class:`ChainPieces` (the steps' loading, piece by piece), :class:`ChainRule` (the
re-anchoring rule) and :class:`ChainRun` (the timeline, each segment's anchoring, the event
windows). Used by :meth:`fleetbrake.model.rom.ReducedModel.simulate_chain` and
:func:`fleetbrake.model.romchain.simulate_chain_sensor`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["CHAIN_ANCHORS", "ChainPieces", "ChainRule", "ChainRun"]


CHAIN_ANCHORS: tuple[str, ...] = ("none", "start", "before", "after")
"""How a segment of a chain was anchored, by the code :meth:`ReducedModel.simulate_chain`
returns."""


@dataclass(frozen=True)
class ChainPieces:
    """The pieces of one span's chain, for :meth:`ReducedModel.simulate_chain`.

    A piece is samples ``a .. b`` (inclusive) run from a carried state at one reference
    temperature. Pieces ``0 .. J-1`` are the timeline's segments, in order; the others
    continue event windows past their braking segments (un-anchored). Piece ``p``'s steps
    are ``step_offsets[p] .. step_offsets[p+1]`` of the step arrays (T); a 1 s piece has
    ``b - a`` of them, a coarse piece (a long gap, on a grid of its own) has its grid
    positions in ``at[at_offsets[p] : at_offsets[p+1]]`` (from ``a`` to ``b``), its outputs
    interpolated to the seconds.
    """

    a: NDArray[np.int64]
    b: NDArray[np.int64]
    dt_s: NDArray[np.float64]
    """(P) each piece's time step."""
    step_offsets: NDArray[np.int64]
    at: NDArray[np.float64]
    at_offsets: NDArray[np.int64]
    flux_w_m2: NDArray[np.float64]
    """(T) flux of each step (effects applied)."""
    ambient_c: NDArray[np.float64]
    """(T) air temperature of each step."""
    h_w_m2k: NDArray[np.float64]
    """(T, F) convection of each step, per face set in ``face_names`` order."""
    window_continuation: NDArray[np.int64]
    """(J) the piece continuing the window that starts at segment j, -1 if none."""
    window_length: NDArray[np.int64]
    """(J) samples of the window starting at segment j, 0 if none."""


@dataclass(frozen=True)
class ChainRule:
    """The re-anchoring rule (``fleetbrake.simulation.chains.ChainParams``)."""

    anchor_s: int
    anchor_min_readings: int
    window_s: int
    tolerance_k: float
    lag_tau_s: float | None
    """A sensor lag's time constant (acting on the block, not on the shifts); None: none."""


@dataclass(frozen=True)
class ChainRun:
    """A span's chain simulated: the timeline (n, NaN where not simulated), the segments'
    anchoring (code into :data:`CHAIN_ANCHORS`, shift, reference temperature), and the event
    windows concatenated in segment order."""

    sensor_c: NDArray[np.float64]
    contact_mean_c: NDArray[np.float64]
    contact_max_c: NDArray[np.float64]
    anchor: NDArray[np.uint8]
    shift_k: NDArray[np.float64]
    reference_c: NDArray[np.float64]
    window_sensor_c: NDArray[np.float64]
    window_mean_c: NDArray[np.float64]
    window_max_c: NDArray[np.float64]
