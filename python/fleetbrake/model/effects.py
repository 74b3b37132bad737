"""The physical effects the declared model lacks (the vocabulary of ``shared/spec/interface.md``).

Each effect is a small frozen dataclass: its parameters (SI, the unit in the name), its
``name`` in the vocabulary, the *law* it follows (``law``: a family may hold more than one
law under one vocabulary name), the physical ranges its parameters may take
(``PARAMETER_RANGES``: what a test, the synthetic fleet or a fit's starting point draws
from), what is admissible at all (``LIMITS``), and a method that acts *where the effect acts
physically*:

========================  ===============  ========================================  ===============
effect                    law              what it changes                           where it acts
========================  ===============  ========================================  ===============
``friction_speed``        ``karwatzki``    mu(v, F) of cast iron, with its level     heat input
``friction_temperature``  ``linear``       mu fades with the face temperature        heat input (T)
``heat_partition``        ``effusivity``   Charron partition, contact factor         heat input
``convection_speed``      ``power``        h(v) = h0 (1 + a (v / v_ref)^b)           convection
``convection_speed``      ``flat_plate``   h0 + m h(Re, Pr): the block as a plate    convection
``holder_conduction``     ``conductance``  conductance into the holder (back, lug)   convection
``ambient_offset``        ``offset``       air around the block off ambient          ambient
``sensor_lag``            ``first_order``  thermistor lags its seat                  sensor output
``empirical``             ``linear``       a linear correction, tried last           heat input, h
========================  ===============  ========================================  ===============

Laws kept to read what was stored before them (``candidate = False``: parsed and simulated,
never tried by the close loop):
``friction_speed``/``normalised`` (mu normalised to the registry's), ``heat_partition``/
``alpha`` (the wheel's share itself: the same family as ``effusivity``, reparametrised).
``sensor_lag``/``two_stage`` (seat contact, then the thermistor's body) acts in
:func:`~fleetbrake.model.timeline.simulate_timeline` and in the synthetic generator, but the
chain simulation carries one lag state, so it is not a close-loop candidate yet
(``candidate = False``) and the chain simulation refuses it rather than drop it.

A law is written ``{"name": ..., "law": ..., "parameters": {...}}`` (:meth:`Effect.to_dict`);
a stored set without ``law`` (written before the laws) is read by its parameter names
(:func:`effect_from_dict`): ``friction_speed`` with ``force_exponent`` is the normalised law,
``heat_partition`` with ``alpha`` the plain alpha, and so on.

Usage::

    from fleetbrake.model.effects import ConvectionSpeed, EffectSet, SensorLag, parse_effect

    effects = EffectSet((ConvectionSpeed(gain=2.0, exponent=0.8), SensorLag(tau_s=40.0)))
    text = effects.to_json()                       # '[{"law": "power", "name": ...}, ...]'
    assert EffectSet.from_json(text) == effects
    parse_effect("sensor_lag:tau_s=30")            # the command line's NAME[:k=v,...]
    parse_effect("convection_speed:law=flat_plate,multiplier=0.5")
    SensorLag.random(rng)                          # parameters drawn from PARAMETER_RANGES

The simulation (``fleetbrake.model.timeline.simulate_timeline``) builds :class:`DriveInputs` at
the sample instants (1 Hz), lets :meth:`EffectSet.apply_to_inputs` change them, integrates
the reduced model, and passes its sensor output through :meth:`EffectSet.apply_to_sensor`.
Effects are applied in the fixed order of :data:`EFFECT_CLASSES` whatever order a set was
given in, so that a set means one thing. A set holds each vocabulary name at most once.

:data:`EFFECT_ORDER` is what the close loop tries (every candidate law, ``empirical`` last,
marked ``fallback``: tried only when no physical effect is adequate); :data:`EFFECTS` maps a
vocabulary name to its first law; :data:`LAWS` a name to all its laws.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from fleetbrake.model.rom import first_order_lag

__all__ = [
    "EFFECTS",
    "EFFECT_CLASSES",
    "EFFECT_ORDER",
    "LAWS",
    "AmbientOffset",
    "ConvectionFlatPlate",
    "ConvectionSpeed",
    "DriveInputs",
    "Effect",
    "EffectSet",
    "Empirical",
    "FrictionSpeed",
    "FrictionSpeedNormalised",
    "FrictionTemperature",
    "HeatPartition",
    "HeatPartitionEffusivity",
    "HolderConduction",
    "SensorLag",
    "SensorLagTwoStage",
    "effect_from_dict",
    "find_law",
    "parse_effect",
]

FloatArray = NDArray[np.float64]

# --------------------------------------------------------------------------------------------
# What the effects act on


@dataclass(frozen=True)
class DriveInputs:
    """The loading of one simulation at the sample instants ``t_k = k dt`` (k = 0 .. N-1).

    The simulation turns these into per-step inputs (the mean of the two samples bounding
    each step), so an effect need not know about steps.
    """

    dt_s: float
    speed_kmh: FloatArray
    """Train speed (N)."""
    block_force_n: FloatArray
    """Normal force of one block on the wheel (N), anomalies included."""
    flux_w_m2: FloatArray
    """Heat flux into the block's friction face (N), W/m^2: (1 - alpha) mu F v / A_contact."""
    alpha: float
    """The declared heat partition (eqs. 9-12): the wheel's share of the friction heat."""
    ambient_c: FloatArray
    """Air temperature around the block (N)."""
    h_w_m2k: Mapping[str, FloatArray]
    """Convection coefficient per face set of the reduced model (each N)."""
    contact_c: FloatArray | None = None
    """Friction-face mean temperature (N) of the previous iteration, for state-dependent
    effects; None before the first simulation."""
    friction_coefficient: float | None = None
    """The registry's mu that ``flux_w_m2`` was computed with (a law that gives mu itself,
    such as Karwatzki's, replaces it); None where the builder did not say."""

    def replace(self, **changes: Any) -> DriveInputs:
        return dataclasses.replace(self, **changes)


