"""``empirical``: a linear data-driven correction of the heat input and the convection, the
close loop's fallback when no physical effect leaves an adequate fit."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from fleetbrake.model.effects.base import DriveInputs, Effect
from fleetbrake.model.effects.convection import AIR_FACES

__all__ = ["Empirical"]


@dataclass(frozen=True)
class Empirical(Effect):
    """A data-driven correction where no physical effect fits (interface.md): linear in its
    parameters, on drivers with a physical meaning, acting on the loading only (the chain
    simulation passes the sensor output through nothing but a lag):

    - the friction-face heat input, by a share of the block power and a share that grows
      with speed: ``flux (1 + flux_gain + flux_speed_gain v / v_ref)`` (>= 0);
    - the heat lost to the air, by a loss proportional to ``T - T_ambient`` and one
      proportional to ``(T - T_ambient) v / v_ref``: ``h + h_extra_w_m2k +
      h_speed_w_m2k v / v_ref`` on every air-cooled face set (>= 0).

    Every parameter 0 is no change at all; ``v_ref = REFERENCE_SPEED_KMH``. Free parameters:
    all four. ``fallback``: the close loop tries it last, when nothing physical is adequate,
    and the synthetic generator never draws it.
    """

    name: ClassVar[str] = "empirical"
    law: ClassVar[str] = "linear"
    fallback: ClassVar[bool] = True
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "flux_gain": (-0.3, 0.3),
        "flux_speed_gain": (-0.3, 0.3),
        "h_extra_w_m2k": (-5.0, 5.0),
        "h_speed_w_m2k": (-5.0, 5.0),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "flux_gain": (-0.95, 5.0),
        "flux_speed_gain": (-5.0, 5.0),
        "h_extra_w_m2k": (-9.0, 500.0),
        "h_speed_w_m2k": (-100.0, 500.0),
    }
    FACES: ClassVar[tuple[str, ...]] = AIR_FACES
    REFERENCE_SPEED_KMH: ClassVar[float] = 100.0

    flux_gain: float = 0.0
    flux_speed_gain: float = 0.0
    h_extra_w_m2k: float = 0.0
    h_speed_w_m2k: float = 0.0

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        v = np.maximum(np.asarray(inputs.speed_kmh, dtype=np.float64), 0.0)
        v = v / self.REFERENCE_SPEED_KMH
        if self.flux_gain or self.flux_speed_gain:
            factor = np.maximum(1.0 + self.flux_gain + self.flux_speed_gain * v, 0.0)
            inputs = inputs.replace(flux_w_m2=inputs.flux_w_m2 * factor)
        if self.h_extra_w_m2k or self.h_speed_w_m2k:
            extra = self.h_extra_w_m2k + self.h_speed_w_m2k * v
            h = dict(inputs.h_w_m2k)
            for face in self.FACES:
                if face in h:
                    h[face] = np.maximum(h[face] + extra, 0.0)
            inputs = inputs.replace(h_w_m2k=h)
        return inputs
