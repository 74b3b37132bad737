"""The effects on the heat the friction puts into the block: ``friction_speed`` (mu of cast
iron with speed and force), ``friction_temperature`` (mu fading with the face temperature) and
``heat_partition`` (the block's share of the friction heat)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from fleetbrake.model.effects.base import DriveInputs, Effect, FloatArray

__all__ = [
    "KARWATZKI_FORCE_SCALE_KN",
    "KARWATZKI_LEVEL",
    "TONNE_FORCE_N",
    "FrictionSpeed",
    "FrictionSpeedNormalised",
    "FrictionTemperature",
    "HeatPartition",
    "HeatPartitionEffusivity",
]


KARWATZKI_LEVEL = 0.6
"""The constant of Karwatzki's law for cast-iron blocks (mu at rest under a vanishing force)."""

TONNE_FORCE_N = 9.80665e3
"""N in one tonne-force, the unit of the block force in Karwatzki's law as published."""

KARWATZKI_FORCE_SCALE_KN = 100.0 * TONNE_FORCE_N / 1000.0
"""K_s of Karwatzki's law: 100 tonne-force, in kN (980.665)."""


@dataclass(frozen=True)
class FrictionSpeed(Effect):
    """Karwatzki's law for cast-iron (P10) brake blocks, with its level:

    ``mu(v, K) = level 0.6 (16 K + K_s) / (80 K + K_s) (v + v_s) / (5 v + v_s)``

    with K the block's normal force and v the speed in km/h; the literature's constants are
    K_s = 100 and v_s = 100 with K in tonne-force (Karwatzki's formula for grey cast-iron
    blocks as the railway braking literature quotes it, e.g. Wende, *Fahrdynamik des
    Schienenverkehrs*, Teubner 2003, and the Russian braking textbooks that write it with K
    in tonne-force; its SI form ``(1.6 K + 100) / (8 K + 100)`` with K in kN rounds g to
    10 m/s²). The force ratio depends on K / K_s alone, so the code takes K in kN and
    K_s = 100 tf = 980.665 kN (``KARWATZKI_FORCE_SCALE_KN``). Read with K in kN against
    K_s = 100, the law would give mu of 0.06-0.07 at a freight wagon's 20-30 kN a block
    and 40 km/h, half of what cast iron gives; in tonne-force it gives 0.12-0.14.
    The coefficient is the law's own, NOT normalised to the registry's mu: the friction
    power is ``mu(v, F) F v``, so the flux built with the registry's mu is scaled by
    ``mu(v, F) / mu_registry`` (``DriveInputs.friction_coefficient``).

    Free parameters: ``level`` (a scale on the literature's 0.6: blocks of another cast or
    state), ``speed_scale_kmh`` (v_s) and ``force_scale_kn`` (K_s). The scales are admissible
    within 0.3-3x the literature's (``LIMITS``): beyond, the law loses its shape and becomes a
    constant scale of the heat input, which is what ``heat_partition`` says (a fit could then
    name friction_speed for a partition error).
    """

    name: ClassVar[str] = "friction_speed"
    law: ClassVar[str] = "karwatzki"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "level": (0.7, 1.4),
        "speed_scale_kmh": (60.0, 160.0),
        "force_scale_kn": (0.5 * KARWATZKI_FORCE_SCALE_KN, 2.0 * KARWATZKI_FORCE_SCALE_KN),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "level": (0.1, 4.0),
        "speed_scale_kmh": (30.0, 300.0),
        "force_scale_kn": (0.3 * KARWATZKI_FORCE_SCALE_KN, 3.0 * KARWATZKI_FORCE_SCALE_KN),
    }

    level: float = 1.0
    speed_scale_kmh: float = 100.0
    force_scale_kn: float = KARWATZKI_FORCE_SCALE_KN

    def mu(self, speed_kmh: FloatArray, block_force_n: FloatArray) -> FloatArray:
        """The friction coefficient at each sample."""
        v = np.maximum(np.asarray(speed_kmh, dtype=np.float64), 0.0)
        k = np.maximum(np.asarray(block_force_n, dtype=np.float64), 0.0) / 1000.0
        force = (16.0 * k + self.force_scale_kn) / (80.0 * k + self.force_scale_kn)
        speed = (v + self.speed_scale_kmh) / (5.0 * v + self.speed_scale_kmh)
        return self.level * KARWATZKI_LEVEL * force * speed

    def friction_factor(
        self, speed_kmh: FloatArray, block_force_n: FloatArray, friction_coefficient: float
    ) -> FloatArray:
        """mu / mu_registry at each sample."""
        return self.mu(speed_kmh, block_force_n) / friction_coefficient

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        mu0 = inputs.friction_coefficient
        if mu0 is None or not mu0 > 0:
            raise ValueError(
                "friction_speed (karwatzki) needs the registry's friction coefficient in the "
                f"drive inputs, got {mu0!r}"
            )
        factor = self.friction_factor(inputs.speed_kmh, inputs.block_force_n, mu0)
        return inputs.replace(flux_w_m2=inputs.flux_w_m2 * factor)


