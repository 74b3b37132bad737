"""The physical effects the declared model lacks (the vocabulary of ``shared/spec/interface.md``).

Each effect is a small frozen dataclass: its parameters (SI, the unit in the name), its
``name`` in the vocabulary, the physical ranges its parameters may take
(``PARAMETER_RANGES``: what a test or the synthetic fleet may draw from at random), and a
method that acts *where the effect acts physically*:

==========================  ===================================  ==============================
effect                      what it changes                      where it acts
==========================  ===================================  ==============================
``friction_speed``          mu(v, F), Karwatzki-type              heat input (flux)
``friction_temperature``    mu fades with the friction-face T     heat input, state-dependent
``heat_partition``          the block's share 1 - alpha           heat input
``convection_speed``        h(v) = h0 (1 + a (v / v_ref)^b)       convection ("air", "holder")
``holder_conduction``       extra conductance into the holder     convection ("holder")
``ambient_offset``          air around the block off ambient      ambient
``sensor_lag``              thermistor lags its seat              sensor output
==========================  ===================================  ==============================

Usage::

    from fleetbrake.model.effects import ConvectionSpeed, EffectSet, SensorLag, parse_effect

    effects = EffectSet((ConvectionSpeed(gain=2.0, exponent=0.8), SensorLag(tau_s=40.0)))
    text = effects.to_json()                       # '[{"name": "convection_speed", ...}]'
    assert EffectSet.from_json(text) == effects
    parse_effect("sensor_lag:tau_s=30")            # the command line's NAME[:k=v,...]
    SensorLag.random(rng)                          # parameters drawn from PARAMETER_RANGES

The simulation (``fleetbrake.model.timeline.simulate_timeline``) builds :class:`DriveInputs` at
the sample instants (1 Hz), lets :meth:`EffectSet.apply_to_inputs` change them, integrates
the reduced model, and passes its sensor output through :meth:`EffectSet.apply_to_sensor`.
Effects are applied in the fixed order of :data:`EFFECT_ORDER` whatever order a set was
given in, so that a set means one thing. A set holds each effect at most once.
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
    "EFFECT_ORDER",
    "AmbientOffset",
    "ConvectionSpeed",
    "DriveInputs",
    "Effect",
    "EffectSet",
    "FrictionSpeed",
    "FrictionTemperature",
    "HeatPartition",
    "HolderConduction",
    "SensorLag",
    "effect_from_dict",
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

    Subclasses set ``name`` (the vocabulary), ``PARAMETER_RANGES`` (physical ranges to draw
    from) and ``LIMITS`` (what is admissible at all, wider; ``None`` = unbounded), and
    override the hooks they act through.
    """

    name: ClassVar[str] = ""
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {}
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {}
    state_dependent: ClassVar[bool] = False
    """True when the effect needs the block's own temperature (solved by fixed point)."""

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

    def to_dict(self) -> dict[str, Any]:
        """``{"name": ..., "parameters": {...}}``, JSON-serialisable."""
        return {"name": self.name, "parameters": self.parameters}

    @classmethod
    def from_parameters(cls, parameters: Mapping[str, float]) -> Effect:
        """The effect with these parameters (missing ones take the defaults); unknown names
        are an error."""
        known = {f.name for f in fields(cls)}
        unknown = set(parameters) - known
        if unknown:
            raise ValueError(
                f"{cls.name}: unknown parameter(s) {sorted(unknown)}; known: {sorted(known)}"
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
        shown = ",".join(f"{k}={v!r}" for k, v in self.parameters.items())
        return f"{self.name}:{shown}" if shown else self.name


@dataclass(frozen=True)
class FrictionSpeed(Effect):
    """Karwatzki-type friction of cast iron: mu depends on speed and on the block force.

    ``mu(v, F) = mu_registry k(v) / k(v_ref) (F_eff / F_ref)^-force_exponent`` with
    ``k(v) = (v + v_s) / (5 v + v_s)`` (Karwatzki: v_s = 100 km/h, mu falls from 1 at rest to
    about 1/5 at high speed) and ``F_eff = max(F, F_min)``. Normalised so that mu equals the
    registry's at the reference speed and force (``REFERENCE_SPEED_KMH``,
    ``REFERENCE_FORCE_N``: a mid service braking). A larger ``speed_scale_kmh`` makes mu
    depend less on speed. Acts on the heat input: the friction power is mu F v.
    """

    name: ClassVar[str] = "friction_speed"
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
    """Friction fade: ``mu = mu_registry (1 - c (T_face - T_ref))``, clipped to
    [``MIN_FACTOR``, ``MAX_FACTOR``] of the registry's, with T_face the friction-face mean
    temperature and T_ref = ``REFERENCE_C``. Acts on the heat input and depends on the
    block's state: the simulation solves it by fixed-point iteration.
    """

    name: ClassVar[str] = "friction_temperature"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "fade_per_k": (5.0e-4, 2.5e-3),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "fade_per_k": (-0.01, 0.01),
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
class HeatPartition(Effect):
    """The wheel takes ``alpha`` of the friction heat instead of the declared alpha of
    eqs. 9-12 (0.7455 for the reference block): the flux into the block is scaled by
    ``(1 - alpha) / (1 - alpha_declared)``."""

    name: ClassVar[str] = "heat_partition"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {"alpha": (0.6, 0.9)}
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {"alpha": (0.0, 0.999)}

    alpha: float = 0.8

    def flux_factor(self, alpha_declared: float) -> float:
        return (1.0 - self.alpha) / (1.0 - alpha_declared)

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        return inputs.replace(flux_w_m2=inputs.flux_w_m2 * self.flux_factor(inputs.alpha))


@dataclass(frozen=True)
class ConvectionSpeed(Effect):
    """Forced convection: ``h(v) = h0 (1 + gain (v / v_ref)^exponent)`` on the face sets of
    ``FACES`` (every surface but the friction face), ``v_ref = REFERENCE_SPEED_KMH``."""

    name: ClassVar[str] = "convection_speed"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "gain": (0.8, 4.0),
        "exponent": (0.6, 1.0),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "gain": (0.0, 50.0),
        "exponent": (0.1, 2.0),
    }
    FACES: ClassVar[tuple[str, ...]] = ("air", "holder")
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
class HolderConduction(Effect):
    """Heat leaves through the back face and the lug into the holder (held at ambient): an
    extra conductance ``h_holder_extra_w_m2k`` on the "holder" face set."""

    name: ClassVar[str] = "holder_conduction"
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
    shaded, wetted bogie)."""

    name: ClassVar[str] = "ambient_offset"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {"offset_k": (-4.0, 6.0)}
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {"offset_k": (-50.0, 50.0)}

    offset_k: float = 3.0

    def apply_to_inputs(self, inputs: DriveInputs) -> DriveInputs:
        return inputs.replace(ambient_c=inputs.ambient_c + self.offset_k)


@dataclass(frozen=True)
class SensorLag(Effect):
    """The thermistor lags the block temperature at its seat (contact resistance of the
    seat): a first-order lag with time constant ``tau_s`` on the sensor output."""

    name: ClassVar[str] = "sensor_lag"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {"tau_s": (15.0, 120.0)}
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {"tau_s": (0.0, 3600.0)}

    tau_s: float = 40.0

    def apply_to_sensor(self, sensor_c: FloatArray, dt_s: float) -> FloatArray:
        return first_order_lag(np.asarray(sensor_c, dtype=np.float64), dt_s, self.tau_s)


EFFECT_ORDER: tuple[type[Effect], ...] = (
    FrictionSpeed,
    FrictionTemperature,
    HeatPartition,
    ConvectionSpeed,
    HolderConduction,
    AmbientOffset,
    SensorLag,
)
"""Every effect, in the order a set applies them."""

EFFECTS: Mapping[str, type[Effect]] = {cls.name: cls for cls in EFFECT_ORDER}
"""Effect class by vocabulary name (``empirical`` is the fitter's, not here)."""


def effect_from_dict(data: Mapping[str, Any]) -> Effect:
    """The inverse of :meth:`Effect.to_dict`."""
    name = data.get("name")
    if not isinstance(name, str) or name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    parameters = data.get("parameters", {})
    if not isinstance(parameters, Mapping):
        raise ValueError(f"{name}: parameters must be a mapping, got {parameters!r}")
    return EFFECTS[name].from_parameters(parameters)


def parse_effect(text: str) -> Effect:
    """An effect from the command line's ``NAME[:key=value,...]`` (defaults for the rest)."""
    name, _, rest = text.strip().partition(":")
    name = name.strip()
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    parameters: dict[str, float] = {}
    for item in filter(None, (part.strip() for part in rest.split(","))):
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"{text!r}: expected key=value, got {item!r}")
        try:
            parameters[key.strip()] = float(value)
        except ValueError:
            raise ValueError(f"{text!r}: {key.strip()} must be a number, got {value!r}") from None
    return EFFECTS[name].from_parameters(parameters)


# --------------------------------------------------------------------------------------------
# A set of effects


@dataclass(frozen=True)
class EffectSet:
    """Effects acting together (each at most once), applied in :data:`EFFECT_ORDER`."""

    effects: tuple[Effect, ...] = field(default=())

    def __post_init__(self) -> None:
        effects = tuple(self.effects)
        for effect in effects:
            if not isinstance(effect, Effect) or type(effect) not in EFFECT_ORDER:
                raise TypeError(f"EffectSet: not an effect: {effect!r}")
        names = [e.name for e in effects]
        doubled = sorted({n for n in names if names.count(n) > 1})
        if doubled:
            raise ValueError(f"EffectSet: each effect at most once, got {doubled} twice")
        rank = {cls: i for i, cls in enumerate(EFFECT_ORDER)}
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
            raise ValueError("an effect set in JSON is a list of {name, parameters}")
        return cls.from_list(data)

    def __str__(self) -> str:
        return " + ".join(str(e) for e in self.effects) or "declared"
