"""The effects on how the block exchanges heat with its surroundings: ``convection_speed``
(forced convection with speed), ``holder_conduction`` (conduction into the holder) and
``ambient_offset`` (the air around the block off ambient)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from fleetbrake.model.effects.base import DriveInputs, Effect, FloatArray

__all__ = [
    "AIR_FACES",
    "AmbientOffset",
    "ConvectionFlatPlate",
    "ConvectionSpeed",
    "HolderConduction",
]


AIR_FACES: tuple[str, ...] = ("air", "holder")
"""The face sets cooled by air (every surface but the friction face)."""


@dataclass(frozen=True)
class ConvectionSpeed(Effect):
    """Forced convection as a power law of speed: ``h(v) = h0 (1 + gain (v / v_ref)^exponent)``
    on the face sets of ``FACES`` (every surface but the friction face),
    ``v_ref = REFERENCE_SPEED_KMH``: the form of the forced-convection correlations
    ``Nu = C Re^m Pr^n`` (Hilpert's, Zukauskas's) with the constant and the Reynolds
    exponent free, added to the still-air coefficient h0. Free parameters: ``gain``,
    ``exponent``."""

    name: ClassVar[str] = "convection_speed"
    law: ClassVar[str] = "power"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "gain": (0.8, 4.0),
        "exponent": (0.6, 1.0),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "gain": (0.0, 50.0),
        "exponent": (0.1, 2.0),
    }
    FACES: ClassVar[tuple[str, ...]] = AIR_FACES
    REFERENCE_SPEED_KMH: ClassVar[float] = 100.0

    gain: float = 2.0
    exponent: float = 0.8

    def h_factor(self, speed_kmh: FloatArray) -> FloatArray:
        v = np.maximum(np.asarray(speed_kmh, dtype=np.float64), 0.0)
        return 1.0 + self.gain * (v / self.REFERENCE_SPEED_KMH) ** self.exponent

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        factor = self.h_factor(inputs.speed_kmh)
        h = dict(inputs.h_w_m2k)
        for face in self.FACES:
            if face in h:
                h[face] = h[face] * factor
        return inputs.replace(h_w_m2k=h)


@dataclass(frozen=True)
class ConvectionFlatPlate(Effect):
    """Forced convection from a correlation of the block's geometry: the block as a flat
    plate of length L along the flow (its arc ``R_w theta_c``, 0.236 m for
    ``cast-iron-bgu``) in air at the train's speed,

    ``Nu_L = 0.664 Re_L^1/2 Pr^1/3`` (laminar, Re_L <= 5e5) and
    ``Nu_L = (0.037 Re_L^4/5 - 871) Pr^1/3`` (mixed laminar-turbulent, Re_L > 5e5),

    ``h_f = Nu_L k_air / L`` (Incropera & DeWitt, *Fundamentals of Heat and Mass Transfer*,
    6th ed., eqs. 7.30 and 7.38; air at 300 K from its Table A.4), added to the still-air
    coefficient of each face set of ``FACES``: ``h(v) = h0 + multiplier h_f(v)``. Free
    parameter: ``multiplier`` (the flow under a wagon is neither free-stream nor parallel:
    shielding by the bogie, turbulence from the wheel). The air's properties and L are
    fixed (``AIR_*``, ``LENGTH_M``).
    """

    name: ClassVar[str] = "convection_speed"
    law: ClassVar[str] = "flat_plate"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "multiplier": (0.15, 1.0),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "multiplier": (0.0, 20.0),
    }
    FACES: ClassVar[tuple[str, ...]] = AIR_FACES
    LENGTH_M: ClassVar[float] = 0.460 * math.radians(29.4)
    """The block's length along the flow: the arc of ``shared/spec/block-model.md``."""
    AIR_NU_M2_S: ClassVar[float] = 15.89e-6
    AIR_K_W_MK: ClassVar[float] = 0.0263
    AIR_PR: ClassVar[float] = 0.707
    RE_CRITICAL: ClassVar[float] = 5.0e5

    multiplier: float = 0.5

    @classmethod
    def h_forced(cls, speed_kmh: FloatArray) -> FloatArray:
        """The flat plate's mean coefficient (W/m^2 K) at each speed (multiplier 1)."""
        v = np.maximum(np.asarray(speed_kmh, dtype=np.float64), 0.0) / 3.6
        re = v * cls.LENGTH_M / cls.AIR_NU_M2_S
        pr3 = cls.AIR_PR ** (1.0 / 3.0)
        laminar = 0.664 * np.sqrt(re) * pr3
        mixed = (0.037 * re**0.8 - 871.0) * pr3
        nu = np.where(re > cls.RE_CRITICAL, mixed, laminar)
        return nu * cls.AIR_K_W_MK / cls.LENGTH_M

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        extra = self.multiplier * self.h_forced(inputs.speed_kmh)
        h = dict(inputs.h_w_m2k)
        for face in self.FACES:
            if face in h:
                h[face] = h[face] + extra
        return inputs.replace(h_w_m2k=h)


@dataclass(frozen=True)
class HolderConduction(Effect):
    """Heat leaves through the back face and the lug into the holder (held at ambient): a
    contact conductance ``h_holder_extra_w_m2k`` added on the reduced model's "holder" face
    set, which is the back face and the lug together (the mesh, ``thermal_core::mesh``, has
    no separate lug set: the lug is where the holder grips the back). The holder's mass is
    large and well ventilated, so it is taken at ambient (a thermal contact conductance of
    a dry, lightly pressed steel joint, tens to hundreds of W/m^2 K: e.g. Madhusudana,
    *Thermal Contact Conductance*, 2014). Free parameter: ``h_holder_extra_w_m2k``."""

    name: ClassVar[str] = "holder_conduction"
    law: ClassVar[str] = "conductance"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "h_holder_extra_w_m2k": (20.0, 150.0),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "h_holder_extra_w_m2k": (0.0, 5000.0),
    }
    FACE: ClassVar[str] = "holder"

    h_holder_extra_w_m2k: float = 60.0

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        h = dict(inputs.h_w_m2k)
        h[self.FACE] = h.get(self.FACE, np.zeros_like(inputs.flux_w_m2)) + self.h_holder_extra_w_m2k
        return inputs.replace(h_w_m2k=h)


@dataclass(frozen=True)
class AmbientOffset(Effect):
    """The air around the block is at ambient + ``offset_k`` (warm air under the wagon, or a
    shaded, wetted bogie): the air temperature of every convective boundary, as a sol-air or
    under-floor air temperature enters a heat balance (e.g. ASHRAE Fundamentals, ch. 18).
    Free parameter: ``offset_k``."""

    name: ClassVar[str] = "ambient_offset"
    law: ClassVar[str] = "offset"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {"offset_k": (-4.0, 6.0)}
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {"offset_k": (-50.0, 50.0)}

    offset_k: float = 3.0

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        return inputs.replace(ambient_c=inputs.ambient_c + self.offset_k)
