"""The full finite-element model behind the reduced model's interface: what
``fleetbrake run --solver full`` predicts with and the acceptance fleets are written by
(:class:`FullModelRunner`), and a full result viewed as a reduced one
(:func:`full_result_as_rom`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike

from fleetbrake.fleet.block import DEFAULT_AMBIENT_C, DEFAULT_CONVECTION_W_M2K
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.rom import DEFAULT_REFINEMENT, RomSimulation
from fleetbrake.model.thermal import AIR_FACES, BlockModel, SimulationResult

__all__ = ["FullModelRunner", "full_result_as_rom"]


class FullModelRunner:
    """The full finite-element model behind the reduced model's ``simulate`` interface, so
    that ``fleetbrake run --solver full`` is one option away. The state it hands on is
    ``θ = T - T_ref`` (the whole nodal field), as the reduced model's is, so continuation and
    re-anchoring mean the same."""

    def __init__(
        self,
        model: BlockModel,
        probe_m: Sequence[float],
        h_nominal: Mapping[str, float] | None = None,
    ):
        self.model = model
        self.probe_m = [tuple(float(v) for v in probe_m)]
        self.h_nominal: dict[str, float] = dict(
            h_nominal
            if h_nominal is not None
            else dict.fromkeys(AIR_FACES, DEFAULT_CONVECTION_W_M2K)
        )

    @classmethod
    def for_wagon(
        cls, wagon: WagonConfig, *, refinement: float = DEFAULT_REFINEMENT
    ) -> FullModelRunner:
        """The full model of a wagon's block on the mesh of ``refinement``, its sensor seat
        the one probe."""
        model = BlockModel(
            wagon.geometry,
            wagon.block_material,
            refinement=refinement,
            sensor_m=wagon.sensor_point_m,
        )
        return cls(model, wagon.sensor_point_m)

    def simulate(
        self,
        *,
        dt_s: float,
        flux_w_m2: ArrayLike,
        initial_c: float,
        ambient_c: float | ArrayLike = DEFAULT_AMBIENT_C,
        h_w_m2k: Mapping[str, float | ArrayLike] | None = None,
        initial_state: ArrayLike | None = None,
    ) -> RomSimulation:
        start = (
            float(initial_c)
            if initial_state is None
            else np.asarray(initial_state, dtype=np.float64) + float(initial_c)
        )
        res = self.model.simulate(
            dt_s=dt_s,
            flux_w_m2=flux_w_m2,
            initial_c=start,
            ambient_c=ambient_c,
            h_w_m2k=self.h_nominal if h_w_m2k is None else h_w_m2k,
            probes_m=self.probe_m,
        )
        return RomSimulation(
            time_s=res.time_s,
            probe_c=res.probe_c,
            face_mean_c=res.face_mean_c,
            face_max_c=res.face_max_c,
            final_state=res.final_c - float(initial_c),
        )


def full_result_as_rom(result: SimulationResult) -> RomSimulation:
    """View a full-model result with the reduced model's fields (for side-by-side checks)."""
    return RomSimulation(
        time_s=result.time_s,
        probe_c=result.probe_c,
        face_mean_c=result.face_mean_c,
        face_max_c=result.face_max_c,
        final_state=result.final_c,
    )
