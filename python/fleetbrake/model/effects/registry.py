"""The vocabulary's laws: every law in the order a set applies them (:data:`EFFECT_CLASSES`),
the ones the close loop tries (:data:`EFFECT_ORDER`), each name's laws (:data:`LAWS`) and
default law (:data:`EFFECTS`), and an effect read from a dict or the command line
(:func:`effect_from_dict`, :func:`parse_effect`)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from fleetbrake.model.effects.base import Effect, law_for_parameters
from fleetbrake.model.effects.convection import (
    AmbientOffset,
    ConvectionFlatPlate,
    ConvectionSpeed,
    HolderConduction,
)
from fleetbrake.model.effects.empirical import Empirical
from fleetbrake.model.effects.heat_input import (
    FrictionSpeed,
    FrictionSpeedNormalised,
    FrictionTemperature,
    HeatPartition,
    HeatPartitionEffusivity,
)
from fleetbrake.model.effects.sensor import SensorLag, SensorLagTwoStage

__all__ = [
    "EFFECTS",
    "EFFECT_CLASSES",
    "EFFECT_ORDER",
    "LAWS",
    "effect_from_dict",
    "find_law",
    "parse_effect",
]


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
    return law_for_parameters(laws, parameters)


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
