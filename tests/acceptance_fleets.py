"""The fleets of the close loop's acceptance tests (fleets the pipeline did not make easy), and
what the tests measure on them.

Each :class:`Case` is one small fleet (``WAGONS`` wagons x ``DAYS`` UTC days, the last day the
holdout) written by ``fleetbrake.synth`` with the **full finite-element model** (``solver =
"full"``, ``FE_REFINEMENT``), never by the reduced model the pipeline predicts and fits with;
every anomaly and file fault on. A case holds one effect of the vocabulary whose law (among the
laws the close loop can name) and parameters are drawn at random from the case's seed
(:func:`draw_case_effect`: uniform in each law's ``PARAMETER_RANGES``), or no effect (the clean
fleet), or an effect outside the vocabulary (sunshine by the hour of day,
``SynthConfig.solar_heating_w_m2``, its peak drawn from ``SOLAR_PEAK_W_M2``).

:func:`make_outcome` generates a case, runs the pipeline on it (``run``: declared model, flags)
and the close loop, and returns an :class:`Outcome` holding everything the tests assert on; the
measures are plain functions of the database and the generator's truth:
:func:`holdout_rmse_against_truth`, :func:`report_vs_predictions`, :func:`flag_score`.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import inspect
import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import polars as pl

from fleetbrake.app.run import run_fleet
from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.loop import run_close_loop
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import LAWS, Effect, EffectSet, effect_from_dict
from fleetbrake.model.fullmodel import FullModelRunner
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.synth.block import BlockSimulator
from fleetbrake.synth.config import draw_effect
from fleetbrake.synth.generator import (
    FleetTruth,
    SynthConfig,
    generate_fleet,
    load_truth,
)
from fleetbrake.synth.scoring import FlagScore, score_flags

REPO = Path(__file__).resolve().parents[1]

WAGONS = 4
"""Registered wagons per fleet (with 4: wagon 1 clean, a dragging brake on 2, a weak brake on
3, the four sensor faults on 2-4; plus synth's unregistered and badly registered wagons)."""
DAYS = 3
"""UTC days per fleet: two fit days, the last one the holdout."""
FE_REFINEMENT = 0.6
"""The full model's mesh that writes the fleets: 6,131 hex20 nodes, the mesh the reduced model
of the tests is reduced from (``conftest.TEST_REFINEMENT``), so the world is not coarser than
the model that identifies it (on a coarser writer's mesh, such as 0.2 with 409 nodes, part of
the "truth" would be the writer's own mesh error, docs/estimator.md, "Accuracy"). The model
differs from the writer by its reduction and its time integration, not by a coarser mesh."""
NOISE_K = 0.1
"""The sensor noise the fleets are read with (``SynthConfig.sensor_noise_k``'s default)."""
SOLAR_PEAK_W_M2 = (40.0, 90.0)
"""Range of the absorbed sunshine's noon peak of the out-of-vocabulary fleet: a sol-air rise
of 4-9 K at noon on the block's air-cooled faces (``q / h0``, h0 10 W/m^2 K)."""

VOCABULARY = (
    "friction_speed",
    "friction_temperature",
    "convection_speed",
    "sensor_lag",
    "heat_partition",
    "holder_conduction",
    "ambient_offset",
)
"""The physical vocabulary of ``interface.md`` (``empirical``, a fitting device, excluded)."""


@dataclass(frozen=True)
class Case:
    """One acceptance fleet: ``effect`` (a vocabulary name, or None) or, with
    ``outside_vocabulary``, sunshine by the hour of day; everything random drawn from ``seed``."""

    name: str
    seed: int
    effect: str | None = None
    outside_vocabulary: bool = False


CASES: tuple[Case, ...] = (
    *(Case(name, seed=301 + i, effect=name) for i, name in enumerate(VOCABULARY)),
    Case("clean", seed=311),
    Case("hour_of_day", seed=313, outside_vocabulary=True),
)


def candidate_laws(name: str) -> list[type[Effect]]:
    """The laws of ``name`` the close loop can name and fit (``candidate``, not ``fallback``)."""
    return [cls for cls in LAWS[name] if cls.candidate and not cls.fallback]


def draw_case_effect(case: Case) -> Effect | None:
    """The case's effect: a law drawn among :func:`candidate_laws`, its parameters drawn by
    ``fleetbrake.synth.config.draw_effect`` (uniform in the law's ``PARAMETER_RANGES``), both
    from the case's seed."""
    if case.effect is None:
        return None
    laws = candidate_laws(case.effect)
    law = laws[int(np.random.default_rng(case.seed).integers(len(laws)))]
    return draw_effect(f"{case.effect}:law={law.law}", case.seed)


def synth_config(case: Case) -> SynthConfig:
    effect = draw_case_effect(case)
    solar = 0.0
    if case.outside_vocabulary:
        solar = round(float(np.random.default_rng(case.seed).uniform(*SOLAR_PEAK_W_M2)), 1)
    return SynthConfig(
        wagons=WAGONS,
        days=DAYS,
        seed=case.seed,
        effects=EffectSet((effect,)) if effect is not None else EffectSet(),
        anomalies=True,
        sensor_noise_k=NOISE_K,
        solver="full",
        refinement=FE_REFINEMENT,
        solar_heating_w_m2=solar,
    )


@dataclass
class Outcome:
    """A case generated, run and closed: the truth, the database, the report, and timings."""

    case: Case
    truth: FleetTruth
    db: Path
    report: dict[str, Any]
    holdout_from: dt.date
    loop: CloseLoopConfig
    seconds: dict[str, float] = field(default_factory=dict)


_WRITERS: dict[tuple[object, ...], FullModelRunner] = {}


def writer_for(wagon: WagonConfig) -> FullModelRunner:
    """The full finite-element model that writes a fleet's wagon, at ``FE_REFINEMENT``
    (assembled once per block and process)."""
    key = (wagon.geometry, wagon.block, wagon.sensor_point_m, FE_REFINEMENT)
    if key not in _WRITERS:
        _WRITERS[key] = FullModelRunner.for_wagon(wagon, refinement=FE_REFINEMENT)
    return _WRITERS[key]


# ------------------------------------------------------------------ the written fleets' cache

WRITER_SOURCES: tuple[str, ...] = (
    "python/fleetbrake/__init__.py",
    "python/fleetbrake/errors.py",
    "python/fleetbrake/synth",
    "python/fleetbrake/fleet",
    "python/fleetbrake/model/__init__.py",
    "python/fleetbrake/model/chaintypes.py",
    "python/fleetbrake/model/effects",
    "python/fleetbrake/model/fullmodel.py",
    "python/fleetbrake/model/physics.py",
    "python/fleetbrake/model/rom.py",
    "python/fleetbrake/model/rombasis.py",
    "python/fleetbrake/model/thermal.py",
    "python/fleetbrake/model/timeline.py",
    "crates/thermal_core/src",
    "crates/thermal_core/Cargo.toml",
    "crates/fleetbrake_py/src",
    "crates/fleetbrake_py/Cargo.toml",
    "Cargo.lock",
)
"""What writes an acceptance fleet, relative to the repository: ``fleetbrake.synth`` and the
modules it runs (``test_closeloop_fleet_cache`` checks that every ``fleetbrake`` module whose
code runs while a fleet is written by the full model is here), and the Rust of the full
model (its mesh, elements, assembly and time stepping, and their bindings). A directory
stands for its ``.py`` and ``.rs`` files; ``WRITER_SOURCES_EXCLUDED`` are left out. The
built extension is not hashed: a run uses the one built from these sources."""
WRITER_SOURCES_EXCLUDED: frozenset[str] = frozenset({"estimator.rs", "estimator"})
"""Files (by name) and Rust module directories (every file below them) that do not write a
fleet: the Kalman filter's kernel (``thermal_core/src/estimator/``) and its bindings
(``fleetbrake_py/src/estimator.rs``), the pipeline's estimator, not the generator's."""
FULL_WRITER_EXCLUDED: frozenset[str] = frozenset({"rom.rs", "rom"})
"""Files and directories that do not write a fleet of the full model (``solver="full"``,
every acceptance fleet): the reduced model's Rust (``thermal_core/src/rom/``) and its
bindings (``_ext.rom_*``), which the full model's writer never calls
(``test_the_full_writer_calls_no_reduced_model_rust`` writes a fleet with them made to
raise). A fleet of the reduced model (``solver="rom"``) hashes them."""
WRITER_FUNCTIONS: tuple[Callable[..., Any], ...] = (
    candidate_laws,
    draw_case_effect,
    synth_config,
    writer_for,
)
"""This module's writing part: its source is part of the writer's version."""


def writer_source_files(
    sources: Sequence[str] = WRITER_SOURCES,
    root: Path = REPO,
    excluded: frozenset[str] = WRITER_SOURCES_EXCLUDED,
) -> list[Path]:
    """The files of ``sources`` (a directory: its ``.py`` and ``.rs`` files at any depth, but
    those named in ``excluded`` and those below a directory named there), sorted; a source
    that does not exist is an error."""
    files: list[Path] = []
    for name in sources:
        path = root / name
        if path.is_file():
            files.append(path)
        elif path.is_dir():
            files += [
                f
                for f in path.rglob("*")
                if f.suffix in {".py", ".rs"}
                and f.is_file()
                and excluded.isdisjoint(f.relative_to(path).parts)
            ]
        else:
            raise FileNotFoundError(f"{path}: a writer source that does not exist")
    return sorted(set(files))


def writer_version(
    config: SynthConfig,
    refinement: float = FE_REFINEMENT,
    sources: Sequence[str] = WRITER_SOURCES,
    root: Path = REPO,
) -> str:
    """The hash (sha256, hex) of what determines a written fleet: the full model's
    ``refinement``, the ``config`` (seed, drawn effect and its parameters, everything else),
    the source of this module's writing part (``WRITER_FUNCTIONS``) and the content of every
    writer source file (:func:`writer_source_files`, by its path under ``root``). Any change
    to one of them gives another version, so a changed writer never reuses a stale fleet.
    A fleet of the full model leaves out ``FULL_WRITER_EXCLUDED`` (it never runs them)."""
    digest = hashlib.sha256()

    def put(label: str, data: bytes) -> None:
        digest.update(f"{label}\0{len(data)}\0".encode())
        digest.update(data)

    put("refinement", repr(float(refinement)).encode())
    put("config", json.dumps(config.to_dict(), sort_keys=True, default=str).encode())
    for function in WRITER_FUNCTIONS:
        put(function.__name__, inspect.getsource(function).encode())
    excluded = WRITER_SOURCES_EXCLUDED
    if config.solver == "full":
        excluded |= FULL_WRITER_EXCLUDED
    for path in writer_source_files(sources, root, excluded):
        put(path.relative_to(root).as_posix(), path.read_bytes())
    return digest.hexdigest()


def fleet_cache_root() -> Path | None:
    """Where written acceptance fleets are kept: ``$FLEETBRAKE_ACCEPTANCE_CACHE``, else
    ``~/.cache/fleetbrake/acceptance``; None (no cache) when the variable is ``off``."""
    env = os.environ.get("FLEETBRAKE_ACCEPTANCE_CACHE")
    if env == "off":
        return None
    return Path(env) if env else Path.home() / ".cache" / "fleetbrake" / "acceptance"


def cached_fleet(
    name: str,
    config: SynthConfig,
    fleet_dir: Path,
    write: Callable[[Path], object],
    *,
    version: str,
    root: Path,
) -> bool:
    """Put the fleet of (``name``, ``config.seed``, ``version``) in ``fleet_dir`` (which must not
    exist), a copy of the cached one; on a miss ``write(directory)`` writes it first into a
    temporary directory under ``root``, renamed into place once complete (a run killed while
    writing leaves no entry; of two runs writing one entry the first rename wins). True when
    the fleet came from the cache. The run works on its copy: the cached fleet is only read."""
    entry = root / f"{name}-s{config.seed}-{version[:24]}"
    reused = (entry / "fleet").is_dir()
    if not reused:
        root.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{entry.name}.", dir=root))
        try:
            write(staging / "fleet")
            about = {
                "case": name,
                "seed": config.seed,
                "writer_version": version,
                "config": config.to_dict(),
                "written_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            }
            (staging / "writer.json").write_text(
                json.dumps(about, indent=1, default=str), encoding="utf-8"
            )
            try:
                staging.rename(entry)
            except OSError:
                if not (entry / "fleet").is_dir():  # not another run's complete entry
                    raise
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    shutil.copytree(entry / "fleet", fleet_dir)
    return reused


def write_fleet(
    name: str,
    config: SynthConfig,
    fleet_dir: Path,
    full_model_for: Callable[[WagonConfig], BlockSimulator] = writer_for,
    seconds: dict[str, float] | None = None,
) -> FleetTruth:
    """``config``'s fleet in ``fleet_dir``, written by ``full_model_for``; with the default
    writer (:func:`writer_for`) a copy from the cache (:func:`fleet_cache_root`) when it holds
    the fleet of this ``name``, seed and :func:`writer_version`, else written and cached (any
    other writer, or no cache: written here). ``seconds["generate"]`` (written) or
    ``seconds["from_cache"]`` (copied) is set."""
    root = fleet_cache_root()
    spent = {} if seconds is None else seconds
    began = time.perf_counter()
    if full_model_for is not writer_for or root is None:
        truth = generate_fleet(fleet_dir, config, rom=full_model_for)
        spent["generate"] = time.perf_counter() - began
        return truth
    reused = cached_fleet(
        name,
        config,
        fleet_dir,
        lambda d: generate_fleet(d, config, rom=writer_for),
        version=writer_version(config),
        root=root,
    )
    spent["from_cache" if reused else "generate"] = time.perf_counter() - began
    return load_truth(fleet_dir)


def write_case_fleet(
    case: Case,
    fleet_dir: Path,
    full_model_for: Callable[[WagonConfig], BlockSimulator] = writer_for,
    seconds: dict[str, float] | None = None,
) -> FleetTruth:
    """The case's fleet (:func:`synth_config`) in ``fleet_dir``: :func:`write_fleet` under the
    case's name."""
    return write_fleet(case.name, synth_config(case), fleet_dir, full_model_for, seconds)


def make_outcome(
    case: Case,
    out_dir: Path,
    rom_refinement: float,
    full_model_for: Callable[[WagonConfig], FullModelRunner] = writer_for,
) -> Outcome:
    """Generate ``case`` in ``out_dir`` with the full model (``full_model_for``, by default
    :func:`writer_for`: ``FE_REFINEMENT``, the fleet then copied from the cache when it holds
    it, :func:`write_case_fleet`), ``run`` it (reduced model at ``rom_refinement``, in this
    process), then close the loop with the holdout on the last day."""
    config = synth_config(case)
    seconds: dict[str, float] = {}
    truth = write_case_fleet(case, out_dir / "fleet", full_model_for, seconds)
    db = out_dir / "fleet.duckdb"
    simulation = SimulationConfig(refinement=rom_refinement)
    began = time.perf_counter()
    run_fleet(out_dir / "fleet", db, simulation=simulation, progress=False, workers=1)
    seconds["run"] = time.perf_counter() - began
    holdout = config.start + dt.timedelta(days=config.days - 1)
    loop = CloseLoopConfig(holdout, simulation=simulation)
    out = out_dir / "close-loop.json"
    began = time.perf_counter()
    report = run_close_loop(db, holdout, out, config=loop)
    seconds["close_loop"] = time.perf_counter() - began
    # the report on disk is the one returned
    assert json.loads(out.read_text()) == json.loads(json.dumps(report, default=str))
    return Outcome(case, truth, db, report, holdout, loop, seconds)


def outcome_in(case: Case, out_dir: Path, rom_refinement: float) -> Outcome:
    """The outcome :func:`make_outcome` left in ``out_dir``, read back (to measure a kept
    fleet again without generating and closing it again)."""
    truth = load_truth(out_dir / "fleet")
    report = json.loads((out_dir / "close-loop.json").read_text(encoding="utf-8"))
    holdout = truth.config.start + dt.timedelta(days=truth.config.days - 1)
    loop = CloseLoopConfig(holdout, simulation=SimulationConfig(refinement=rom_refinement))
    return Outcome(case, truth, out_dir / "fleet.duckdb", report, holdout, loop)


def refit_through_meshes(
    outcome: Outcome, meshes: Sequence[str], max_nfev: int = 7
) -> dict[str, dict[str, float]]:
    """The report's added effects refitted, from its parameters, on the fit events as the
    kept database now has them (outliers the report names left out) through other meshes:
    each of ``meshes`` a reduced model's refinement (``"0.4"``) or ``"full<refinement>"``
    (the full FE model, slow): mesh -> ``effect.parameter`` -> value. A diagnostic of the
    numerical term (docs/closeloop.md), on a kept fleet (:func:`outcome_in`)."""
    from fleetbrake.closeloop import evidence
    from fleetbrake.closeloop.fitdata import FitData
    from fleetbrake.closeloop.leastsquares import FitTask, fit_task
    from fleetbrake.simulation.predictions import revision, stored_wagons
    from fleetbrake.warehouse.connection import open_warehouse, sql

    report = outcome.report
    added = [effect_from_dict(d) for d in report["effects"]]
    excluded = frozenset(report.get("outliers", {}).get("event_ids", []))
    unknown = frozenset(report.get("unknown_heat", {}).get("event_ids", []))
    out: dict[str, dict[str, float]] = {}
    with open_warehouse(outcome.db) as wh:
        wagons = stored_wagons(wh)
        base = revision(wh, report["baseline_revision"])
        sim = outcome.loop.simulation
        events = wh.con.sql(sql("q_closeloop_events")).pl()
        loaded = evidence.load_wagons(wh, wagons, events, sim)
        fit, _, _ = evidence.event_sets(wh, base.name, outcome.loop, unknown)
        for mesh in meshes:
            solver, refinement = ("full", mesh[4:]) if mesh.startswith("full") else ("rom", mesh)
            other = dataclasses.replace(base, solver=solver, refinement=float(refinement))
            task = FitTask(
                FitData.build(loaded, fit, sim, other),
                base.effects,
                tuple(type(e) for e in added),
                tuple(added),
                max_nfev,
                outcome.loop.diff_step,
                excluded,
            )
            fitted = fit_task(task)
            out[mesh] = dict(zip(fitted.names, map(float, fitted.x), strict=True))
    return out


# ------------------------------------------------------------------------------ measures


def fitted_effects(report: Mapping[str, Any]) -> list[Effect]:
    """The effects the report says were added (``effects``, each with its law; else read from
    ``effect`` and ``parameters`` by the parameter names)."""
    if report.get("new_revision") is None:
        return []
    if report.get("effects"):
        return [effect_from_dict(d) for d in report["effects"]]
    names = str(report["effect"]).split("+")
    if len(names) != 1:
        raise AssertionError(f"several effects and no per-effect parameters: {report['effect']}")
    return [effect_from_dict({"name": names[0], "parameters": report["parameters"]})]


def interval_misses(
    truth: Effect, intervals: Mapping[str, Sequence[float | None]]
) -> dict[str, tuple[float, Any]]:
    """The true parameters of ``truth`` whose reported interval does not contain them (or that
    have no interval): name -> (true value, interval). ``None`` is an unbounded side."""
    misses: dict[str, tuple[float, Any]] = {}
    for name, value in truth.parameters.items():
        interval = intervals.get(name)
        if interval is None or len(interval) != 2:
            misses[name] = (value, interval)
            continue
        lo, hi = interval
        if not ((lo is None or lo <= value) and (hi is None or value <= hi)):
            misses[name] = (value, interval)
    return misses


def _connect(db: Path) -> duckdb.DuckDBPyConnection:
    return duckdb.connect(str(db), read_only=True)


def event_sets(outcome: Outcome) -> dict[str, dict[str, list[str]]]:
    """The fit and holdout event ids by the report's documented exclusion rule (an event whose
    window overlaps a dragging/weak brake or sensor-fault flag of its wagon, or the window of
    one of its events cut by a data gap, or starts within ``settle_after_flag_s`` after one
    ends, is left out), computed from the views: ``{"used": {...}, "every": {...}}``."""
    con = _connect(outcome.db)
    try:
        frame = con.sql(
            """
            WITH windows AS (
                SELECT event_id, wagon_id, min(time_utc) AS t0, max(time_utc) AS t1
                FROM v_predictions WHERE model_revision = $base GROUP BY ALL
            )
            , disturbances AS (
                SELECT wagon_id, start_utc AS d0, end_utc AS d1 FROM v_flags
                WHERE kind IN ('dragging_brake', 'weak_brake', 'sensor_fault')
                UNION ALL
                SELECT w.wagon_id, w.t0, w.t1 FROM windows w JOIN events e USING (event_id)
                WHERE NOT e.complete
            )
            SELECT w.event_id, e.start_utc, EXISTS (
                SELECT 1 FROM disturbances d WHERE d.wagon_id = w.wagon_id
                AND d.d0 <= w.t1 AND d.d1 + to_microseconds($settle_us) >= w.t0
            ) AS flagged
            FROM windows w JOIN v_events e USING (event_id)
            """,
            params={
                "base": outcome.report["baseline_revision"],
                "settle_us": round(outcome.loop.settle_after_flag_s * 1e6),
            },
        ).pl()
    finally:
        con.close()
    cutoff = dt.datetime.combine(outcome.holdout_from, dt.time())
    before = pl.col("start_utc") < cutoff
    # brakings over a frozen GPS speed, as the report names them (the rule itself is tested
    # in test_closeloop.py: frozen speed found from the samples)
    unknown = list(outcome.report.get("unknown_heat", {}).get("event_ids", []))
    clean = frame.filter(~pl.col("flagged") & ~pl.col("event_id").is_in(unknown))
    return {
        "used": {
            "fit": clean.filter(before)["event_id"].to_list(),
            "holdout": clean.filter(~before)["event_id"].to_list(),
        },
        "every": {
            "fit": frame.filter(before)["event_id"].to_list(),
            "holdout": frame.filter(~before)["event_id"].to_list(),
        },
    }


def rmse_measured(db: Path, revision: str, event_ids: Sequence[str]) -> float | None:
    """RMSE of measured - predicted sensor over these events' seconds with a valid reading."""
    if not event_ids:
        return None
    con = _connect(db)
    try:
        con.register("ids", pl.DataFrame({"event_id": list(event_ids)}, schema={"event_id": str}))
        ((value,),) = con.execute(
            "SELECT sqrt(avg(power(measured_sensor_c - predicted_sensor_c, 2))) "
            "FROM v_predictions WHERE model_revision = $rev "
            "AND measured_sensor_c IS NOT NULL AND event_id IN (SELECT event_id FROM ids)",
            {"rev": revision},
        ).fetchall()
    finally:
        con.close()
    return None if value is None else float(value)


def report_vs_predictions(outcome: Outcome) -> list[str]:
    """Every figure of the report's ``fit``/``holdout`` parts that differs from what
    ``v_predictions`` gives for the same events (empty: they agree to 1e-9)."""
    report = outcome.report
    sets = event_sets(outcome)
    base = report["baseline_revision"]
    after = report["new_revision"] or base
    problems = []
    for key in ("fit", "holdout"):
        part = report[key]
        for count, ids in (("events", sets["used"][key]), ("events_all", sets["every"][key])):
            if part.get(count) != len(ids):
                problems.append(f"{key}.{count}: report {part.get(count)}, views {len(ids)}")
        for field_name, rev, ids in (
            ("rmse_before_k", base, sets["used"][key]),
            ("rmse_after_k", after, sets["used"][key]),
            ("rmse_before_all_k", base, sets["every"][key]),
            ("rmse_after_all_k", after, sets["every"][key]),
        ):
            value = rmse_measured(outcome.db, rev, ids)
            stated = part.get(field_name)
            same = (
                stated is None
                if value is None
                else stated is not None and abs(stated - value) <= 1e-9 * max(abs(value), 1e-12)
            )
            if not same:
                problems.append(f"{key}.{field_name}: report {stated}, views {value}")
    return problems


def holdout_rmse_against_truth(outcome: Outcome, revision: str) -> float:
    """RMSE of ``revision``'s predicted sensor against the generator's noise-free sensor over
    the holdout events the report uses (every second of their windows)."""
    ids = event_sets(outcome)["used"]["holdout"]
    if not ids:
        raise AssertionError(f"{outcome.case.name}: no holdout event left to judge")
    con = _connect(outcome.db)
    try:
        con.register("ids", pl.DataFrame({"event_id": ids}, schema={"event_id": str}))
        pred = con.sql(
            "SELECT wagon_id, time_utc, predicted_sensor_c FROM v_predictions "
            "WHERE model_revision = $rev AND event_id IN (SELECT event_id FROM ids)",
            params={"rev": revision},
        ).pl()
    finally:
        con.close()
    errors = []
    for (wagon_id,), part in pred.partition_by("wagon_id", as_dict=True).items():
        series = outcome.truth.series(str(wagon_id)).select(
            pl.col("time_utc").dt.cast_time_unit("us"), "sensor_c"
        )
        joined = part.with_columns(pl.col("time_utc").dt.cast_time_unit("us")).join(
            series, on="time_utc"
        )
        errors.append((joined["predicted_sensor_c"] - joined["sensor_c"]).to_numpy())
    e = np.concatenate(errors)
    return float(np.sqrt(np.mean(e * e)))


def flag_score(outcome: Outcome) -> FlagScore:
    """The stored flags (judged with the revision the loop left current) against the
    generator's injected anomalies (:func:`fleetbrake.synth.scoring.score_flags`)."""
    return score_flags(outcome.db, outcome.truth)


def summary_row(outcome: Outcome) -> dict[str, Any]:
    """What the acceptance table shows for a case (each figure None when it cannot be had)."""
    report = outcome.report
    truth = draw_case_effect(outcome.case)
    row: dict[str, Any] = {
        "case": outcome.case.name,
        "truth": truth.to_dict() if truth is not None else None,
        "solar_w_m2": outcome.truth.config.solar_heating_w_m2 or None,
        "named": report.get("effect"),
        "fitted": [e.to_dict() for e in _quiet(lambda: fitted_effects(report), [])],
        "intervals": report.get("parameter_intervals"),
        "noise_k": report.get("noise_k"),
        "adequate": report.get("adequate"),
        "unexplained": report.get("unexplained"),
        "fit_rmse_k": [report["fit"].get("rmse_before_k"), report["fit"].get("rmse_after_k")],
        "seconds": {k: round(v, 1) for k, v in outcome.seconds.items()},
    }
    row["holdout_truth_rmse_k"] = [
        _quiet(lambda rev=rev: round(holdout_rmse_against_truth(outcome, rev), 4), None)
        for rev in (report["baseline_revision"], report.get("new_revision"))
        if rev is not None
    ]
    score = _quiet(lambda: flag_score(outcome), None)
    if not isinstance(score, FlagScore):
        row["flags"] = score
    else:
        row["flags"] = {
            "precision": round(score.precision, 3),
            "recall": round(score.recall, 3),
            "by_kind": {
                k: (v.flags, v.true_flags, v.anomalies, v.found) for k, v in score.by_kind.items()
            },
            "misses": score.misses,
        }
    return row


def _quiet(make: Callable[[], Any], default: Any) -> Any:
    try:
        return make()
    except Exception as exc:  # a summary never hides the test's own failure
        return default if default is not None else f"error: {exc!r}"
