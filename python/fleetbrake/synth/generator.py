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
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import polars as pl

from fleetbrake.fleet.registry import SPEC_DEFAULTS, Registry, WagonConfig, load_registry
from fleetbrake.synth.block import (
    BlockSimulator,
    SimulatedBlock,
    block_models,
    model_info,
    simulate_block,
    solar_rise_k,
)
from fleetbrake.synth.config import SENSOR_FAULT_SUBTYPES, SynthConfig, stream
from fleetbrake.synth.corrupt import Session, write_sessions
from fleetbrake.synth.operation import Operation, air_temperature, operate, sessions
from fleetbrake.synth.readings import sessions_as_logged
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
from fleetbrake.synth.wagons import (
    WagonPlan,
    physical_anomalies,
    plan_wagons,
    registry_toml,
    true_brakings,
)

__all__ = [
    "SENSOR_FAULT_SUBTYPES",
    "SERIES_COLUMNS",
    "Anomaly",
    "FileTruth",
    "FleetTruth",
    "SynthConfig",
    "TrueEvent",
    "WagonTruth",
    "generate_fleet",
    "load_truth",
    "summary",
]

logger = logging.getLogger(__name__)


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
    ``config.solver`` is ``rom``, a :class:`~fleetbrake.model.fullmodel.FullModelRunner` when
    it is ``full``. Default: the wagon's model of ``config.solver`` at ``config.refinement``
    (a reduced model is cached on disk).
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
    plans = plan_wagons(config)
    air = air_temperature(stream(config.seed, "ambient"), start_utc, n_main, config.ambient_mean_c)
    fleet = _write_registry(out_dir, config, plans, air)
    physical, fault_plan = _plan_anomalies(config, plans)

    model_of = block_models(config, rom)
    truth_dir = out_dir / TRUTH_DIR
    (truth_dir / SERIES_DIR).mkdir(parents=True, exist_ok=True)
    wagons: list[WagonTruth] = []
    anomalies: list[Anomaly] = []
    events: list[TrueEvent] = []
    recorded: list[Session] = []
    model_description: dict[str, Any] = {}
    for plan in plans:
        say(f"simulating {plan.wagon_id}")
        made = _generate_wagon(
            config,
            plan,
            fleet,
            physical[plan.wagon_id],
            model_of,
            air,
            start_utc,
            truth_dir,
        )
        anomalies += made.anomalies
        model_description = made.model
        wagons.append(made.truth)
        recorded += made.sessions
        events += made.events

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
        registry_problems=fleet.problems,
        rom=model_description,
    )
    (truth_dir / TRUTH_JSON).write_text(
        json.dumps(truth.to_dict(), indent=1, sort_keys=True) + "\n", encoding="utf-8"
    )
    return load_truth(out_dir)  # exactly what is on disk (floats rounded as written)


class _Fleet(NamedTuple):
    """The registry written for the fleet, as the generator reads it back."""

    registry: Registry
    defaults: dict[str, Any]
    """The registry's defaults (the fleet's mean air temperature among them)."""
    problems: list[dict[str, Any]]
    """The registry's problems, for the truth (the bad entry's)."""


def _write_registry(
    out_dir: Path, config: SynthConfig, plans: Sequence[WagonPlan], air: np.ndarray
) -> _Fleet:
    """Write ``fleet.toml`` (every wagon planned with an entry, good or bad) and read it back."""
    defaults = dict(SPEC_DEFAULTS)
    defaults["ambient_temp_c"] = round(float(np.mean(air)), 1)
    entries = [
        (p.wagon_id, p.wagon_type, p.overrides) for p in plans if p.registry in ("ok", "bad")
    ]
    registry_path = out_dir / "fleet.toml"
    registry_path.write_text(registry_toml(defaults, entries, config.seed), encoding="utf-8")
    registry = load_registry(registry_path)
    problems = [
        {"file": "fleet.toml", "wagon_id": pr.wagon_id, "key": pr.key, "message": pr.message}
        for pr in registry.problems
    ]
    return _Fleet(registry, defaults, problems)