# --------------------------------------------------------------------------------------------
# The effects


def _check_number(owner: str, name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{owner}.{name} must be a finite number, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Effect:
    """Base of every effect: parameters as dataclass fields, checked against their limits.

    Subclasses set ``name`` (the vocabulary), ``law`` (which of the family's laws),
    ``PARAMETER_RANGES`` (physical ranges to draw from: every parameter is free) and
    ``LIMITS`` (what is admissible at all, wider; ``None`` = unbounded), and override the
    hooks they act through.
    """

    name: ClassVar[str] = ""
    law: ClassVar[str] = ""
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {}
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {}
    state_dependent: ClassVar[bool] = False
    """True when the effect needs the block's own temperature (solved by fixed point)."""
    fallback: ClassVar[bool] = False
    """True for a data-driven correction (``empirical``): the close loop tries it last, only
    when no physical effect leaves an adequate fit; the synthetic generator never draws it."""
    candidate: ClassVar[bool] = True
    """False for a law that is read and simulated but not tried by the close loop (legacy
    parameter sets, or a law the chain simulation cannot carry yet)."""

    def __post_init__(self) -> None:
        owner = type(self).__name__
        for f in fields(self):
            value = _check_number(owner, f.name, getattr(self, f.name))
            low, high = self.LIMITS.get(f.name, (None, None))
            if (low is not None and value < low) or (high is not None and value > high):
                raise ValueError(f"{owner}.{f.name} must be in [{low}, {high}], got {value!r}")
            object.__setattr__(self, f.name, value)

    # ---------------------------------------------------------------- parameters
    @property
    def parameters(self) -> dict[str, float]:
        """The parameters by name (SI, unit in the name)."""
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def parameter_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

    def to_dict(self) -> dict[str, Any]:
        """``{"name": ..., "law": ..., "parameters": {...}}``, JSON-serialisable."""
        return {"name": self.name, "law": self.law, "parameters": self.parameters}

    @classmethod
    def from_parameters(cls, parameters: Mapping[str, float]) -> Effect:
        """The effect with these parameters (missing ones take the defaults); unknown names
        are an error."""
        known = set(cls.parameter_names())
        unknown = set(parameters) - known
        if unknown:
            raise ValueError(
                f"{cls.name} ({cls.law}): unknown parameter(s) {sorted(unknown)}; "
                f"known: {sorted(known)}"
            )
        return cls(**dict(parameters))

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        """Parameters drawn uniformly from ``PARAMETER_RANGES``."""
        drawn = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in cls.PARAMETER_RANGES.items()}
        return cls(**drawn)

    def with_parameters(self, **changes: float) -> Effect:
        return dataclasses.replace(self, **changes)

    # ---------------------------------------------------------------- hooks
    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        """The loading as this effect changes it (default: unchanged)."""
        return inputs

    def apply_to_sensor(self, sensor_c: FloatArray, dt_s: float) -> FloatArray:
        """The sensor reading as this effect changes it (default: unchanged)."""
        return sensor_c

    def __str__(self) -> str:
        # the law only where its parameter names do not say it (parse_effect's inference)
        inferred = find_law(self.name, None, self.parameters) is type(self)
        items = [] if inferred else [f"law={self.law}"]
        items += [f"{k}={v!r}" for k, v in self.parameters.items()]
        return f"{self.name}:{','.join(items)}" if items else self.name


