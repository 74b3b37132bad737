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
3. **Candidates.** Every effect of :mod:`fleetbrake.model.effects`, acting where it acts
   physically, its parameters fitted by bounded least squares on the per-second residual of
   the fit events (each evaluation re-simulates them, carried state and all); then, when
   one effect leaves the fit clearly above the noise, pairs with the best.
4. **Choice** (never looks at the holdout): the Bayesian information criterion on an
   effective sample size (one independent residual per ``CORRELATION_S`` seconds: the
   residual of a missing effect is smooth, so the seconds are far from independent). A
   candidate must beat the current revision by ``bic_margin`` (a pair must also beat the
   best single effect by it) and cut the fit RMSE by ``min_improvement``; otherwise nothing
   is added and the report says so.
5. **Revision.** The chosen effects become a new model revision (the current one), every
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
import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from fleetbrake.errors import FleetbrakeError
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import EFFECT_ORDER, Effect, EffectSet
from fleetbrake.simulation.predictions import (
    Revision,
    SimulationConfig,
    SimulationReport,
    _simulate_wagon,
    current_revision,
    load_chains,
    model_for,
    simulate_events,
    stored_wagons,
)
from fleetbrake.warehouse.connection import Warehouse, open_warehouse

__all__ = ["CloseLoopConfig", "CloseLoopError", "close_loop", "run_close_loop"]

CORRELATION_S = 30.0
"""Seconds per independent residual in the information criterion."""

ANOMALY_KINDS = ("dragging_brake", "weak_brake", "sensor_fault")


class CloseLoopError(FleetbrakeError, RuntimeError):
    """The closed loop cannot run (no events before the holdout date, no registry, ...)."""


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
    simulation: SimulationConfig = field(default_factory=SimulationConfig)


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
    """Re-simulates a set of events with candidate effects (data loaded once)."""

    def __init__(
        self,
        wh: Warehouse,
        wagons: Mapping[str, WagonConfig],
        all_events: pl.DataFrame,
        events: pl.DataFrame,
        config: SimulationConfig,
    ):
        self.config = config
        self.parts = []
        for wagon_id in events["wagon_id"].unique(maintain_order=True).to_list():
            wagon = wagons.get(wagon_id)
            if wagon is None:
                continue
            todo = events.filter(pl.col("wagon_id") == wagon_id)
            self.parts.append(
                (
                    wagon,
                    model_for(wagon, "rom", config.refinement),
                    all_events.filter(pl.col("wagon_id") == wagon_id),
                    todo,
                    load_chains(wh, wagon_id, todo, config),
                )
            )
        self.wh = wh

    def frames(self, effects: EffectSet) -> pl.DataFrame:
        rev = Revision("candidate", effects)
        out = []
        for wagon, rom, wagon_events, todo, wagon_chains in self.parts:
            out += _simulate_wagon(
                self.wh,
                wagon,
                rom,
                rev,
                wagon_events,
                todo,
                self.config,
                SimulationReport(),
                wagon_chains,
            )
        return pl.concat(out) if out else pl.DataFrame()

    def residual(self, effects: EffectSet) -> np.ndarray:
        frame = self.frames(effects)
        if frame.height == 0:
            return np.zeros(0)
        r = (frame["measured_sensor_c"] - frame["predicted_sensor_c"]).to_numpy()
        return r[np.isfinite(r)]


