"""What every effect is: :class:`Effect` (parameters checked against their limits, the hooks
it acts through, its text and dict forms) and :class:`DriveInputs` (the loading an effect
changes). The vocabulary and its laws: :mod:`fleetbrake.model.effects`."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

__all__ = ["FAMILY_LAWS", "DriveInputs", "Effect", "FloatArray", "law_for_parameters"]


FloatArray = NDArray[np.float64]


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


def _check_number(owner: str, name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{owner}.{name} must be a finite number, got {value!r}")
    return float(value)


FAMILY_LAWS: dict[str, list[type[Effect]]] = {}
"""Each vocabulary name's laws, in the order their classes are defined (a family's laws side by
side in its module, in :data:`~fleetbrake.model.effects.registry.EFFECT_CLASSES` order):
what :meth:`Effect.__str__` infers a law from, without the registry."""


def law_for_parameters(laws: Sequence[type[Effect]], parameters: Iterable[str]) -> type[Effect]:
    """The first of a family's ``laws`` whose parameters include every name given (the
    family's first law when none does: ``from_parameters`` then names the unknown ones)."""
    given = set(parameters)
    for cls in laws:
        if given <= set(cls.parameter_names()):
            return cls
    return laws[0]


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
    """False for a law that is read and simulated but not tried by the close loop (a law kept
    for the revisions stored with it, or one the chain simulation cannot carry)."""

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

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        FAMILY_LAWS.setdefault(cls.name, []).append(cls)

    def __str__(self) -> str:
        # the law only where its parameter names do not say it (parse_effect's inference)
        laws = FAMILY_LAWS[self.name]
        inferred = law_for_parameters(laws, self.parameters) is type(self)
        items = [] if inferred else [f"law={self.law}"]
        items += [f"{k}={v!r}" for k, v in self.parameters.items()]
        return f"{self.name}:{','.join(items)}" if items else self.name
