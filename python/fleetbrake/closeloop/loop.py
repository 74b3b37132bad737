"""``fleetbrake close-loop``: find the residual, trace it to the effect the model lacks, add
it, and report the error before and after (contract: ``shared/spec/interface.md``).

1. **Events.** Fit events start before the holdout date, holdout events on or after it; an
   event whose window overlaps a flag of its wagon (dragging or weak brake, sensor fault) or
   an event cut by a data gap (its heat input partly unlogged), or starts less than
   ``settle_after_flag_s`` after one ends, is left out of both: an anomaly is something to
   flag, not physics to fit, and the block state carried out of a weak or dragging brake (or
   re-anchored on a faulty reading, or missing a braking's heat) stays wrong for a while. The
   report gives the RMSE over every event of each set too (``*_all_k``), as the contract's
   plain definition reads.
2. **Residual.** measured - predicted sensor temperature, per second, of the current
   revision on the fit events: how it relates to speed, pressure, the predicted heating,
   ambient, time since activation and the phase (heating or cooling) is the evidence.
   The sensor noise is estimated from the residual itself (``std(diff) / sqrt(2)``: model
   errors are smooth, the thermistor's noise is white).
3. **Candidates.** Every effect of :mod:`fleetbrake.model.effects` (or those of
   ``CloseLoopConfig.candidates``), acting where it acts physically, its parameters fitted by
   bounded least squares on the per-second residual of the fit events (each evaluation
   re-simulates them, carried state and all, with the baseline revision's solver; each is
   compared with the starting point second by second, matched by event and second, so that a
   candidate losing a prediction is not scored on shifted seconds); then, when one effect
   leaves the fit clearly above the noise, pairs with the best.
4. **Choice** (never looks at the holdout): the Bayesian information criterion on an
   effective sample size (one independent residual per ``CORRELATION_S`` seconds: the
   residual of a missing effect is smooth, so the seconds are far from independent). A
   candidate must beat the current revision by ``bic_margin`` (a pair must also beat the
   best single effect by it) and cut the fit RMSE by ``min_improvement``; otherwise nothing
   is added and the report says so.
5. **Revision.** The chosen effects become a new model revision (the current one, predicting
   with its parent's solver: before and after compare one model form), every
   event is re-simulated with it, the flags are judged again with it (the baseline's flags
   take a fleet-wide misfit for weak brakes or failing sensors) and the effect is refitted on
   the events usable then, and the JSON report (and a Markdown report with plots
   beside it) gives the RMSE before and after on the fit and holdout events, computed from
   ``v_predictions`` exactly as an analyst would.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from fleetbrake.errors import ConfigError, FleetbrakeError
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import EFFECT_ORDER, EFFECTS, Effect, EffectSet
from fleetbrake.simulation.predictions import (
    Revision,
    SimulationConfig,
    WagonData,
    current_revision,
    load_wagon,
    model_for,
    predict_wagon,
    simulate_events,
    stored_wagons,
)
from fleetbrake.warehouse.connection import Warehouse, open_warehouse, sql

__all__ = [
    "CloseLoopConfig",
    "CloseLoopConfigError",
    "CloseLoopError",
    "close_loop",
    "run_close_loop",
]

logger = logging.getLogger(__name__)

CORRELATION_S = 30.0
"""Seconds per independent residual in the information criterion."""

ANOMALY_KINDS = ("dragging_brake", "weak_brake", "sensor_fault")


class CloseLoopError(FleetbrakeError, RuntimeError):
    """The closed loop cannot run (no events before the holdout date, no registry, ...)."""


class CloseLoopConfigError(ConfigError):
    """A close-loop configuration that cannot be used (the message names the key)."""


@dataclass(frozen=True)
class CloseLoopConfig:
    holdout_from: dt.date
    max_effects: int = 2
    bic_margin: float = 10.0
    """How much lower the criterion of a candidate must be than the current revision's."""
    min_improvement: float = 0.05
    """Relative cut of the fit RMSE a candidate must bring."""
    pair_above_noise: float = 1.3
    """Try pairs of effects when the best single leaves the fit RMSE above this many times
    the estimated sensor noise."""
    max_nfev: int = 14
    """Model evaluations per parameter fit (each re-simulates the fit events)."""
    screen_events: int = 60
    """Candidates are first fitted on at most this many fit events (spread evenly over the
    fit period); the best ones are then refitted on all of them."""
    refit: int = 2
    """How many of the screened candidates are refitted on every fit event."""
    reflag: bool = True
    """After adding an effect, judge the flags again with the new revision and refit on the
    events that are usable then (flags judged with a model that lacks the effect mistake a
    fleet-wide misfit for anomalies)."""
    settle_after_flag_s: float = 3600.0
    """Events starting less than this after the end of a brake or sensor-fault flag of their
    wagon are left out: the state carried out of the anomaly is still off (a weak braking
    leaves the simulated block ~0.8 K too warm at the sensor 25 min later)."""
    candidates: tuple[str, ...] | None = None
    """The effects to try, by vocabulary name (None: every effect of
    :data:`fleetbrake.model.effects.EFFECT_ORDER`)."""
    simulation: SimulationConfig = field(default_factory=SimulationConfig)

    def __post_init__(self) -> None:
        unknown = sorted(set(self.candidates or ()) - set(EFFECTS))
        if unknown:
            raise CloseLoopConfigError(
                f"candidates: unknown effect(s) {', '.join(unknown)}; the vocabulary is "
                f"{', '.join(EFFECTS)}"
            )

    def candidate_classes(self) -> tuple[type[Effect], ...]:
        """The effect classes to try, in :data:`EFFECT_ORDER`."""
        wanted = set(EFFECTS) if self.candidates is None else set(self.candidates)
        return tuple(cls for cls in EFFECT_ORDER if cls.name in wanted)