def _debug(message: str) -> None:
    if os.environ.get("FLEETBRAKE_DEBUG"):
        print(f"[close-loop {time.strftime('%H:%M:%S')}] {message}", flush=True)


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

    reference = evaluator.residual(build(np.asarray(x0)))

    def fun(x: np.ndarray) -> np.ndarray:
        r = evaluator.residual(build(x))
        if r.size != reference.size:  # a window lost or gained samples: compare like sizes
            r = np.resize(r, reference.size)
        return r

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
    return effects, evaluator.residual(effects)


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
        """
        WITH windows AS (
            SELECT event_id, wagon_id, min(time_utc) AS t0, max(time_utc) AS t1
            FROM predictions WHERE model_revision = $rev GROUP BY event_id, wagon_id
        ),
        disturbances AS (
            SELECT wagon_id, start_utc AS d0, end_utc AS d1 FROM flags
            WHERE kind IN ('dragging_brake', 'weak_brake', 'sensor_fault')
            UNION ALL
            SELECT w.wagon_id, w.t0, w.t1 FROM windows w JOIN events e USING (event_id)
            WHERE NOT e.complete
        ),
        flagged AS (
            SELECT DISTINCT w.event_id
            FROM windows w JOIN disturbances d
              ON d.wagon_id = w.wagon_id AND d.d0 <= w.t1
             AND d.d1 + to_microseconds(CAST($settle_us AS BIGINT)) >= w.t0
        )
        SELECT e.event_id, e.wagon_id, e.start_utc, e.end_utc, e.detected_utc,
               e.event_id IN (SELECT event_id FROM flagged) AS flagged
        FROM events e JOIN windows w USING (event_id)
        ORDER BY e.wagon_id, e.start_utc
        """,
        params={"rev": revision, "settle_us": round(settle_after_flag_s * 1e6)},
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
    ids = pl.DataFrame({"event_id": list(event_ids)}, schema={"event_id": pl.String})
    wh.con.register("fb_rmse_ids", ids)
    try:
        ((value,),) = wh.con.execute(
            "SELECT sqrt(avg(power(measured_sensor_c - predicted_sensor_c, 2))) "
            "FROM v_predictions WHERE model_revision = $rev "
            "AND measured_sensor_c IS NOT NULL "
            "AND event_id IN (SELECT event_id FROM fb_rmse_ids)",
            {"rev": revision},
        ).fetchall()
    finally:
        wh.con.unregister("fb_rmse_ids")
    return float(value) if value is not None else float("nan")


