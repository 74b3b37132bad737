"""A generated wagon's block, simulated continuously over the whole period: by the reduced
model in one run, or by the full finite-element model segment by segment (1 Hz, and
``ASLEEP_STEP_S`` while the unit sleeps); the block model of each wagon
(:func:`block_models`), and sunshine outside the vocabulary (:func:`solar_rise_k`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import AmbientOffset, Effect, EffectSet
from fleetbrake.model.fullmodel import FullModelRunner
from fleetbrake.model.physics import block_force_n
from fleetbrake.model.rom import ReducedModel
from fleetbrake.model.timeline import TimelineResult, simulate_timeline
from fleetbrake.synth.config import SynthConfig
from fleetbrake.synth.operation import Operation

__all__ = [
    "ASLEEP_MIN_S",
    "ASLEEP_STEP_S",
    "SOL_AIR_H_W_M2K",
    "BlockSimulator",
    "SimulatedBlock",
    "block_models",
    "model_info",
    "simulate_block",
    "solar_rise_k",
]


BlockSimulator = ReducedModel | FullModelRunner
"""What simulates a wagon's block: the reduced model, or the full finite-element model behind
the reduced model's interface."""


ASLEEP_STEP_S = 20
"""The full model's time step while the unit sleeps (at 1 Hz otherwise): the wagon stands with
its brake released and nothing is logged, the block only cools, smoothly, towards the air
(Crank-Nicolson at 20 s is exact to well under a millikelvin there); the truth series is
interpolated linearly between these steps. Half of a generated wagon's time is such sleep,
so the full model costs half as much."""


ASLEEP_MIN_S = 1800
"""Sleep shorter than this is simulated at 1 Hz (not worth a segment of its own)."""


SOL_AIR_H_W_M2K = 10.0
"""The declared convection coefficient (block-model.md) that turns absorbed sunshine into a
sol-air temperature rise (``SynthConfig.solar_heating_w_m2``)."""


def solar_rise_k(peak_w_m2: float, hour_utc: np.ndarray) -> np.ndarray:
    """The sol-air rise (K) of the block's air-cooled surfaces at each hour of the day:
    ``q / h0`` with ``q = peak max(0, sin(pi (hour - 6) / 12))`` (daylight 06-18 UTC, noon
    peak); an effect outside the vocabulary (``SynthConfig.solar_heating_w_m2``)."""
    hour = np.asarray(hour_utc, dtype=np.float64) % 24.0
    q = peak_w_m2 * np.maximum(np.sin(np.pi * (hour - 6.0) / 12.0), 0.0)
    return q / SOL_AIR_H_W_M2K


def block_models(
    config: SynthConfig, given: BlockSimulator | Callable[[WagonConfig], BlockSimulator] | None
) -> Callable[[WagonConfig], BlockSimulator]:
    """The block model of each wagon: the one given, or the wagon's model of
    ``config.solver`` (one per block geometry, material and sensor seat); checked to be of
    the configured solver, so that the truth says what made it."""
    made: dict[tuple[Any, ...], BlockSimulator] = {}

    def build(wagon: WagonConfig) -> BlockSimulator:
        key = (wagon.geometry, wagon.block, wagon.sensor_point_m)
        if key not in made:
            if config.solver == "full":
                made[key] = FullModelRunner.for_wagon(wagon, refinement=config.refinement)
            else:
                made[key] = ReducedModel.for_wagon(wagon, refinement=config.refinement)
        return made[key]

    def model_of(wagon: WagonConfig) -> BlockSimulator:
        if given is None:
            return build(wagon)
        model = given if isinstance(given, ReducedModel | FullModelRunner) else given(wagon)
        solver = "full" if isinstance(model, FullModelRunner) else "rom"
        if solver != config.solver:
            raise ValueError(
                f"the block model given is the {solver} model, but the configuration's solver "
                f"is {config.solver!r}"
            )
        return model

    return model_of


def model_info(model: BlockSimulator, config: SynthConfig) -> dict[str, Any]:
    """What simulated the block, for the truth (``rom`` in ``truth.json``)."""
    if isinstance(model, FullModelRunner):
        return {
            "solver": "full",
            "refinement": config.refinement,
            "nodes": model.model.n_nodes,
        }
    return {"solver": "rom", "order": model.order, "cache_key": model.meta.get("cache_key")}


@dataclass(frozen=True)
class SimulatedBlock:
    """A wagon's simulated block, per second (what the truth series keeps)."""

    block_force_n: np.ndarray
    sample_flux_w_m2: np.ndarray
    seat_c: np.ndarray
    sensor_c: np.ndarray
    contact_mean_c: np.ndarray
    contact_max_c: np.ndarray

    @classmethod
    def of(cls, result: TimelineResult) -> SimulatedBlock:
        return cls(
            block_force_n=result.block_force_n,
            sample_flux_w_m2=result.sample_flux_w_m2,
            seat_c=result.seat_c,
            sensor_c=result.sensor_c,
            contact_mean_c=result.contact_mean_c,
            contact_max_c=result.contact_max_c,
        )