@dataclass
class Candidate:
    effects: EffectSet
    rmse_fit_k: float
    bic: float
    n_parameters: int
    rmse_holdout_k: float | None = None

    @property
    def label(self) -> str:
        return "+".join(e.name for e in self.effects) or "none"


# ---------------------------------------------------------------------------- evaluation
class _Evaluator:
    """Re-simulates a set of events with candidate effects (data loaded once), with the
    solver and mesh of the revision the candidates would become children of."""

    def __init__(
        self,
        wh: Warehouse,
        wagons: Mapping[str, WagonConfig],
        all_events: pl.DataFrame,
        events: pl.DataFrame,
        config: SimulationConfig,
        base: Revision,
        loaded: dict[tuple[str, float], WagonData] | None = None,
    ):
        """``loaded``: the wagons' data already read, by (wagon, ``bridge_max_s``), shared by
        the evaluators of one run (filled here): each wagon is read once per run."""
        self.config = config
        self.base = base
        self.parts = []
        loaded = {} if loaded is None else loaded
        for wagon_id in events["wagon_id"].unique(maintain_order=True).to_list():
            wagon = wagons.get(wagon_id)
            if wagon is None:
                continue
            todo = events.filter(pl.col("wagon_id") == wagon_id)["event_id"].to_list()
            key = (wagon_id, config.chain.bridge_max_s)
            if key not in loaded:
                loaded[key] = load_wagon(wh, wagon, config)
            self.parts.append(
                (model_for(wagon, base.solver, base.refinement), loaded[key], set(todo))
            )

    def frames(self, effects: EffectSet) -> pl.DataFrame:
        """The events' windows as the simulation stage predicts them (the one chain
        algorithm), with ``effects``."""
        rev = Revision("candidate", effects, self.base.solver, self.base.refinement)
        out = [
            predict_wagon(data, model, rev, self.config, event_ids=todo, timeline=False).predictions
            for model, data, todo in self.parts
        ]
        return pl.concat(out) if out else pl.DataFrame()

    def residual(self, effects: EffectSet) -> np.ndarray:
        return _finite_residual(self.frames(effects))


def _finite_residual(frame: pl.DataFrame) -> np.ndarray:
    """measured - predicted sensor temperature of every second where both are finite, in the
    frame's order."""
    if frame.height == 0:
        return np.zeros(0)
    r = (frame["measured_sensor_c"] - frame["predicted_sensor_c"]).to_numpy()
    return r[np.isfinite(r)]


RESIDUAL_KEY = ("event_id", "time_utc")
"""What identifies one residual: the event and the second."""


def _keyed_residual(frame: pl.DataFrame) -> pl.DataFrame:
    """measured - predicted sensor temperature (``residual_k``) by event and second, where
    both are known and finite."""
    if frame.height == 0:
        return pl.DataFrame(
            schema={"event_id": pl.String, "time_utc": pl.Datetime("us"), "residual_k": pl.Float64}
        )
    return frame.select(
        *RESIDUAL_KEY,
        residual_k=pl.col("measured_sensor_c") - pl.col("predicted_sensor_c"),
    ).filter(pl.col("residual_k").is_finite())