# ---------------------------------------------------------------- friction_speed


KARWATZKI_LEVEL = 0.6
"""The constant of Karwatzki's law for cast-iron blocks (mu at rest under a vanishing force)."""


@dataclass(frozen=True)
class FrictionSpeed(Effect):
    """Karwatzki's law for cast-iron (P10) brake blocks, with its level:

    ``mu(v, F) = level 0.6 (16 K + K_s) / (80 K + K_s) (v + v_s) / (5 v + v_s)``

    with K the block's normal force in kN, v the speed in km/h, and the literature's
    constants K_s = 100 kN and v_s = 100 km/h (Karwatzki's formula for grey cast-iron blocks
    as the railway braking literature quotes it, e.g. Wende, *Fahrdynamik des
    Schienenverkehrs*, Teubner 2003; the same speed and block-pressure dependence is
    discussed by Koffman, "Adhesion and friction in rail traction", J. Inst. Locomotive
    Engineers 38, 1948). The coefficient is the law's own, NOT normalised to the registry's
    mu: the friction power is ``mu(v, F) F v``, so the flux built with the registry's mu is
    scaled by ``mu(v, F) / mu_registry`` (``DriveInputs.friction_coefficient``).

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
        "force_scale_kn": (50.0, 200.0),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "level": (0.1, 4.0),
        "speed_scale_kmh": (30.0, 300.0),
        "force_scale_kn": (30.0, 300.0),
    }

    level: float = 1.0
    speed_scale_kmh: float = 100.0
    force_scale_kn: float = 100.0

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


# ---------------------------------------------------------------- friction_temperature


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


# ---------------------------------------------------------------- heat_partition


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


# ---------------------------------------------------------------- convection_speed


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


# ---------------------------------------------------------------- holder_conduction


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


# ---------------------------------------------------------------- ambient_offset


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


# ---------------------------------------------------------------- sensor_lag


@dataclass(frozen=True)
class SensorLag(Effect):
    """The thermistor lags the block temperature at its seat (contact resistance of the
    seat): a first-order lag ``tau y' = x - y`` with time constant ``tau_s`` on the sensor
    output (the response of a lumped sensor, e.g. Doebelin, *Measurement Systems*, ch. 3).
    Free parameter: ``tau_s``."""

    name: ClassVar[str] = "sensor_lag"
    law: ClassVar[str] = "first_order"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {"tau_s": (15.0, 120.0)}
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {"tau_s": (0.0, 3600.0)}

    tau_s: float = 40.0

    def apply_to_sensor(self, sensor_c: FloatArray, dt_s: float) -> FloatArray:
        return first_order_lag(np.asarray(sensor_c, dtype=np.float64), dt_s, self.tau_s)


@dataclass(frozen=True)
class SensorLagTwoStage(Effect):
    """Two lags in series: the seat's contact resistance (``tau_contact_s``) brings the heat
    to the thermistor's body, whose own capacity lags it again (``tau_body_s``), the
    two-time-constant model of a sheathed sensor in a seat (Doebelin, *Measurement Systems*,
    ch. 3: second-order, overdamped). Free parameters: ``tau_contact_s``, ``tau_body_s``.

    Simulated by :func:`~fleetbrake.model.timeline.simulate_timeline` and the synthetic
    generator; the chain simulation (``fleetbrake.simulation``) carries one lag state, so
    this law is not a close-loop candidate, and asking the chain for its single ``tau_s``
    is an error rather than a silently dropped lag."""

    name: ClassVar[str] = "sensor_lag"
    law: ClassVar[str] = "two_stage"
    candidate: ClassVar[bool] = False
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "tau_contact_s": (15.0, 90.0),
        "tau_body_s": (5.0, 40.0),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "tau_contact_s": (0.0, 3600.0),
        "tau_body_s": (0.0, 3600.0),
    }

    tau_contact_s: float = 40.0
    tau_body_s: float = 10.0

    @property
    def tau_s(self) -> float:
        raise ValueError(
            "sensor_lag (two_stage) has two time constants; the chain simulation carries "
            "one lag state and cannot simulate it"
        )

    def apply_to_sensor(self, sensor_c: FloatArray, dt_s: float) -> FloatArray:
        x = np.asarray(sensor_c, dtype=np.float64)
        return first_order_lag(first_order_lag(x, dt_s, self.tau_contact_s), dt_s, self.tau_body_s)


# ---------------------------------------------------------------- empirical


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


# ---------------------------------------------------------------- the registry of laws


EFFECT_CLASSES: tuple[type[Effect], ...] = (
    FrictionSpeed,
    FrictionSpeedNormalised,
    FrictionTemperature,
    HeatPartitionEffusivity,
    HeatPartition,
    ConvectionSpeed,
    ConvectionFlatPlate,
    HolderConduction,
    AmbientOffset,
    SensorLag,
    SensorLagTwoStage,
    Empirical,
)
"""Every law, in the order a set applies them (a family's laws side by side; ``empirical``,
a correction on top of everything, last)."""

EFFECT_ORDER: tuple[type[Effect], ...] = tuple(cls for cls in EFFECT_CLASSES if cls.candidate)
"""The laws the close loop tries, in order (``empirical``, ``fallback``, last)."""

LAWS: Mapping[str, tuple[type[Effect], ...]] = {
    name: tuple(cls for cls in EFFECT_CLASSES if cls.name == name)
    for name in dict.fromkeys(cls.name for cls in EFFECT_CLASSES)
}
"""Every law of each vocabulary name, the first one the family's default."""

