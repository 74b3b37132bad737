"""The generated fleet's wagons: what each one is (:class:`WagonPlan`, :func:`plan_wagons`),
the registry written for them (:func:`registry_toml`), the physical anomalies planted on a
wagon (:func:`physical_anomalies`) and its true brakings (:func:`true_brakings`)."""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fleetbrake.synth.config import SynthConfig, stream
from fleetbrake.synth.operation import Operation, true_events
from fleetbrake.synth.truth import Anomaly, TrueEvent

__all__ = [
    "WagonPlan",
    "physical_anomalies",
    "plan_wagons",
    "registry_toml",
    "true_brakings",
]


def registry_toml(
    defaults: Mapping[str, Any], entries: Sequence[tuple[str, str, Mapping[str, Any]]], seed: int
) -> str:
    def show(value: Any) -> str:
        if isinstance(value, str):
            return json.dumps(value)
        if isinstance(value, bool):
            return "true" if value else "false"
        return repr(value)

    lines = [
        f"# synthetic fleet written by `fleetbrake synth` (seed {seed})",
        "",
        "[defaults]",
    ]
    lines += [f"{key} = {show(value)}" for key, value in defaults.items()]
    for wagon_id, wagon_type, overrides in entries:
        lines += ["", "[[wagon]]", f"id = {show(wagon_id)}", f"type = {show(wagon_type)}"]
        lines += [f"{key} = {show(value)}" for key, value in overrides.items()]
    return "\n".join(lines) + "\n"


@dataclass
class WagonPlan:
    index: int
    wagon_id: str
    registry: str  # ok / missing / bad
    overrides: dict[str, Any]
    wagon_type: str
    ambient_column: str
    mass_kg: float
    """Mass braked by the wagon's own brake: with the declared force chain it sets the
    train's deceleration (every wagon of the train brakes alike)."""
    sleep_after_s: int
    """The unit sleeps after the wagon has stood this long."""
    days: int


def plan_wagons(config: SynthConfig) -> list[WagonPlan]:
    rng = stream(config.seed, "fleet")
    n_sensor = round(config.ambient_sensor_fraction * config.wagons)
    plans = []
    total = config.wagons + int(config.unregistered_wagon) + int(config.bad_registry_entry)
    without = 0
    for i in range(total):
        wagon_rng = stream(config.seed, "wagon", i)
        registry = "ok"
        if i >= config.wagons:
            registry = "missing" if config.unregistered_wagon and i == config.wagons else "bad"
        overrides: dict[str, Any] = {}
        wagon_type = "Sggmrs"
        if i % 3 == 2:
            overrides["cylinder_diameter_m"] = 0.305
            wagon_type = "Rns"
        if registry == "bad":
            overrides["cylinder_diameter_m"] = -0.254  # the bad value (wrong sign)
        if i >= config.wagons:
            ambient_column = "values"
        elif i < n_sensor:
            ambient_column = "values"
        else:
            ambient_column = "absent" if without % 2 == 0 else "empty"
            without += 1
        plans.append(
            WagonPlan(
                index=i,
                wagon_id=f"SGG-{i + 1:04d}",
                registry=registry,
                overrides=overrides,
                wagon_type=wagon_type,
                ambient_column=ambient_column,
                mass_kg=round(float(wagon_rng.uniform(55_000.0, 90_000.0)), -2),
                sleep_after_s=int(wagon_rng.integers(240, 600)),
                days=config.days if registry == "ok" else 1,
            )
        )
    del rng
    return plans


def physical_anomalies(
    config: SynthConfig,
    plan: WagonPlan,
    kinds: Sequence[str],
    op: Operation,
    awake: np.ndarray,
    start_utc: dt.datetime,
) -> tuple[np.ndarray, np.ndarray, list[Anomaly]]:
    """The wagon's dragging brake (extra block force) and weak brake (a share of the
    declared force), per second, and their truth."""
    n_s = op.speed_kmh.size
    an_rng = stream(config.seed, "anomalies", plan.index)
    drag_force = np.zeros(n_s)
    efficiency = np.ones(n_s)
    anomalies: list[Anomaly] = []
    for kind in kinds:
        if kind == "dragging_brake":
            running = np.flatnonzero((op.speed_kmh > 30.0) & (op.pressure_bar < 0.01) & awake)
            late = running[running >= n_s // 3]
            pick = late if late.size else running
            if pick.size == 0:
                continue
            first = int(pick[int(an_rng.integers(0, pick.size))])
            stop = min(first + int(an_rng.integers(15 * 60, 40 * 60)), n_s)
            force_n = float(an_rng.uniform(150.0, 400.0))
            drag_force[first:stop] = force_n
            anomalies.append(
                Anomaly(
                    plan.wagon_id,
                    "dragging_brake",
                    start_utc + dt.timedelta(seconds=first),
                    start_utc + dt.timedelta(seconds=stop),
                    parameters={"drag_force_n": force_n},
                )
            )
        elif kind == "weak_brake":
            day = 1 if plan.days >= 2 else 0
            share = float(an_rng.uniform(0.4, 0.6))
            efficiency[day * 86_400 : (day + 1) * 86_400] = share
            anomalies.append(
                Anomaly(
                    plan.wagon_id,
                    "weak_brake",
                    start_utc + dt.timedelta(days=day),
                    start_utc + dt.timedelta(days=day + 1),
                    parameters={"brake_efficiency": share},
                )
            )
    return drag_force, efficiency, anomalies


def true_brakings(plan: WagonPlan, op: Operation, start_utc: dt.datetime) -> list[TrueEvent]:
    """The wagon's brakings as the generator made them (not yet known to be recorded)."""
    events: list[TrueEvent] = []
    for command, first, last in true_events(op):
        window = op.pressure_bar[first : last + 1]
        p_mean = float(np.sum(window[1:] + window[:-1]) * 0.5 / max(last - first, 1))
        detail = {"stop": "station", "signal_stop": "signal"}.get(command.kind)
        events.append(
            TrueEvent(
                wagon_id=plan.wagon_id,
                kind="stop" if detail else command.kind,
                detail=detail,
                start_utc=start_utc + dt.timedelta(seconds=first),
                end_utc=start_utc + dt.timedelta(seconds=last),
                command_utc=start_utc + dt.timedelta(seconds=command.command),
                release_command_utc=start_utc + dt.timedelta(seconds=command.release),
                p_target_bar=round(command.p_target_bar, 4),
                p_mean_bar=p_mean,
                v_start_kmh=float(op.speed_kmh[first]),
                v_end_kmh=float(op.speed_kmh[last]),
                recorded=False,
                file=None,
            )
        )
    return events