@dataclass(frozen=True)
class FrictionSpeedNormalised(Effect):
    """Legacy (revisions stored before the laws): Karwatzki's speed shape normalised to the
    registry's mu at a reference speed and force, ``mu = mu_registry k(v) / k(v_ref)
    (F_eff / F_ref)^-force_exponent``, ``k(v) = (v + v_s) / (5 v + v_s)``. It cannot follow
    the law's level (why :class:`FrictionSpeed` replaced it); read and simulated, never
    tried. Free parameters: ``speed_scale_kmh``, ``force_exponent``."""

    name: ClassVar[str] = "friction_speed"
    law: ClassVar[str] = "normalised"
    candidate: ClassVar[bool] = False
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "speed_scale_kmh": (60.0, 250.0),
        "force_exponent": (0.0, 0.4),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "speed_scale_kmh": (1.0, 1.0e4),
        "force_exponent": (-1.0, 0.9),
    }
    REFERENCE_SPEED_KMH: ClassVar[float] = 60.0
    REFERENCE_FORCE_N: ClassVar[float] = 1500.0
    MIN_FORCE_N: ClassVar[float] = 100.0

    speed_scale_kmh: float = 100.0
    force_exponent: float = 0.2

    def _k(self, speed_kmh: FloatArray) -> FloatArray:
        v = np.maximum(speed_kmh, 0.0)
        return (v + self.speed_scale_kmh) / (5.0 * v + self.speed_scale_kmh)

    def friction_factor(self, speed_kmh: FloatArray, block_force_n: FloatArray) -> FloatArray:
        """mu / mu_registry at each sample."""
        speed = np.asarray(speed_kmh, dtype=np.float64)
        force = np.maximum(np.asarray(block_force_n, dtype=np.float64), self.MIN_FORCE_N)
        k_ref = float(self._k(np.asarray(self.REFERENCE_SPEED_KMH)))
        return self._k(speed) / k_ref * (force / self.REFERENCE_FORCE_N) ** -self.force_exponent

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        factor = self.friction_factor(inputs.speed_kmh, inputs.block_force_n)
        return inputs.replace(flux_w_m2=inputs.flux_w_m2 * factor)