def _plan_anomalies(
    config: SynthConfig, plans: Sequence[WagonPlan]
) -> tuple[dict[str, list[str]], dict[str, list[str]]]:
    """The anomalies planned per wagon: the physical ones (on the block) and the sensor
    faults (on files)."""
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
    return physical, fault_plan


class _GeneratedWagon(NamedTuple):
    """One wagon generated: its truth (its series written), what its unit logged, its true
    brakings and physical anomalies, and what simulated its block."""

    truth: WagonTruth
    sessions: list[Session]
    events: list[TrueEvent]
    anomalies: list[Anomaly]
    model: dict[str, Any]


def _generate_wagon(
    config: SynthConfig,
    plan: WagonPlan,
    fleet: _Fleet,
    physical: Sequence[str],
    model_of: Callable[[WagonConfig], BlockSimulator],
    air: np.ndarray,
    start_utc: dt.datetime,
    truth_dir: Path,
) -> _GeneratedWagon:
    """One wagon: its operation, its air, its block, its truth series (written), and what
    its unit logged."""
    wagon = (
        fleet.registry.wagons[plan.wagon_id]
        if plan.registry == "ok"
        else WagonConfig(
            wagon_id=plan.wagon_id,
            type=plan.wagon_type,
            **{
                **fleet.defaults,
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
    wagon_air = air[:n_s] + float(stream(config.seed, "ambient", plan.index + 1).normal(0.0, 0.7))
    if plan.ambient_column == "values":
        ambient_truth = wagon_air
        ambient_source = "log"
    else:
        ambient_truth = np.full(n_s, wagon.ambient_temp_c)
        ambient_source = "registry"

    drag_force, efficiency, anomalies = physical_anomalies(
        config, plan, physical, op, awake, start_utc
    )

    # the block, continuously
    model = model_of(wagon)
    # the air the block exchanges heat with: the air, plus the sunshine outside the
    # vocabulary when asked for (the truth's ambient_c stays the air's)
    block_air = ambient_truth
    if config.solar_heating_w_m2 > 0:
        hours = (start_utc.hour + np.arange(n_s) / 3600.0) % 24.0
        block_air = ambient_truth + solar_rise_k(config.solar_heating_w_m2, hours)
    result = simulate_block(model, wagon, config, op, block_air, drag_force, efficiency, awake)
    series_rel = f"{SERIES_DIR}/{plan.wagon_id}.parquet"
    times = pl.Series(
        "time_utc",
        (np.datetime64(start_utc, "s") + np.arange(n_s).astype("timedelta64[s]")).astype(
            "datetime64[us]"
        ),
    ).cast(pl.Datetime("us"))
    _write_series(truth_dir / series_rel, times, awake, op, result, ambient_truth)
    truth = WagonTruth(
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
    return _GeneratedWagon(
        truth=truth,
        sessions=sessions_as_logged(
            config, plan, wagon, op, result, wagon_air, times, spans, start_utc
        ),
        events=true_brakings(plan, op, start_utc),
        anomalies=anomalies,
        model=model_info(model, config),
    )


def _write_series(
    path: Path,
    times: pl.Series,
    awake: np.ndarray,
    op: Operation,
    result: SimulatedBlock,
    ambient_c: np.ndarray,
) -> None:
    """The wagon's truth series, per second over the whole period (a parquet file)."""
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
            "ambient_c": np.round(ambient_c, 4),
            "seat_c": np.round(result.seat_c, 4),
            "sensor_c": np.round(result.sensor_c, 4),
            "contact_mean_c": np.round(result.contact_mean_c, 4),
            "contact_max_c": np.round(result.contact_max_c, 4),
        }
    ).select(SERIES_COLUMNS).write_parquet(path, compression="zstd", statistics=False)


# --------------------------------------------------------------------------------------------
# The block


# --------------------------------------------------------------------------------------------
# Readings, sessions, true brakings


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