def simulate_block(
    model: BlockSimulator,
    wagon: WagonConfig,
    config: SynthConfig,
    op: Operation,
    ambient_c: np.ndarray,
    drag_force_n: np.ndarray,
    brake_efficiency: np.ndarray,
    awake: np.ndarray,
) -> SimulatedBlock:
    """The wagon's block over the whole period, from a uniform start at the air around it:
    by the reduced model in one run (its batch kernel), or by the full model in segments,
    at 1 Hz, and at ``ASLEEP_STEP_S`` while the unit sleeps (the series starts at the fleet's
    start: the drifting effects' clock)."""
    offset = config.effects.get("ambient_offset")
    initial_c = float(ambient_c[0]) + (
        offset.offset_k if isinstance(offset, AmbientOffset) else 0.0
    )
    drag = drag_force_n if drag_force_n.any() else None
    efficiency = brake_efficiency if np.any(brake_efficiency != 1.0) else 1.0
    if isinstance(model, ReducedModel) and not config.effect_drift_per_day:
        return SimulatedBlock.of(
            simulate_timeline(
                model,
                wagon,
                dt_s=1.0,
                p_bar=op.pressure_bar,
                speed_kmh=op.speed_kmh,
                ambient_c=ambient_c,
                initial_c=initial_c,
                effects=config.effects,
                drag_force_n=drag,
                brake_efficiency=efficiency,
                keep_state=False,
            )
        )

    # the full model (or drifting effects): segment by segment, the field handed on, each
    # segment with the effects of its first second; the sensor's own effects (a lag) act on
    # the whole 1 Hz series of the seat afterwards, so that they run on unbroken
    n_s = op.speed_kmh.size
    force = np.asarray(block_force_n(wagon, op.pressure_bar), dtype=np.float64)
    force = force * brake_efficiency + drag_force_n
    quiet = ~awake & (op.speed_kmh == 0.0) & (force == 0.0)
    names = ("block_force_n", "sample_flux_w_m2", "seat_c", "contact_mean_c", "contact_max_c")
    out = {name: np.empty(n_s) for name in names}
    state = None
    for first, last, step in _segments(quiet, ASLEEP_STEP_S, ASLEEP_MIN_S):
        at = np.arange(first, last + 1, step)
        on_day = config.effects_on_day(first / 86_400.0)
        inputs_only = EffectSet(tuple(e for e in on_day if not _acts_on_sensor(e)))
        part = simulate_timeline(
            model,  # type: ignore[arg-type]  # the full model behind the reduced one's interface
            wagon,
            dt_s=float(step),
            p_bar=op.pressure_bar[at],
            speed_kmh=op.speed_kmh[at],
            ambient_c=ambient_c[at],
            initial_c=initial_c,
            initial_state=state,
            effects=inputs_only,
            drag_force_n=None if drag is None else drag[at],
            brake_efficiency=brake_efficiency[at] if isinstance(efficiency, np.ndarray) else 1.0,
            keep_state=True,
        )
        state = part.final_state
        seconds = np.arange(first, last + 1)
        for name in names:
            values = getattr(part, name)
            out[name][first : last + 1] = values if step == 1 else np.interp(seconds, at, values)
    return SimulatedBlock(
        block_force_n=out["block_force_n"],
        sample_flux_w_m2=out["sample_flux_w_m2"],
        seat_c=out["seat_c"],
        sensor_c=config.effects.apply_to_sensor(out["seat_c"], 1.0),
        contact_mean_c=out["contact_mean_c"],
        contact_max_c=out["contact_max_c"],
    )


def _acts_on_sensor(effect: Effect) -> bool:
    """Whether an effect changes the sensor's output (rather than the block's inputs)."""
    return type(effect).apply_to_sensor is not Effect.apply_to_sensor


def _segments(quiet: np.ndarray, step_s: int, min_s: int) -> list[tuple[int, int, int]]:
    """``(first, last, step)`` sample spans covering ``[0, n)``, consecutive ones sharing
    their boundary sample: stretches of ``quiet`` of at least ``min_s`` seconds at ``step_s``
    (shortened to a whole number of steps), everything else at 1 s."""
    n = quiet.size
    edges = np.flatnonzero(np.diff(np.concatenate(([0], quiet.astype(np.int8), [0]))))
    spans: list[tuple[int, int, int]] = []
    cursor = 0
    for a, b in edges.reshape(-1, 2):
        a, b = int(a), int(b)  # quiet on [a, b)
        length = (b - 1 - a) // step_s * step_s
        if length < min_s:
            continue
        if a > cursor:
            spans.append((cursor, a, 1))
        spans.append((a, a + length, step_s))
        cursor = a + length
    if cursor < n - 1:
        spans.append((cursor, n - 1, 1))
    return spans