def close_loop(wh: Warehouse, config: CloseLoopConfig) -> dict[str, Any]:
    """The closed loop on an open (writable) warehouse; returns the report (see module)."""
    wagons = stored_wagons(wh)
    if not wagons:
        raise CloseLoopError(f"{wh.path}: no registry stored: run `fleetbrake run` first")
    base = current_revision(wh)
    fit, holdout, sets_all = _event_sets(wh, base.name, config)
    if fit.height == 0:
        raise CloseLoopError(
            f"{wh.path}: no unflagged event with predictions before {config.holdout_from}"
        )
    all_events = wh.con.sql(
        "SELECT event_id, wagon_id, start_utc, end_utc FROM events ORDER BY wagon_id, start_utc"
    ).pl()
    sim = config.simulation
    fit_eval = _Evaluator(wh, wagons, all_events, fit, sim)
    hold_eval = _Evaluator(wh, wagons, all_events, holdout, sim) if holdout.height else None

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
        wh, wagons, all_events, fit[np.unique(picks.round().astype(int))], screen_config
    )
    screened: list[Candidate] = []
    present = {type(e) for e in base.effects}
    for cls in EFFECT_ORDER:
        if cls in present:
            continue
        effects, r = _fit(screen_eval, base.effects, [cls], None, config.max_nfev)
        k = len(cls.PARAMETER_RANGES)
        screened.append(Candidate(effects, _rmse(r), _bic(r, k), k))
        _debug(f"screened {cls.name}: {effects} rmse {screened[-1].rmse_fit_k:.4f}")
    screened.sort(key=lambda c: c.bic)
    # refit the best on every fit event, from the screened parameters
    candidates: list[Candidate] = []
    for c in screened:
        if len(candidates) < config.refit:
            added = [e for e in c.effects if type(e) not in present]
            classes = [type(e) for e in added]
            effects, r = _fit(fit_eval, base.effects, classes, added, max(4, config.max_nfev // 2))
            candidates.append(Candidate(effects, _rmse(r), _bic(r, c.n_parameters), c.n_parameters))
            _debug(f"refitted {c.label}: {effects} rmse {candidates[-1].rmse_fit_k:.4f}")
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
        for cls in EFFECT_ORDER:
            if cls in present or cls in {type(e) for e in first}:
                continue
            classes = [type(first[0]), cls]
            effects, r = _fit(screen_eval, base.effects, classes, first, config.max_nfev)
            k = best.n_parameters + len(cls.PARAMETER_RANGES)
            pairs.append(Candidate(effects, _rmse(r), _bic(r, k), k))
            _debug(f"screened pair {pairs[-1].label}: rmse {pairs[-1].rmse_fit_k:.4f}")
        if pairs:
            top = min(pairs, key=lambda c: c.bic)
            added = [e for e in top.effects if type(e) not in present]
            effects, r = _fit(
                fit_eval, base.effects, [type(e) for e in added], added, config.max_nfev // 2
            )
            candidates.append(
                Candidate(effects, _rmse(r), _bic(r, top.n_parameters), top.n_parameters)
            )
            _debug(f"refitted pair {candidates[-1].label}: rmse {candidates[-1].rmse_fit_k:.4f}")
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
    _record_revision(wh, name, base.name, best)
    new_rev = Revision(name, best.effects)
    simulate_events(wh, wagons, new_rev, sim, event_ids=all_events["event_id"].to_list())
    if config.reflag:
        # the flags were judged with the baseline, which lacks the effect: a fleet-wide misfit
        # looks like weak brakes or failing sensors. Judge them again with the new revision,
        # and refit on the events that are usable now.
        _reflag(wh, wagons, name, sim)
        fit, holdout, _ = _event_sets(wh, base.name, config)
        if fit.height and set(fit["event_id"].to_list()) != set(fit_ids):
            refit_eval = _Evaluator(wh, wagons, all_events, fit, sim)
            effects, r = _fit(
                refit_eval, base.effects, [type(e) for e in added], added, config.max_nfev // 2
            )
            _debug(f"refitted on {fit.height} events after re-flagging: {effects}")
            best = Candidate(effects, _rmse(r), _bic(r, best.n_parameters), best.n_parameters)
            added = [e for e in best.effects if type(e) not in present]
            _set_revision_effects(wh, name, best.effects)
            new_rev = Revision(name, best.effects)
            simulate_events(wh, wagons, new_rev, sim, event_ids=all_events["event_id"].to_list())
            _reflag(wh, wagons, name, sim)
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
        "UPDATE model_revisions SET rmse_fit_k = $fit, rmse_holdout_k = $hold "
        "WHERE model_revision = $name",
        {"fit": rmse[("fit", name)], "hold": rmse[("holdout", name)], "name": name},
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
    wh: Warehouse, wagons: Mapping[str, WagonConfig], revision: str, sim: SimulationConfig
) -> None:
    """Judge every wagon's flags again with ``revision`` (the model its predictions came
    from)."""
    from fleetbrake.flags.detect import raise_flags

    raise_flags(wh, wagons, revision, refinement=sim.refinement)


def _set_revision_effects(wh: Warehouse, name: str, effects: EffectSet) -> None:
    wh.con.execute(
        "UPDATE model_revisions SET parameters_json = $params WHERE model_revision = $name",
        {"params": json.dumps({"effects": effects.to_list()}), "name": name},
    )


def _new_revision_name(wh: Warehouse, label: str) -> str:
    ((count,),) = wh.con.execute("SELECT count(*) FROM model_revisions").fetchall()
    return f"r{count}-{label}"


def _record_revision(wh: Warehouse, name: str, parent: str, best: Candidate) -> None:
    now = dt.datetime.now(dt.UTC).replace(tzinfo=None)
    wh.con.execute("BEGIN TRANSACTION")
    try:
        wh.con.execute("UPDATE model_revisions SET is_current = FALSE")
        wh.con.execute(
            "INSERT INTO model_revisions VALUES "
            "($name, $parent, $effect, $params, NULL, NULL, 'rom', TRUE, $now)",
            {
                "name": name,
                "parent": parent,
                "effect": best.label,
                "params": json.dumps({"effects": best.effects.to_list()}),
                "now": now,
            },
        )
        wh.con.execute("COMMIT")
    except BaseException:
        wh.con.execute("ROLLBACK")
        raise


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