EFFECTS: Mapping[str, type[Effect]] = {name: laws[0] for name, laws in LAWS.items()}
"""The default law of each vocabulary name (the whole vocabulary, ``empirical`` included)."""


def find_law(name: str, law: str | None = None, parameters: Iterable[str] = ()) -> type[Effect]:
    """The class of ``name``'s law ``law``; without a law (a set stored before the laws, or
    the command line), the first law whose parameters include every name given."""
    if name not in LAWS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(LAWS)}")
    laws = LAWS[name]
    if law is not None:
        for cls in laws:
            if cls.law == law:
                return cls
        raise ValueError(
            f"{name}: unknown law {law!r}; known: {', '.join(cls.law for cls in laws)}"
        )
    given = set(parameters)
    for cls in laws:
        if given <= set(cls.parameter_names()):
            return cls
    return laws[0]  # from_parameters names the unknown parameters


def effect_from_dict(data: Mapping[str, Any]) -> Effect:
    """The inverse of :meth:`Effect.to_dict` (also reads sets stored before the laws)."""
    name = data.get("name")
    if not isinstance(name, str) or name not in LAWS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(LAWS)}")
    parameters = data.get("parameters", {})
    if not isinstance(parameters, Mapping):
        raise ValueError(f"{name}: parameters must be a mapping, got {parameters!r}")
    law = data.get("law")
    if law is not None and not isinstance(law, str):
        raise ValueError(f"{name}: law must be a string, got {law!r}")
    return find_law(name, law, parameters).from_parameters(parameters)