def _aligned(reference: pl.DataFrame, candidate: pl.DataFrame) -> np.ndarray:
    """The candidate's residual at each (event, second) of ``reference``, in its order; where
    the candidate has no residual (a prediction dropped), the reference's. A second the
    candidate gained is not scored: every candidate of one fit is scored on the same seconds,
    and a dropped one neither helps nor hurts it."""
    joined = reference.join(
        candidate.rename({"residual_k": "candidate_k"}),
        on=list(RESIDUAL_KEY),
        how="left",
        maintain_order="left",
    )
    return (
        joined.select(pl.coalesce("candidate_k", "residual_k"))
        .to_series()
        .to_numpy()
        .astype(np.float64)
    )


def _rmse(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")


def _bic(r: np.ndarray, k: int) -> float:
    n_eff = max(r.size / CORRELATION_S, k + 2.0)
    return n_eff * math.log(max(float(np.mean(r * r)), 1e-12)) + k * math.log(n_eff)


def _noise_k(frame: pl.DataFrame) -> float:
    """Sensor noise from the residual's second-to-second changes within each event."""
    diffs = (
        frame.with_columns(r=pl.col("measured_sensor_c") - pl.col("predicted_sensor_c"))
        .with_columns(d=pl.col("r").diff().over("event_id"))
        .get_column("d")
        .drop_nulls()
        .drop_nans()
        .to_numpy()
    )
    return float(np.std(diffs) / math.sqrt(2.0)) if diffs.size > 10 else float("nan")


def _fit(
    evaluator: _Evaluator,
    base: EffectSet,
    classes: Sequence[type[Effect]],
    start: Sequence[Effect] | None,
    max_nfev: int,
) -> tuple[EffectSet, np.ndarray]:
    """Fit the parameters of ``classes`` (added to ``base``) by bounded least squares."""
    from scipy.optimize import least_squares

    names: list[tuple[type[Effect], str]] = []
    x0, lo, hi, scale = [], [], [], []
    starting = {type(e): e for e in (start or [])}
    for cls in classes:
        for pname, (a, b) in cls.PARAMETER_RANGES.items():
            lim_lo, lim_hi = cls.LIMITS.get(pname, (None, None))
            names.append((cls, pname))
            init = starting[cls].parameters[pname] if cls in starting else 0.5 * (a + b)
            x0.append(init)
            lo.append(-np.inf if lim_lo is None else lim_lo)
            hi.append(np.inf if lim_hi is None else lim_hi)
            scale.append(b - a)

    def build(x: np.ndarray) -> EffectSet:
        params: dict[type[Effect], dict[str, float]] = {cls: {} for cls in classes}
        for (cls, pname), value in zip(names, x, strict=True):
            params[cls][pname] = float(value)
        effects = base
        for cls in classes:
            effects = effects.with_effect(cls.from_parameters(params[cls]))
        return effects

    # every evaluation is scored on the seconds of the starting point, matched by key: a
    # candidate that loses or gains a prediction is still compared second by second. Each
    # parameter vector is simulated once: the optimiser's first call (the starting point) and
    # the residual of its result (its last accepted point) are taken from what was computed.
    seen: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def evaluate(x: np.ndarray, reference: pl.DataFrame | None) -> pl.DataFrame:
        frame = evaluator.frames(build(x))
        keyed = _keyed_residual(frame)
        aligned = _aligned(keyed if reference is None else reference, keyed)
        seen[np.asarray(x, dtype=np.float64).tobytes()] = (aligned, _finite_residual(frame))
        return keyed

    reference = evaluate(np.asarray(x0, dtype=np.float64), None)

    def fun(x: np.ndarray) -> np.ndarray:
        key = np.asarray(x, dtype=np.float64).tobytes()
        if key not in seen:
            evaluate(x, reference)
        return seen[key][0]

    x_start = np.clip(np.asarray(x0), np.asarray(lo) + 1e-9, np.asarray(hi) - 1e-9)
    result = least_squares(
        fun,
        x_start,
        bounds=(lo, hi),
        x_scale=np.asarray(scale),
        diff_step=0.05,  # above simulate.H_QUANTUM_W_M2K's rounding of a varying h
        max_nfev=max_nfev,
        method="trf",
    )
    effects = build(result.x)
    done = seen.get(np.asarray(result.x, dtype=np.float64).tobytes())
    return effects, done[1] if done is not None else evaluator.residual(effects)


# ---------------------------------------------------------------------------- evidence
def _evidence(frame: pl.DataFrame) -> dict[str, Any]:
    """How the residual relates to what the model is driven by (fit events)."""
    f = (
        frame.filter(pl.col("measured_sensor_c").is_not_null())
        .with_columns(r=pl.col("measured_sensor_c") - pl.col("predicted_sensor_c"))
        .with_columns(
            rise=pl.col("predicted_sensor_c")
            - pl.col("predicted_sensor_c").first().over("event_id"),
            since_s=(
                pl.col("time_utc") - pl.col("time_utc").first().over("event_id")
            ).dt.total_seconds(),
        )
    )
    if f.height < 10:
        return {"seconds": f.height}
    out: dict[str, Any] = {"seconds": f.height, "events": f["event_id"].n_unique()}
    r = f["r"].to_numpy()
    out["mean_k"] = float(r.mean())
    out["rmse_k"] = _rmse(r)
    for phase in ("heating", "cooling"):
        part = f.filter(pl.col("phase") == phase)["r"].to_numpy()
        out[f"mean_{phase}_k"] = float(part.mean()) if part.size else None
    correlations = {}
    for name, col in [
        ("speed", "speed_kmh"),
        ("pressure", "brake_pressure_bar"),
        ("heat input", "flux_w_m2"),
        ("predicted heating", "rise"),
        ("ambient", "ambient_c"),
        ("time since activation", "since_s"),
    ]:
        x = f[col].to_numpy().astype(np.float64)
        ok = np.isfinite(x)
        if ok.sum() > 10 and np.std(x[ok]) > 0:
            correlations[name] = float(np.corrcoef(x[ok], r[ok])[0, 1])
    out["correlations"] = correlations
    return out


def _evidence_sentence(ev: Mapping[str, Any], noise_k: float) -> str:
    if "correlations" not in ev:
        return "too few valid seconds in the fit events to analyse the residual"
    strongest = sorted(ev["correlations"].items(), key=lambda kv: -abs(kv[1]))[:3]
    parts = ", ".join(f"{name} (r = {value:+.2f})" for name, value in strongest)
    return (
        f"over {ev['events']} fit events ({ev['seconds']} s) the residual (measured - "
        f"predicted) has RMSE {ev['rmse_k']:.3f} K against a sensor noise of {noise_k:.3f} K, "
        f"mean {ev['mean_heating_k'] or 0.0:+.3f} K while heating and "
        f"{ev['mean_cooling_k'] or 0.0:+.3f} K while cooling; it correlates most with {parts}"
    )


# ---------------------------------------------------------------------------- main
def _used_events(wh: Warehouse, revision: str, settle_after_flag_s: float) -> pl.DataFrame:
    """Events with predictions of ``revision``; column ``flagged``: whether the window
    overlaps a disturbance of its wagon or starts within ``settle_after_flag_s`` after one.
    Disturbances: the anomaly flags, and the windows of events cut by a data gap
    (``complete`` false: part of their heat input was never logged)."""
    return wh.con.sql(
        sql("q_closeloop_used_events"),
        params={"revision": revision, "settle_us": round(settle_after_flag_s * 1e6)},
    ).pl()


def _event_sets(
    wh: Warehouse, revision: str, config: CloseLoopConfig
) -> tuple[pl.DataFrame, pl.DataFrame, dict[str, list[str]]]:
    """The fit and holdout events the exclusion rule leaves (flags as they stand now), and
    the ids of every event of each set."""
    every = _used_events(wh, revision, config.settle_after_flag_s)
    cutoff = dt.datetime.combine(config.holdout_from, dt.time())
    before = pl.col("start_utc") < cutoff
    sets_all = {
        "fit": every.filter(before)["event_id"].to_list(),
        "holdout": every.filter(~before)["event_id"].to_list(),
    }
    used = every.filter(~pl.col("flagged"))
    return used.filter(before), used.filter(~before), sets_all


def rmse_from_predictions(wh: Warehouse, revision: str, event_ids: Sequence[str]) -> float:
    """RMSE over every second of these events' windows with a valid measurement."""
    ((value,),) = wh.con.execute(
        sql("q_closeloop_rmse"), {"revision": revision, "event_ids": [str(e) for e in event_ids]}
    ).fetchall()
    return float(value) if value is not None else float("nan")


def close_loop(wh: Warehouse, config: CloseLoopConfig) -> dict[str, Any]:
    """The closed loop on an open (writable) warehouse; returns the report (see module)."""
    wagons = stored_wagons(wh)
    if not wagons:
        raise CloseLoopError(f"{wh.path}: no registry stored: run `fleetbrake run` first")
    # the baseline keeps the solver and mesh it was made with; a database with no revision yet
    # gets the declared one as ``run`` would make it
    base = current_revision(wh, config.simulation.solver, config.simulation.refinement)
    fit, holdout, sets_all = _event_sets(wh, base.name, config)
    if fit.height == 0:
        raise CloseLoopError(
            f"{wh.path}: no unflagged event with predictions before {config.holdout_from}"
        )
    all_events = wh.con.sql(sql("q_closeloop_events")).pl()
    sim = config.simulation
    # candidates are simulated as the baseline's predictions were: with its solver
    loaded: dict[tuple[str, float], WagonData] = {}
    fit_eval = _Evaluator(wh, wagons, all_events, fit, sim, base, loaded)
    hold_eval = (
        _Evaluator(wh, wagons, all_events, holdout, sim, base, loaded) if holdout.height else None
    )

    base_frame = fit_eval.frames(base.effects)
    noise_k = _noise_k(base_frame)
    evidence = _evidence(base_frame)
    r_base = fit_eval.residual(base.effects)
    current = Candidate(base.effects, _rmse(r_base), _bic(r_base, 0), 0)

    # screening: every effect on a subset of the fit events, each from a uniform start at
    # its measured temperature (independent windows: a tenth of the cost of carrying the
    # state through whole sessions, and enough to rank effects)
    picks = np.linspace(0, fit.height - 1, min(config.screen_events, fit.height))
    screen_config = dataclasses.replace(sim, initial_state="uniform")
    screen_eval = _Evaluator(
        wh,
        wagons,
        all_events,
        fit[np.unique(picks.round().astype(int))],
        screen_config,
        base,
        loaded,
    )
    screened: list[Candidate] = []
    present = {type(e) for e in base.effects}
    for cls in config.candidate_classes():
        if cls in present:
            continue
        effects, r = _fit(screen_eval, base.effects, [cls], None, config.max_nfev)
        k = len(cls.PARAMETER_RANGES)
        screened.append(Candidate(effects, _rmse(r), _bic(r, k), k))
        logger.debug("screened %s: %s rmse %.4f K", cls.name, effects, screened[-1].rmse_fit_k)
    screened.sort(key=lambda c: c.bic)
    # refit the best on every fit event, from the screened parameters
    candidates: list[Candidate] = []
    for c in screened:
        if len(candidates) < config.refit:
            added = [e for e in c.effects if type(e) not in present]
            classes = [type(e) for e in added]
            effects, r = _fit(fit_eval, base.effects, classes, added, max(4, config.max_nfev // 2))
            candidates.append(Candidate(effects, _rmse(r), _bic(r, c.n_parameters), c.n_parameters))
            logger.debug("refitted %s: %s rmse %.4f K", c.label, effects, candidates[-1].rmse_fit_k)
        else:
            r = fit_eval.residual(c.effects)
            candidates.append(
                Candidate(c.effects, _rmse(r), _bic(r, c.n_parameters), c.n_parameters)
            )
    candidates.sort(key=lambda c: c.bic)
    best = candidates[0] if candidates else None
    if (
        best is not None
        and config.max_effects >= 2
        and best.rmse_fit_k > config.pair_above_noise * noise_k
    ):
        first = [e for e in best.effects if type(e) not in present]
        pairs: list[Candidate] = []
        for cls in config.candidate_classes():
            if cls in present or cls in {type(e) for e in first}:
                continue
            classes = [type(first[0]), cls]
            effects, r = _fit(screen_eval, base.effects, classes, first, config.max_nfev)
            k = best.n_parameters + len(cls.PARAMETER_RANGES)
            pairs.append(Candidate(effects, _rmse(r), _bic(r, k), k))
            logger.debug("screened pair %s: rmse %.4f K", pairs[-1].label, pairs[-1].rmse_fit_k)
        if pairs:
            top = min(pairs, key=lambda c: c.bic)
            added = [e for e in top.effects if type(e) not in present]
            effects, r = _fit(
                fit_eval, base.effects, [type(e) for e in added], added, config.max_nfev // 2
            )
            candidates.append(
                Candidate(effects, _rmse(r), _bic(r, top.n_parameters), top.n_parameters)
            )
            logger.debug(
                "refitted pair %s: rmse %.4f K", candidates[-1].label, candidates[-1].rmse_fit_k
            )
        candidates.sort(key=lambda c: c.bic)
        best = candidates[0]
        # a pair must beat the best single effect by the margin too
        singles = [c for c in candidates if len(c.effects) - len(present) == 1]
        if best not in singles and singles and best.bic > singles[0].bic - config.bic_margin:
            best = singles[0]
    if hold_eval is not None:
        for c in candidates:
            c.rmse_holdout_k = _rmse(hold_eval.residual(c.effects))

    significant = (
        best is not None
        and best.bic < current.bic - config.bic_margin
        and best.rmse_fit_k < (1.0 - config.min_improvement) * current.rmse_fit_k
    )
    report: dict[str, Any] = {
        "baseline_revision": base.name,
        "new_revision": None,
        "effect": None,
        "parameters": {},
        "evidence": _evidence_sentence(evidence, noise_k),
        "fit": {"events": fit.height},
        "holdout": {"events": holdout.height},
        "candidates": [
            {
                "effect": c.label,
                "parameters": {e.name: e.parameters for e in c.effects if type(e) not in present},
                "rmse_fit_k": round(c.rmse_fit_k, 5),
                "rmse_holdout_k": None if c.rmse_holdout_k is None else round(c.rmse_holdout_k, 5),
                "score": round(current.bic - c.bic, 3),
            }
            for c in candidates
        ],
        "noise_k": round(noise_k, 5),
        "flags_judged_with": base.name,
        "solver": base.solver,
        "residual": evidence,
        "selection": (
            f"Bayesian information criterion on the fit events (one independent residual per "
            f"{CORRELATION_S:.0f} s); score = improvement over the baseline; a candidate must "
            f"score above {config.bic_margin} and cut the fit RMSE by "
            f"{100 * config.min_improvement:.0f} %. The holdout is never used to choose."
        ),
        "exclusion": "events whose window overlaps a dragging_brake, weak_brake or "
        "sensor_fault flag of their wagon or the window of one of its events cut by a data gap "
        f"(incomplete), or starts less than {config.settle_after_flag_s:.0f} s after one ends, "
        "are left out of fit and holdout; events_all and rmse_*_all_k count every event of the "
        "set",
    }
    fit_ids = fit["event_id"].to_list()
    hold_ids = holdout["event_id"].to_list()
    if not significant or best is None:
        report["evidence"] += (
            "; no candidate effect explains a significant part of it: nothing was added"
        )
        for key, ids in (("fit", fit_ids), ("holdout", hold_ids)):
            value = rmse_from_predictions(wh, base.name, ids) if ids else None
            report[key].update({"rmse_before_k": value, "rmse_after_k": value})
        _add_all_events(wh, report, sets_all, base.name, base.name)
        return report

    added = [e for e in best.effects if type(e) not in present]
    name = _new_revision_name(wh, best.label)
    _record_revision(wh, name, base, best)
    new_rev = Revision(name, best.effects, base.solver, base.refinement)
    simulate_events(wh, wagons, new_rev, sim, event_ids=all_events["event_id"].to_list())
    if config.reflag:
        # the flags were judged with the baseline, which lacks the effect: a fleet-wide misfit
        # looks like weak brakes or failing sensors. Judge them again with the new revision,
        # and refit on the events that are usable now.
        _reflag(wh, wagons, new_rev, sim)
        fit, holdout, _ = _event_sets(wh, base.name, config)
        if fit.height and set(fit["event_id"].to_list()) != set(fit_ids):
            refit_eval = _Evaluator(wh, wagons, all_events, fit, sim, base, loaded)
            effects, r = _fit(
                refit_eval, base.effects, [type(e) for e in added], added, config.max_nfev // 2
            )
            logger.debug("refitted on %d events after re-flagging: %s", fit.height, effects)
            best = Candidate(effects, _rmse(r), _bic(r, best.n_parameters), best.n_parameters)
            added = [e for e in best.effects if type(e) not in present]
            _set_revision_effects(wh, name, best.effects)
            new_rev = Revision(name, best.effects, base.solver, base.refinement)
            simulate_events(wh, wagons, new_rev, sim, event_ids=all_events["event_id"].to_list())
            _reflag(wh, wagons, new_rev, sim)
            fit, holdout, _ = _event_sets(wh, base.name, config)
        fit_ids = fit["event_id"].to_list()
        hold_ids = holdout["event_id"].to_list()
        report["fit"]["events"] = len(fit_ids)
        report["holdout"]["events"] = len(hold_ids)
        report["flags_judged_with"] = name
    rmse = {
        (key, rev): rmse_from_predictions(wh, rev, idset) if idset else None
        for key, idset in (("fit", fit_ids), ("holdout", hold_ids))
        for rev in (base.name, name)
    }
    wh.con.execute(
        sql("q_closeloop_set_revision_rmse"),
        {
            "name": name,
            "rmse_fit_k": rmse[("fit", name)],
            "rmse_holdout_k": rmse[("holdout", name)],
        },
    )
    report.update(
        {
            "new_revision": name,
            "effect": best.label,
            "parameters": {k: v for e in added for k, v in e.parameters.items()},
            "effects": [e.to_dict() for e in added],
        }
    )
    for key in ("fit", "holdout"):
        report[key].update(
            {"rmse_before_k": rmse[(key, base.name)], "rmse_after_k": rmse[(key, name)]}
        )
    _add_all_events(wh, report, sets_all, base.name, name)
    return report


def _add_all_events(
    wh: Warehouse, report: dict[str, Any], sets: Mapping[str, list[str]], before: str, after: str
) -> None:
    """The RMSE over every event of the fit and holdout sets, flagged ones included."""
    for key, ids in sets.items():
        report[key].update(
            {
                "events_all": len(ids),
                "rmse_before_all_k": rmse_from_predictions(wh, before, ids) if ids else None,
                "rmse_after_all_k": rmse_from_predictions(wh, after, ids) if ids else None,
            }
        )


def _reflag(
    wh: Warehouse, wagons: Mapping[str, WagonConfig], revision: Revision, sim: SimulationConfig
) -> None:
    """Judge every wagon's flags again with ``revision``: the simulation stage's flow, its
    timeline simulated and stored first (nothing to do for a wagon already simulated with it
    from the same data), then the flags judged from what was stored."""
    from fleetbrake.flags import raise_flags

    simulate_events(wh, wagons, revision, sim, progress=False)
    raise_flags(wh, wagons, revision.name)


def _set_revision_effects(wh: Warehouse, name: str, effects: EffectSet) -> None:
    wh.con.execute(
        sql("q_closeloop_set_revision_effects"),
        {"name": name, "parameters_json": json.dumps({"effects": effects.to_list()})},
    )


def _new_revision_name(wh: Warehouse, label: str) -> str:
    ((count,),) = wh.con.execute(sql("q_closeloop_revision_count")).fetchall()
    return f"r{count}-{label}"


def _record_revision(wh: Warehouse, name: str, parent: Revision, best: Candidate) -> None:
    """Record ``best`` as revision ``name``, the current one, child of ``parent``, predicting
    with the parent's solver (a closed loop changes the effects, never the model form)."""
    now = dt.datetime.now(dt.UTC).replace(tzinfo=None)
    with wh.transaction() as con:
        con.execute(sql("q_closeloop_clear_current"))
        con.execute(
            sql("q_closeloop_insert_revision"),
            {
                "name": name,
                "parent": parent.name,
                "effect": best.label,
                "parameters_json": json.dumps({"effects": best.effects.to_list()}),
                "solver": parent.solver,
                "refinement": parent.refinement,
                "created_utc": now,
            },
        )


def run_close_loop(
    db_path: str | Path,
    holdout_from: dt.date,
    json_out: str | Path,
    *,
    wait_s: float = 0.0,
    config: CloseLoopConfig | None = None,
) -> dict[str, Any]:
    """``fleetbrake close-loop``: run, write the JSON report and the Markdown report."""
    config = config or CloseLoopConfig(holdout_from=holdout_from)
    with open_warehouse(db_path, wait_s=wait_s) as wh:
        report = close_loop(wh, config)
        json_out = Path(json_out)
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(report, indent=2, default=str) + "\n", encoding="utf-8")
        from fleetbrake.closeloop.report import write_markdown_report

        write_markdown_report(wh, report, json_out.with_suffix(".md"))
    return report
