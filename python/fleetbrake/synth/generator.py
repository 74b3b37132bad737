"""A synthetic fleet, written exactly as ``shared/spec/fleet-data.md`` says, with its truth beside it.

::

    from fleetbrake.model.effects import ConvectionSpeed, EffectSet
    from fleetbrake.synth.generator import SynthConfig, generate_fleet, load_truth

    truth = generate_fleet("out", SynthConfig(seed=7, effects=EffectSet((ConvectionSpeed(),))))
    truth.events            # every true braking (start/end UTC, kind, target pressure, ...)
    truth.anomalies         # dragging_brake, weak_brake, sensor_fault (open/frozen/loose/drift)
    truth.files             # every log file written, what was done to it, and if it is bad
    truth.series("SGG-0001")    # per second: true pressure, force, heat input, temperatures
    load_truth("out")       # the same, read back from out/truth/

Layout written::

    out/fleet.toml                                   # the registry (fleet-data.md)
    out/logs/<wagon>/<wagon>_<YYYYMMDDTHHMMSSZ>.csv[.gz]
    out/truth/truth.json                             # everything but the series
    out/truth/series/<wagon>.parquet                 # 1 Hz over the whole period

The package in four parts: :mod:`~fleetbrake.synth.config` (what to make, the seeded random
streams), :mod:`~fleetbrake.synth.operation` (how each wagon runs: the driving, the air, the
recording sessions, the true brakings), this module (the wagons, the block's temperatures, the
readings, the truth) and :mod:`~fleetbrake.synth.corrupt` (what befalls the files: the
imperfections and faults of ``fleet-data.md``); :mod:`~fleetbrake.synth.truth` holds the
records.

**Operation** (per wagon, continuous over ``days`` UTC days at 1 Hz): see
:mod:`~fleetbrake.synth.operation`.

**The block** is simulated *continuously* (``fleetbrake.model.timeline.simulate_timeline``),
so it keeps cooling while the unit sleeps, by the reduced model (``solver="rom"``, the one the
pipeline predicts with) or by the full finite-element model it is reduced from
(``solver="full"``, on the mesh of ``refinement``: a fleet that the model fitted to it did
not make).

**Readings.** ``block_temp_c`` = noise-free sensor (effects included) + Gaussian noise
(``sensor_noise_k``, 0.1 K: the Pt1000's), to 0.01 K; pressure + 3 mbar noise, quantised to
7 mbar; GPS speed with 0.3 km/h noise; ``distance_m`` since the session began. The air
temperature follows a daily sine plus a weather drift; wagons with an ambient sensor log it,
the others have no ``ambient_temp_c`` column (or an empty one), and their truth is simulated
with the registry's ``ambient_temp_c``: the value the reader will use.

**Imperfections** (``SynthConfig``; each can be switched off, :meth:`SynthConfig.clean`
switches all off) come from :mod:`~fleetbrake.synth.corrupt`: missing rows and gaps,
duplicated and swapped rows, empty cells, frozen and jumping GPS speed, files truncated
mid-row and gzip files cut mid-stream, garbage files; and from here: a wagon with logs but no
registry entry, a registry entry with a bad value (that wagon's logs exist too), and one wagon
writing its columns in another order with an extra column.

**Anomalies** (``anomalies=True``; wagon 1 of the fleet stays clean when there are two or
more): a dragging brake (block force with no cylinder pressure, 15-40 min), a weak brake (the
block force at 40-60 % of the declared for one UTC day), and sensor faults in single files:
``open`` (reads far out of range), ``frozen``, ``loose`` (relaxes towards ambient), ``drift``
(a growing offset).

**Outside the vocabulary** (``solar_heating_w_m2`` > 0): sunshine on the block's air-cooled
surfaces by the hour of day (:func:`solar_rise_k`), an effect no law of
``fleetbrake.model.effects`` describes: a fleet the close loop should call not adequate.

Everything is drawn from ``numpy`` generators seeded from ``seed`` and a fixed purpose code,
so the same configuration writes byte-identical files.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from fleetbrake.fleet.registry import SPEC_DEFAULTS, WagonConfig, load_registry
from fleetbrake.model.effects import AmbientOffset, Effect, EffectSet
from fleetbrake.model.physics import block_force_n
from fleetbrake.model.rom import FullModelRunner, ReducedModel
from fleetbrake.model.timeline import TimelineResult, simulate_timeline
from fleetbrake.synth.config import SENSOR_FAULT_SUBTYPES, SynthConfig, stream
from fleetbrake.synth.corrupt import Session, write_sessions
from fleetbrake.synth.operation import Operation, air_temperature, operate, sessions, true_events
from fleetbrake.synth.truth import (
    SERIES_COLUMNS,
    SERIES_DIR,
    TRUTH_DIR,
    TRUTH_JSON,
    Anomaly,
    FileTruth,
    FleetTruth,
    TrueEvent,
    WagonTruth,
    format_utc,
    load_truth,
)

__all__ = [
    "SENSOR_FAULT_SUBTYPES",
    "SERIES_COLUMNS",
    "Anomaly",
    "BlockSimulator",
    "FileTruth",
    "FleetTruth",
    "SynthConfig",
    "TrueEvent",
    "WagonTruth",
    "generate_fleet",
    "load_truth",
    "solar_rise_k",
    "summary",
]

logger = logging.getLogger(__name__)

PRESSURE_QUANTUM_BAR = 0.007
"""The pressure sensor's resolution (fleet-data.md)."""

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