def parse_effect(text: str) -> Effect:
    """An effect from the command line's ``NAME[:law=LAW,key=value,...]`` (defaults for the
    rest; without ``law``, the law whose parameters are the ones given)."""
    name, _, rest = text.strip().partition(":")
    name = name.strip()
    if name not in LAWS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(LAWS)}")
    parameters: dict[str, float] = {}
    law: str | None = None
    for item in filter(None, (part.strip() for part in rest.split(","))):
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"{text!r}: expected key=value, got {item!r}")
        if key.strip() == "law":
            law = value.strip()
            continue
        try:
            parameters[key.strip()] = float(value)
        except ValueError:
            raise ValueError(f"{text!r}: {key.strip()} must be a number, got {value!r}") from None
    return find_law(name, law, parameters).from_parameters(parameters)


# --------------------------------------------------------------------------------------------
# A set of effects


@dataclass(frozen=True)
class EffectSet:
    """Effects acting together (each vocabulary name at most once, in one of its laws), applied
    in :data:`EFFECT_CLASSES` order."""

    effects: tuple[Effect, ...] = field(default=())

    def __post_init__(self) -> None:
        effects = tuple(self.effects)
        for effect in effects:
            if not isinstance(effect, Effect) or type(effect) not in EFFECT_CLASSES:
                raise TypeError(f"EffectSet: not an effect: {effect!r}")
        names = [e.name for e in effects]
        doubled = sorted({n for n in names if names.count(n) > 1})
        if doubled:
            raise ValueError(f"EffectSet: each effect at most once, got {doubled} twice")
        rank = {cls: i for i, cls in enumerate(EFFECT_CLASSES)}
        object.__setattr__(self, "effects", tuple(sorted(effects, key=lambda e: rank[type(e)])))

    def __iter__(self) -> Iterator[Effect]:
        return iter(self.effects)

    def __len__(self) -> int:
        return len(self.effects)

    def __bool__(self) -> bool:
        return bool(self.effects)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects)

    @property
    def state_dependent(self) -> bool:
        """Whether the set needs the fixed-point iteration (an effect depends on the state)."""
        return any(e.state_dependent for e in self.effects)

    def get(self, name: str) -> Effect | None:
        return next((e for e in self.effects if e.name == name), None)

    def with_effect(self, effect: Effect) -> EffectSet:
        """This set with ``effect`` added, or replacing the one of the same name."""
        return EffectSet((*(e for e in self.effects if e.name != effect.name), effect))

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        for effect in self.effects:
            inputs = effect.apply_to_inputs(inputs)
        return inputs

    def apply_to_sensor(self, sensor_c: FloatArray, dt_s: float) -> FloatArray:
        out = np.asarray(sensor_c, dtype=np.float64)
        for effect in self.effects:
            out = effect.apply_to_sensor(out, dt_s)
        return out

    # ---------------------------------------------------------------- serialisation
    def to_list(self) -> list[dict[str, Any]]:
        return [e.to_dict() for e in self.effects]

    @classmethod
    def from_list(cls, items: Iterable[Mapping[str, Any]]) -> EffectSet:
        return cls(tuple(effect_from_dict(item) for item in items))

    def to_json(self) -> str:
        return json.dumps(self.to_list(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> EffectSet:
        data = json.loads(text)
        if not isinstance(data, list):
            raise ValueError("an effect set in JSON is a list of {name, law, parameters}")
        return cls.from_list(data)

    def __str__(self) -> str:
        return " + ".join(str(e) for e in self.effects) or "declared"
