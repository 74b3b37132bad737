"""Effects acting together: :class:`EffectSet` (each vocabulary name at most once, applied in
:data:`~fleetbrake.model.effects.registry.EFFECT_CLASSES` order, stored as JSON)."""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fleetbrake.model.effects.base import DriveInputs, Effect, FloatArray
from fleetbrake.model.effects.registry import EFFECT_CLASSES, effect_from_dict

__all__ = ["EffectSet"]


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
