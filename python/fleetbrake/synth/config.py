"""What a synthetic fleet is made of: :class:`SynthConfig`, and the seeded random streams.

Every random choice of the generator is drawn from a stream of its own, seeded from the
configuration's ``seed`` and a fixed purpose code (and a wagon or file number): switching one
thing off (say, the anomalies) leaves every other draw as it was, and the same configuration
writes byte-identical files.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import numpy as np

from fleetbrake.model.effects import Effect, EffectSet, find_law
from fleetbrake.model.rom import DEFAULT_REFINEMENT

__all__ = [
    "SENSOR_FAULT_SUBTYPES",
    "SOLVERS",
    "Solver",
    "SynthConfig",
    "draw_effect",
    "drifting_parameter",
    "stream",
]

SENSOR_FAULT_SUBTYPES: tuple[str, ...] = ("open", "frozen", "loose", "drift")

Solver = Literal["rom", "full"]
"""What simulates the block: the reduced model, or the full finite-element model."""

SOLVERS: tuple[str, ...] = get_args(Solver)


@dataclass(frozen=True)
class SynthConfig:
    """What to generate. Rates are per row (fractions) or per file (probabilities).

    Read by: ``fleetbrake synth``, ``fleetbrake demo``, ``fleetbrake bench fleet``,
    ``fleetbrake bench close-loop``, ``fleetbrake bench watch``.
    """

    wagons: int = 4
    """Registered, well-formed wagons (the extra bad-registry wagons come on top)."""
    days: int = 2
    """UTC days of operation."""
    seed: int = 0
    """Seed of every random stream: the same configuration writes the same bytes."""
    start: dt.date = dt.date(2024, 3, 4)
    """First UTC day."""
    effects: EffectSet = field(default_factory=EffectSet)
    """Undeclared effects acting on every wagon."""
    anomalies: bool = True
    """Dragging brakes, weak brakes and sensor faults in some wagons."""
    gzip_fraction: float = 0.5
    """Share of the log files written gzipped."""
    ambient_sensor_fraction: float = 0.5
    """Share of the wagons whose logs carry ``ambient_temp_c``."""
    ambient_mean_c: float = 8.0
    """Mean air temperature of the period."""
    sensor_noise_k: float = 0.1
    """Standard deviation of the block sensor's Gaussian noise (the Pt1000's)."""
    pressure_noise_bar: float = 0.003
    """Standard deviation of the cylinder pressure's noise (before quantising to 7 mbar)."""
    speed_noise_kmh: float = 0.3
    """Standard deviation of the GPS speed's noise."""

    # imperfections of fleet-data.md
    missing_row_fraction: float = 0.001
    """Share of the rows dropped."""
    gap_probability: float = 0.15
    """Per file: one gap of 5-120 s."""
    duplicate_fraction: float = 0.0005
    """Share of the rows written twice."""
    swap_fraction: float = 0.0005
    """Share of the rows swapped with their neighbour."""
    empty_cell_fraction: float = 0.0002
    """Share of the cells left empty."""
    frozen_speed_probability: float = 0.1
    """Per file: GPS speed frozen for 20-120 s."""
    speed_jump_probability: float = 0.1
    """Per file: one or two GPS speed jumps of a few seconds."""
    gps_dropout_probability: float = 0.0
    """Per file: the fix lost for 30-180 s from a few seconds into a braking: speed empty,
    distance held, then jumping by what was covered when the fix returns."""
    truncated_files: int = 1
    """Plain CSV files cut mid-row (the unit lost power)."""
    truncated_gzip_files: int = 1
    """Gzip files cut mid-stream."""
    garbage_files: int = 1
    """Files that are not CSV at all (extra files, named as sessions)."""
    unregistered_wagon: bool = True
    """One more wagon with logs but no registry entry."""
    bad_registry_entry: bool = True
    """One more wagon with logs and a registry entry with a bad value."""
    odd_columns: bool = True
    """One wagon writes its columns in another order, with an extra unknown column."""

    solver: Solver = "rom"
    """What simulates the block: ``rom``, the reduced model (the one the pipeline predicts
    with), or ``full``, the finite-element model it is reduced from (``model.thermal``), so
    that a fleet is not made by the very model that is fitted to it. The full model costs
    about 35 us per simulated second at ``refinement`` 0.2 (409 nodes), 75 us at 0.3 and
    2 ms at 0.6: give it a coarse mesh."""
    refinement: float = DEFAULT_REFINEMENT
    """Mesh refinement of the model (1.0: the default mesh, about 21,000 nodes). The reduced
    and full models are meshed by the same code, so one value gives them one mesh."""
    solar_heating_w_m2: float = 0.0
    """An effect OUTSIDE the vocabulary, for testing that the close loop says "not adequate":
    sunshine absorbed by the block's air-cooled surfaces, peak W/m^2 at solar noon (12:00
    UTC), ``peak max(0, sin(pi (hour - 6) / 12))``: a heat input that depends on the hour of
    day. It enters as the sol-air temperature of those surfaces (``air + q / h0``, h0 the
    declared 10 W/m^2 K; ASHRAE Fundamentals, ch. 18), so the block sees a warmer air by
    day while the logged air temperature stays the air's. 0: none."""

    effect_drift_per_day: dict[str, float] = field(default_factory=dict)
    """Effects that drift over the calendar (a component that degrades, a property that
    changes): per parameter of ``effects`` (``parameter``, or ``effect.parameter`` where two
    effects share a name), its change per day from ``start``. The block is then simulated in
    segments (as the full model always is), each with the parameters of its first second; the
    effects on the sensor's output (``sensor_lag``) do not drift. {}: none."""

    def __post_init__(self) -> None:
        if isinstance(self.start, dt.datetime) or not isinstance(self.start, dt.date):
            raise ValueError(f"start must be a date, got {self.start!r}")
        if isinstance(self.effects, tuple | list):  # a plain sequence of effects
            object.__setattr__(self, "effects", EffectSet(tuple(self.effects)))
        for key, rate in self.effect_drift_per_day.items():
            drifting_parameter(self.effects, key)
            if not math.isfinite(rate):
                raise ValueError(f"effect_drift_per_day[{key!r}] must be finite, got {rate!r}")
        for name in ("wagons", "days"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.wagons > 9000:
            raise ValueError("at most 9000 wagons")
        for name in (
            "gzip_fraction",
            "ambient_sensor_fraction",
            "missing_row_fraction",
            "gap_probability",
            "duplicate_fraction",
            "swap_fraction",
            "empty_cell_fraction",
            "frozen_speed_probability",
            "speed_jump_probability",
            "gps_dropout_probability",
        ):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value!r}")
        for name in ("truncated_files", "truncated_gzip_files", "garbage_files"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")
        for name in ("sensor_noise_k", "pressure_noise_bar", "speed_noise_kmh"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if not self.refinement > 0:
            raise ValueError(f"refinement must be > 0, got {self.refinement!r}")
        if not 0.0 <= self.solar_heating_w_m2 <= 1500.0:
            raise ValueError(
                f"solar_heating_w_m2 must be in [0, 1500], got {self.solar_heating_w_m2!r}"
            )

    @classmethod
    def clean(cls, **changes: Any) -> SynthConfig:
        """No imperfection and no anomaly (``changes`` on top)."""
        base = {
            "anomalies": False,
            "missing_row_fraction": 0.0,
            "gap_probability": 0.0,
            "duplicate_fraction": 0.0,
            "swap_fraction": 0.0,
            "empty_cell_fraction": 0.0,
            "frozen_speed_probability": 0.0,
            "speed_jump_probability": 0.0,
            "gps_dropout_probability": 0.0,
            "truncated_files": 0,
            "truncated_gzip_files": 0,
            "garbage_files": 0,
            "unregistered_wagon": False,
            "bad_registry_entry": False,
            "odd_columns": False,
        }
        return cls(**{**base, **changes})

    def effects_on_day(self, days: float) -> EffectSet:
        """``effects`` with the drifting parameters as they are ``days`` after ``start``."""
        if not self.effect_drift_per_day:
            return self.effects
        moved = list(self.effects)
        for key, rate in self.effect_drift_per_day.items():
            index, name = drifting_parameter(self.effects, key)
            effect = moved[index]
            moved[index] = dataclasses.replace(
                effect, **{name: effect.parameters[name] + rate * days}
            )
        return EffectSet(tuple(moved))

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, EffectSet):
                value = value.to_list()
            elif isinstance(value, dt.date):
                value = value.isoformat()
            out[f.name] = value
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> SynthConfig:
        values = dict(data)
        if "effects" in values:
            values["effects"] = EffectSet.from_list(values["effects"])
        if "start" in values and isinstance(values["start"], str):
            values["start"] = dt.date.fromisoformat(values["start"])
        if values.get("refinement", DEFAULT_REFINEMENT) is None:  # a truth's null: the default
            del values["refinement"]
        return cls(**values)


def drifting_parameter(effects: EffectSet, key: str) -> tuple[int, str]:
    """The effect (its index in ``effects``) and parameter a drift key names (``parameter``
    or ``effect.parameter``); ValueError naming the key when none, several, or one acting on
    the sensor's output."""
    effect_name, _, name = key.rpartition(".")
    found = [
        (i, e)
        for i, e in enumerate(effects)
        if name in e.parameters and effect_name in ("", e.name)
    ]
    if len(found) != 1:
        raise ValueError(
            f"effect_drift_per_day: {key!r} names {len(found)} parameters of the effects "
            f"{[e.name for e in effects]}; give one as parameter or effect.parameter"
        )
    index, effect = found[0]
    if type(effect).apply_to_sensor is not Effect.apply_to_sensor:
        raise ValueError(f"effect_drift_per_day: {effect.name} acts on the sensor; it cannot drift")
    return index, name


# --------------------------------------------------------------------------------------------
# Random streams: one per (wagon, purpose), so that switching one thing off leaves the rest


_PURPOSES = {
    "fleet": 0,
    "ambient": 1,
    "operation": 2,
    "readings": 3,
    "files": 4,
    "anomalies": 5,
    "bad_files": 6,
    "wagon": 7,
    "effects": 8,
}


def stream(seed: int, purpose: str, index: int = 0) -> np.random.Generator:
    """The random stream of ``purpose`` (one of the fixed purpose codes) and ``index`` (a
    wagon's or a file's number) for ``seed``."""
    return np.random.default_rng(
        np.random.SeedSequence(seed, spawn_key=(_PURPOSES[purpose], index))
    )


def draw_effect(text: str, seed: int, index: int = 0) -> Effect:
    """An effect of the vocabulary, ``NAME`` or ``NAME:law=LAW``, with every parameter drawn
    uniformly from its law's ``PARAMETER_RANGES`` (the same laws the close loop fits, so a
    drawn fleet is no easier than the world), from the stream of ``seed`` and ``index``.
    ``empirical`` (a fitting device, not physics) is never drawn."""
    name, _, rest = text.strip().partition(":")
    name, law = name.strip(), None
    for item in filter(None, (part.strip() for part in rest.split(","))):
        key, sep, value = item.partition("=")
        if key.strip() != "law" or not sep:
            raise ValueError(f"{text!r}: a drawn effect takes only law=LAW, got {item!r}")
        law = value.strip()
    cls = find_law(name, law)
    if cls.fallback:
        raise ValueError(f"{name}: a data-driven correction, not drawn into a fleet")
    return cls.random(stream(seed, "effects", index))