@dataclass(frozen=True)
class FrictionTemperature(Effect):
    """Friction fade with temperature, the linear form of the brake literature:
    ``mu = mu_registry (1 - c (T_face - T_ref))``, clipped to [``MIN_FACTOR``,
    ``MAX_FACTOR``] of the registry's, with T_face the friction-face mean temperature and
    T_ref = ``REFERENCE_C`` (the first-order expansion of measured fade curves; cast iron
    loses friction as the contact heats; the temperature sensitivity of friction pairs in
    e.g. Day, *Braking of Road Vehicles*, 2014). Acts on the heat input and depends on the
    block's state: the simulation solves it by fixed-point iteration. Free parameter:
    ``fade_per_k`` (c), admissible from 0 up (``LIMITS``): a fade; a friction that grows as
    the contact heats is not this law, and a fit that wants c < 0 is following some other
    misfit (one that comes with the hour of day, say) through the face temperature.
    """

    name: ClassVar[str] = "friction_temperature"
    law: ClassVar[str] = "linear"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "fade_per_k": (5.0e-4, 2.5e-3),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "fade_per_k": (0.0, 0.01),
    }
    state_dependent: ClassVar[bool] = True
    REFERENCE_C: ClassVar[float] = 20.0
    MIN_FACTOR: ClassVar[float] = 0.3
    MAX_FACTOR: ClassVar[float] = 1.2

    fade_per_k: float = 1.0e-3

    def friction_factor(self, contact_c: FloatArray) -> FloatArray:
        """mu / mu_registry at each sample, from the friction-face temperature."""
        factor = 1.0 - self.fade_per_k * (np.asarray(contact_c) - self.REFERENCE_C)
        return np.clip(factor, self.MIN_FACTOR, self.MAX_FACTOR)

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        if inputs.contact_c is None:
            return inputs
        factor = self.friction_factor(inputs.contact_c)
        return inputs.replace(flux_w_m2=inputs.flux_w_m2 * factor)


@dataclass(frozen=True)
class HeatPartitionEffusivity(Effect):
    """Charron's partition of the friction heat by effusivity, with a contact factor:

    ``alpha = b_w S_w / (b_w S_w + c b_s S_s)``, ``b = sqrt(k rho c_p)``

    (F. Charron, *Partage de la chaleur entre deux corps frottants*, Publ. Sci. Tech.
    Ministère de l'Air 182, 1943; the form of the paper's eqs. 9-12, with S_w the wheel's
    swept tread and S_s the blocks' faces). The contact factor ``c`` scales the block's
    side: the fraction of the nominal face that carries the contact, and a contact
    resistance of its surface layer; ``c = 1`` is the declared model. Only the declared
    alpha is needed: with ``r = b_w S_w / (b_s S_s) = alpha_d / (1 - alpha_d)``,
    ``alpha = r / (r + c)`` and the flux into the block scales by ``c (r + 1) / (r + c)``.
    Free parameter: ``contact_factor``. (:class:`HeatPartition` is the same family with
    alpha itself as the parameter; this one is tried because its parameter is the physical
    unknown and its range does not depend on the block.)
    """

    name: ClassVar[str] = "heat_partition"
    law: ClassVar[str] = "effusivity"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "contact_factor": (0.3, 2.0),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "contact_factor": (1.0e-3, 100.0),
    }

    contact_factor: float = 1.0

    def alpha(self, alpha_declared: float) -> float:
        """The wheel's share with this contact factor."""
        r = alpha_declared / (1.0 - alpha_declared)
        return r / (r + self.contact_factor)

    def flux_factor(self, alpha_declared: float) -> float:
        return (1.0 - self.alpha(alpha_declared)) / (1.0 - alpha_declared)

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        return inputs.replace(flux_w_m2=inputs.flux_w_m2 * self.flux_factor(inputs.alpha))


@dataclass(frozen=True)
class HeatPartition(Effect):
    """The wheel takes ``alpha`` of the friction heat instead of the declared alpha of
    eqs. 9-12 (0.7455 for the reference block): the flux into the block is scaled by
    ``(1 - alpha) / (1 - alpha_declared)``. The same family as
    :class:`HeatPartitionEffusivity` (one-to-one: ``alpha = r / (r + c)``), kept for the
    revisions stored with it and for callers that think in alpha; not tried by the close
    loop (the two would be the same candidate twice). Free parameter: ``alpha``."""

    name: ClassVar[str] = "heat_partition"
    law: ClassVar[str] = "alpha"
    candidate: ClassVar[bool] = False
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {"alpha": (0.6, 0.9)}
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {"alpha": (0.0, 0.999)}

    alpha: float = 0.8

    def flux_factor(self, alpha_declared: float) -> float:
        return (1.0 - self.alpha) / (1.0 - alpha_declared)

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        return inputs.replace(flux_w_m2=inputs.flux_w_m2 * self.flux_factor(inputs.alpha))