# --------------------------------------------------------------------------------------------
# The wagons


def _registry_toml(
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
class _WagonPlan:
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


def _plan_wagons(config: SynthConfig) -> list[_WagonPlan]:
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
            _WagonPlan(
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


def generate_fleet(
    out_dir: str | Path,
    config: SynthConfig | None = None,
    *,
    rom: BlockSimulator | Callable[[WagonConfig], BlockSimulator] | None = None,
    progress: Callable[[str], None] | None = None,
) -> FleetTruth:
    """Write a synthetic fleet into ``out_dir`` (created; must be empty if it exists) and its
    truth into ``out_dir/truth``; return the truth.

    ``rom``: the block model to use (every wagon has the same block and sensor seat), or a
    function of the wagon giving it: a :class:`~fleetbrake.model.rom.ReducedModel` when
    ``config.solver`` is ``rom``, a :class:`~fleetbrake.model.rom.FullModelRunner` when it is
    ``full``. Default: the wagon's model of ``config.solver`` at ``config.refinement`` (a
    reduced model is cached on disk).
    """
    config = SynthConfig() if config is None else config
    out_dir = Path(out_dir)
    if out_dir.exists() and any(out_dir.iterdir()):
        raise FileExistsError(f"{out_dir}: not empty; give a new or empty directory")
    out_dir.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda _message: None)

    start_utc = dt.datetime.combine(config.start, dt.time())
    n_main = config.days * 86_400
    end_utc = start_utc + dt.timedelta(seconds=n_main)
    plans = _plan_wagons(config)

    # ---- registry
    air = air_temperature(stream(config.seed, "ambient"), start_utc, n_main, config.ambient_mean_c)
    defaults = dict(SPEC_DEFAULTS)
    defaults["ambient_temp_c"] = round(float(np.mean(air)), 1)
    entries = [
        (p.wagon_id, p.wagon_type, p.overrides) for p in plans if p.registry in ("ok", "bad")
    ]
    registry_path = out_dir / "fleet.toml"
    registry_path.write_text(_registry_toml(defaults, entries, config.seed), encoding="utf-8")
    registry = load_registry(registry_path)
    registry_problems = [
        {"file": "fleet.toml", "wagon_id": pr.wagon_id, "key": pr.key, "message": pr.message}
        for pr in registry.problems
    ]

    # ---- anomalies planned per wagon (physical ones; sensor faults go on files)
    ok = [p for p in plans if p.registry == "ok"]
    physical: dict[str, list[str]] = {p.wagon_id: [] for p in plans}
    fault_plan: dict[str, list[str]] = {p.wagon_id: [] for p in plans}
    if config.anomalies:
        # the first wagon stays clean; with 4 wagons: 2 drags, 3 is weak, faults on 2-4
        pool = ok[1:] if len(ok) > 1 else ok
        physical[pool[0].wagon_id].append("dragging_brake")
        physical[pool[1 % len(pool)].wagon_id].append("weak_brake")
        for number, subtype in enumerate(SENSOR_FAULT_SUBTYPES):
            # open -> third, frozen -> first, loose -> second, drift -> third of the pool
            fault_plan[pool[(number + 2) % len(pool)].wagon_id].append(subtype)

    model_of = _models(config, rom)
    truth_dir = out_dir / TRUTH_DIR
    (truth_dir / SERIES_DIR).mkdir(parents=True, exist_ok=True)
    wagons: list[WagonTruth] = []
    anomalies: list[Anomaly] = []
    events: list[TrueEvent] = []
    recorded: list[Session] = []
    model_info: dict[str, Any] = {}

    for plan in plans:
        say(f"simulating {plan.wagon_id}")
        wagon = (
            registry.wagons[plan.wagon_id]
            if plan.registry == "ok"
            else WagonConfig(
                wagon_id=plan.wagon_id,
                type=plan.wagon_type,
                **{
                    **defaults,
                    **{k: v for k, v in plan.overrides.items() if plan.registry != "bad"},
                },
            )
        )
        n_s = plan.days * 86_400
        op_rng = stream(config.seed, "operation", plan.index)
        position = (
            float(op_rng.uniform(46.0, 52.0)),
            float(op_rng.uniform(6.0, 15.0)),
            float(op_rng.uniform(150.0, 700.0)),
        )
        op = operate(op_rng, n_s, wagon, plan.mass_kg, position)
        spans = sessions(op.speed_kmh, plan.sleep_after_s)
        awake = np.zeros(n_s, dtype=bool)
        for a, b in spans:
            awake[a:b] = True

        # air: the wagon's own (a little off the region's), or the registry's
        wagon_air = air[:n_s] + float(
            stream(config.seed, "ambient", plan.index + 1).normal(0.0, 0.7)
        )
        if plan.ambient_column == "values":
            ambient_truth = wagon_air
            ambient_source = "log"
        else:
            ambient_truth = np.full(n_s, wagon.ambient_temp_c)
            ambient_source = "registry"

        drag_force, efficiency, wagon_anomalies = _physical_anomalies(
            config, plan, physical[plan.wagon_id], op, awake, start_utc
        )
        anomalies += wagon_anomalies

        # the block, continuously
        model = model_of(wagon)
        model_info = _model_info(model, config)
        # the air the block exchanges heat with: the air, plus the sunshine outside the
        # vocabulary when asked for (the truth's ambient_c stays the air's)
        block_air = ambient_truth
        if config.solar_heating_w_m2 > 0:
            hours = (start_utc.hour + np.arange(n_s) / 3600.0) % 24.0
            block_air = ambient_truth + solar_rise_k(config.solar_heating_w_m2, hours)
        result = _simulate_block(model, wagon, config, op, block_air, drag_force, efficiency, awake)
        series_rel = f"{SERIES_DIR}/{plan.wagon_id}.parquet"
        times = pl.Series(
            "time_utc",
            (np.datetime64(start_utc, "s") + np.arange(n_s).astype("timedelta64[s]")).astype(
                "datetime64[us]"
            ),
        ).cast(pl.Datetime("us"))
        pl.DataFrame(
            {
                "time_utc": times,
                "awake": awake,
                # rounded far below any resolution that matters, so that it packs well
                "speed_kmh": np.round(op.speed_kmh, 4),
                "distance_m": np.round(op.distance_m, 3),
                "elevation_m": np.round(op.elevation_m, 3),
                "brake_pressure_bar": np.round(op.pressure_bar, 6),
                "block_force_n": np.round(result.block_force_n, 3),
                "heat_flux_w_m2": np.round(result.sample_flux_w_m2, 2),
                "ambient_c": np.round(ambient_truth, 4),
                "seat_c": np.round(result.seat_c, 4),
                "sensor_c": np.round(result.sensor_c, 4),
                "contact_mean_c": np.round(result.contact_mean_c, 4),
                "contact_max_c": np.round(result.contact_max_c, 4),
            }
        ).select(SERIES_COLUMNS).write_parquet(
            truth_dir / series_rel, compression="zstd", statistics=False
        )

        wagons.append(
            WagonTruth(
                wagon_id=plan.wagon_id,
                registry=plan.registry,
                registry_overrides=dict(plan.overrides),
                ambient_column=plan.ambient_column,
                ambient_source=ambient_source,
                registry_ambient_c=float(wagon.ambient_temp_c),
                mass_kg=plan.mass_kg,
                sleep_after_s=plan.sleep_after_s,
                days=plan.days,
                series=series_rel,
            )
        )
        recorded += _sessions_as_logged(
            config, plan, wagon, op, result, wagon_air, times, spans, start_utc
        )
        events += _true_brakings(plan, op, start_utc)

    # ---- files: what befalls them (imperfections, bad files, sensor faults), then written
    files, fault_anomalies = write_sessions(
        out_dir,
        config,
        recorded,
        fault_plan,
        [p.wagon_id for p in plans if p.registry == "ok"],
        start_utc,
    )
    anomalies += fault_anomalies
    events = _mark_recorded(events, files)
    anomalies.sort(key=lambda a: (a.wagon_id, a.start_utc, a.kind))

    truth = FleetTruth(
        out_dir=out_dir,
        config=config,
        start_utc=start_utc,
        end_utc=end_utc,
        wagons=wagons,
        effects=config.effects,
        anomalies=anomalies,
        events=events,
        files=files,
        registry_problems=registry_problems,
        rom=model_info,
    )
    (truth_dir / TRUTH_JSON).write_text(
        json.dumps(truth.to_dict(), indent=1, sort_keys=True) + "\n", encoding="utf-8"
    )
    return load_truth(out_dir)  # exactly what is on disk (floats rounded as written)


# --------------------------------------------------------------------------------------------
# The block


def _models(
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


def _model_info(model: BlockSimulator, config: SynthConfig) -> dict[str, Any]:
    """What simulated the block, for the truth (``rom`` in ``truth.json``)."""
    if isinstance(model, FullModelRunner):
        return {
            "solver": "full",
            "refinement": config.refinement,
            "nodes": model.model.n_nodes,
        }
    return {"solver": "rom", "order": model.order, "cache_key": model.meta.get("cache_key")}


@dataclass(frozen=True)
class _Block:
    """A wagon's simulated block, per second (what the truth series keeps)."""

    block_force_n: np.ndarray
    sample_flux_w_m2: np.ndarray
    seat_c: np.ndarray
    sensor_c: np.ndarray
    contact_mean_c: np.ndarray
    contact_max_c: np.ndarray

    @classmethod
    def of(cls, result: TimelineResult) -> _Block:
        return cls(
            block_force_n=result.block_force_n,
            sample_flux_w_m2=result.sample_flux_w_m2,
            seat_c=result.seat_c,
            sensor_c=result.sensor_c,
            contact_mean_c=result.contact_mean_c,
            contact_max_c=result.contact_max_c,
        )


def _simulate_block(
    model: BlockSimulator,
    wagon: WagonConfig,
    config: SynthConfig,
    op: Operation,
    ambient_c: np.ndarray,
    drag_force_n: np.ndarray,
    brake_efficiency: np.ndarray,
    awake: np.ndarray,
) -> _Block:
    """The wagon's block over the whole period, from a uniform start at the air around it:
    by the reduced model in one run (its batch kernel), or by the full model in segments,
    at 1 Hz, and at ``ASLEEP_STEP_S`` while the unit sleeps."""
    offset = config.effects.get("ambient_offset")
    initial_c = float(ambient_c[0]) + (
        offset.offset_k if isinstance(offset, AmbientOffset) else 0.0
    )
    drag = drag_force_n if drag_force_n.any() else None
    efficiency = brake_efficiency if np.any(brake_efficiency != 1.0) else 1.0
    if isinstance(model, ReducedModel):
        return _Block.of(
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

    # the full model: segment by segment, the field handed on; the sensor's own effects (a
    # lag) act on the whole 1 Hz series of the seat afterwards, so that they run on unbroken
    n_s = op.speed_kmh.size
    force = np.asarray(block_force_n(wagon, op.pressure_bar), dtype=np.float64)
    force = force * brake_efficiency + drag_force_n
    quiet = ~awake & (op.speed_kmh == 0.0) & (force == 0.0)
    inputs_only = EffectSet(tuple(e for e in config.effects if not _acts_on_sensor(e)))
    names = ("block_force_n", "sample_flux_w_m2", "seat_c", "contact_mean_c", "contact_max_c")
    out = {name: np.empty(n_s) for name in names}
    state = None
    for first, last, step in _segments(quiet, ASLEEP_STEP_S, ASLEEP_MIN_S):
        at = np.arange(first, last + 1, step)
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
    return _Block(
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


def _physical_anomalies(
    config: SynthConfig,
    plan: _WagonPlan,
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


# --------------------------------------------------------------------------------------------
# Readings, sessions, true brakings


def _sessions_as_logged(
    config: SynthConfig,
    plan: _WagonPlan,
    wagon: WagonConfig,
    op: Operation,
    result: _Block,
    wagon_air: np.ndarray,
    times: pl.Series,
    spans: Sequence[tuple[int, int]],
    start_utc: dt.datetime,
) -> list[Session]:
    """What the wagon's unit logged in each session (readings with their noise and
    resolution), before anything befell the files."""
    n_s = op.speed_kmh.size
    rd = stream(config.seed, "readings", plan.index)
    sensor_read = np.round(result.sensor_c + rd.normal(0.0, config.sensor_noise_k, n_s), 2)
    p_read = np.maximum(op.pressure_bar + rd.normal(0.0, config.pressure_noise_bar, n_s), 0.0)
    p_read = np.round(np.round(p_read / PRESSURE_QUANTUM_BAR) * PRESSURE_QUANTUM_BAR, 3)
    v_read = np.round(np.abs(op.speed_kmh + rd.normal(0.0, config.speed_noise_kmh, n_s)), 2)
    v_read = np.where(op.speed_kmh > 0.0, v_read, np.round(np.abs(rd.normal(0.0, 0.1, n_s)), 2))
    elev_read = np.round(op.elevation_m + rd.normal(0.0, 0.8, n_s), 1)
    lat_read = np.round(op.lat_deg + rd.normal(0.0, 2e-5, n_s), 6)
    lon_read = np.round(op.lon_deg + rd.normal(0.0, 2e-5, n_s), 6)
    air_read = np.round(wagon_air + rd.normal(0.0, 0.15, n_s), 1)
    extra_col = np.round(27.6 + rd.normal(0.0, 0.05, n_s), 2)

    odd = config.odd_columns and plan.index == min(3, config.wagons - 1) and plan.registry == "ok"
    out: list[Session] = []
    for number, (a, b) in enumerate(spans):
        columns: dict[str, Any] = {
            "time_utc": times[a:b],
            "speed_kmh": v_read[a:b],
            "distance_m": np.round(op.distance_m[a:b] - op.distance_m[a], 1),
            "elevation_m": elev_read[a:b],
            "lat_deg": lat_read[a:b],
            "lon_deg": lon_read[a:b],
            "brake_pressure_bar": p_read[a:b],
            "block_temp_c": sensor_read[a:b],
        }
        if plan.ambient_column == "values":
            columns["ambient_temp_c"] = air_read[a:b]
        elif plan.ambient_column == "empty":
            columns["ambient_temp_c"] = pl.Series([None] * (b - a), dtype=pl.Float64)
        frame = pl.DataFrame(columns)
        if odd:
            frame = frame.with_columns(pl.Series("battery_v", extra_col[a:b]))
            order = [
                "time_utc",
                "block_temp_c",
                "brake_pressure_bar",
                "speed_kmh",
                "battery_v",
                "distance_m",
                "lat_deg",
                "lon_deg",
                "elevation_m",
            ]
            order += [c for c in frame.columns if c not in order]
            frame = frame.select(order)
        out.append(
            Session(
                wagon_id=plan.wagon_id,
                wagon_index=plan.index,
                number=number,
                registered=plan.registry == "ok",
                frame=frame,
                first_utc=start_utc + dt.timedelta(seconds=a),
                last_utc=start_utc + dt.timedelta(seconds=b - 1),
                odd_columns=odd,
                ambient_c=None if plan.ambient_column == "values" else wagon.ambient_temp_c,
            )
        )
    return out


def _true_brakings(plan: _WagonPlan, op: Operation, start_utc: dt.datetime) -> list[TrueEvent]:
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


def _mark_recorded(events: list[TrueEvent], files: list[FileTruth]) -> list[TrueEvent]:
    by_wagon: dict[str, list[FileTruth]] = {}
    for f in files:
        if f.bad != "garbage":
            by_wagon.setdefault(f.wagon_id, []).append(f)
    out = []
    for event in events:
        holder = next(
            (
                f
                for f in by_wagon.get(event.wagon_id, [])
                if f.start_utc <= event.start_utc and event.end_utc <= f.end_utc
            ),
            None,
        )
        recorded = holder is not None and holder.bad is None
        out.append(
            dataclasses.replace(
                event, recorded=recorded, file=holder.path if holder is not None else None
            )
        )
    return out


def summary(truth: FleetTruth) -> str:
    """A few lines on what was written."""
    good = [f for f in truth.files if f.bad is None]
    rows = sum(f.rows_written for f in truth.files)
    lines = [
        f"{truth.out_dir}: {len(truth.wagons)} wagons, {truth.start_utc:%Y-%m-%d} to "
        f"{truth.end_utc:%Y-%m-%d} (UTC, exclusive), {len(truth.files)} log files "
        f"({len(good)} good, {len(truth.files) - len(good)} bad), {rows:,} rows",
        f"braking events: {len(truth.events)} ({sum(e.recorded for e in truth.events)} recorded)",
        f"effects: {truth.effects}",
    ]
    if truth.config.solar_heating_w_m2 > 0:
        lines.append(
            f"outside the vocabulary: solar heating, {truth.config.solar_heating_w_m2:g} W/m^2 "
            "at noon UTC"
        )
    for a in truth.anomalies:
        kind = a.kind + (f" ({a.subtype})" if a.subtype else "")
        lines.append(
            f"anomaly: {a.wagon_id} {kind} {format_utc(a.start_utc)} .. {format_utc(a.end_utc)}"
        )
    for f in truth.bad_files():
        lines.append(f"bad file: {f.path}: {f.bad}")
    for p in truth.registry_problems:
        lines.append(f"registry: wagon {p['wagon_id']}, key {p['key']}: {p['message']}")
    missing = [w.wagon_id for w in truth.wagons if w.registry == "missing"]
    if missing:
        lines.append(f"logs without registry entry: {', '.join(missing)}")
    lines.append(f"truth: {truth.truth_dir}")
    return "\n".join(lines)
