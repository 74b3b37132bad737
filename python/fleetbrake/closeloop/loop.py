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
   The sensor noise is estimated from the residual itself (its second differences within
   each event window, :func:`~fleetbrake.closeloop.selection.noise_from_residual`: model
   errors are smooth, the thermistor's noise is white).
3. **Candidates.** The fit events are cached as arrays once
   (:class:`~fleetbrake.closeloop.fitdata.FitData`: the chains' pieces and declared loading;
   an evaluation applies the effects in numpy and runs each span's chain in one kernel call,
   the same predictions as the simulation stage's). Every effect of
   :mod:`fleetbrake.model.effects` (or those of ``CloseLoopConfig.candidates``; a
   ``fallback`` law such as ``empirical`` only last, when nothing physical is adequate),
   acting where it acts physically, has its parameters fitted by bounded least squares (trf)
   on the per-second residual, the forward-difference Jacobian's perturbed vectors evaluated
   together; each evaluation is scored on the starting point's seconds (where a candidate
   predicts nothing, the start's residual), carried state and all, with the baseline
   revision's solver. Candidates are fitted in parallel on the engine's workers (the data
   read by each worker once): first on the screening events (the earliest of each wagon:
   short chains), the best then on every fit event from its screened parameters (the next
   ones, up to ``refit``, too when within ``bic_margin`` of it); when the best leaves the fit
   clearly above the noise, pairs seeded from it. Fit events whose residual under the best
   screened effect is far above the bulk (data the flags missed) are left out of every fit
   on the fit events and of the verdict as outliers (report: ``outliers``).
4. **Choice** (never looks at the holdout): the Bayesian information criterion on the
   effective sample size of the baseline residual
   (:func:`~fleetbrake.closeloop.selection.effective_sample_size`: its autocorrelation
   within wagon-days; the residual of a missing effect is smooth, so the seconds are far
   from independent). A candidate must beat the current revision by ``bic_margin`` (a pair
   must also beat the best single effect by it) and cut the fit RMSE by
   ``min_improvement``; otherwise nothing is added and the report says so. The chosen
   model's residual is judged against the noise (``adequate``, ``unexplained``) and its
   parameters get 95 % intervals from the Jacobian (``parameter_intervals``).
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
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import polars as pl

from fleetbrake.closeloop import fitdata
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.selection import (
    Adequacy,
    SelectionError,
    adequacy,
    effective_sample_size,
    event_rms,
    information_criterion,
    intervals_for_json,
    noise_from_residual,
    outlier_events,
    parameter_intervals,
)
from fleetbrake.engine import Engine, InlineEngine, LocalEngine, make_engine
from fleetbrake.errors import ConfigError, FleetbrakeError
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import EFFECT_ORDER, EFFECTS, Effect, EffectSet
from fleetbrake.simulation.estimates import (
    EstimationConfig,
    estimate_wagons,
    fit_revision_noise,
)
from fleetbrake.simulation.predictions import (
    Revision,
    SimulationConfig,
    WagonData,
    current_revision,
    load_wagon,
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
    """Model evaluations per parameter fit (each re-simulates the fit events; the Jacobian's
    perturbed vectors not counted)."""
    diff_step: float = 0.05
    """Relative forward-difference step of the Jacobian (above ``H_QUANTUM_W_M2K``'s rounding
    of a varying convection)."""
    screen_events: int = 60
    """Candidates are first fitted on at most this many fit events (the earliest of each
    wagon in turn: their chains are short); the best ones are then refitted on all of them."""
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
    outlier_noise_factor: float = 5.0
    """Events whose residual RMS under the best screened single effect is above this many
    times the sensor noise ..."""
    outlier_z: float = 5.0
    """... and this many robust standard deviations above the events' median are left out of
    the fit as outliers (:func:`~fleetbrake.closeloop.selection.outlier_events`)."""
    max_outlier_fraction: float = 0.05
    """At most this share of the fit events is left out as outliers (0: none)."""
    refit_changed_fraction: float = 0.02
    """After re-flagging, the effect is refitted only when the fit set changed by at least
    this share of its events."""
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
        # a fallback (``empirical``) only when named: the method tries it last
        return tuple(
            cls
            for cls in EFFECT_ORDER
            if cls.name in wanted and (self.candidates is not None or not cls.fallback)
        )


@dataclass
class Candidate:
    effects: EffectSet
    rmse_fit_k: float
    bic: float
    n_parameters: int
    rmse_holdout_k: float | None = None
    fitted: FitResult | None = None
    fitted_on: str = "fit"
    """``fit``: every fit event; ``screen``: the screening events only."""

    @property
    def label(self) -> str:
        return "+".join(e.name for e in self.effects) or "none"


# ---------------------------------------------------------------------------- evaluation
class Evaluator(Protocol):
    """What a fit evaluates: measured - predicted at fixed seconds for each effect set (NaN
    where a candidate predicts nothing); :class:`~fleetbrake.closeloop.fitdata.FitData`."""

    def residuals(self, effect_sets: Sequence[EffectSet]) -> list[np.ndarray]: ...


def _rmse(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")


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


@dataclass(frozen=True)
class FitResult:
    """A candidate's parameters fitted: its effects, its own residual (every second it
    predicts), the residual at the starting point's seconds (what candidates are compared
    on) with the Jacobian there, the parameter vector and names (``effect.parameter``)."""

    effects: EffectSet
    residual: np.ndarray
    aligned: np.ndarray
    jacobian: np.ndarray
    x: np.ndarray
    names: tuple[str, ...]
    evaluations: int
    scored: np.ndarray
    """(evaluator seconds) which seconds ``aligned`` and the Jacobian's rows are."""
    kernel_calls: int = 0

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(name.split(".", 1)[1] for name in self.names)


def _steps(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, rel: float) -> np.ndarray:
    """Forward-difference steps as scipy's ``2-point`` scheme takes them (``rel |x|``, the
    sign of x, a step that would cross a bound turned round or cut to the farther bound)."""
    sign = np.where(x >= 0, 1.0, -1.0)
    h = rel * sign * np.abs(x)
    h = np.where(h == 0.0, rel * sign * np.maximum(1.0, np.abs(x)), h)
    h = (x + h) - x
    lb_dist, ub_dist = x - lo, hi - x
    violated = (x + h < lo) | (x + h > hi)
    fitting = np.abs(h) <= np.maximum(lb_dist, ub_dist)
    h = np.where(violated & fitting, -h, h)
    forward = violated & ~fitting & (ub_dist >= lb_dist)
    backward = violated & ~fitting & (ub_dist < lb_dist)
    h = np.where(forward, ub_dist, h)
    return np.where(backward, -lb_dist, h)


def _fit(
    evaluator: Evaluator,
    base: EffectSet,
    classes: Sequence[type[Effect]],
    start: Sequence[Effect] | None,
    max_nfev: int,
    diff_step: float = 0.05,
    keep: np.ndarray | None = None,
) -> FitResult:
    """Fit the parameters of ``classes`` (added to ``base``) by bounded least squares (trf),
    the Jacobian by forward differences with every perturbed vector of a step evaluated in
    one pass over the cached data (``evaluator.residuals``). ``keep``: (evaluator seconds)
    the seconds fitted and scored (None: all; outlier events left out)."""
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
    lower, upper = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)

    def build(x: np.ndarray) -> EffectSet:
        params: dict[type[Effect], dict[str, float]] = {cls: {} for cls in classes}
        for (cls, pname), value in zip(names, x, strict=True):
            params[cls][pname] = float(value)
        effects = base
        for cls in classes:
            effects = effects.with_effect(cls.from_parameters(params[cls]))
        return effects

    # every parameter vector is simulated once (the optimiser's first call is the starting
    # point, the fit's residual its last accepted point); each is scored on the seconds the
    # starting point predicts: where a candidate predicts nothing, the start's residual
    seen: dict[bytes, np.ndarray] = {}

    def raw_many(xs: Sequence[np.ndarray]) -> list[np.ndarray]:
        keys = [np.asarray(x, dtype=np.float64).tobytes() for x in xs]
        todo = {k: x for k, x in zip(keys, xs, strict=True) if k not in seen}
        if todo:
            got = evaluator.residuals([build(x) for x in todo.values()])
            seen.update(zip(todo, got, strict=True))
        return [seen[k] for k in keys]

    r0 = raw_many([np.asarray(x0, dtype=np.float64)])[0]
    kept = np.ones(r0.size, dtype=bool) if keep is None else np.asarray(keep, dtype=bool)
    scored = np.isfinite(r0) & kept
    reference = r0[scored]

    def aligned(r: np.ndarray) -> np.ndarray:
        out = r[scored]
        missing = ~np.isfinite(out)
        if missing.any():
            out = np.where(missing, reference, out)
        return out

    def fun(x: np.ndarray) -> np.ndarray:
        return aligned(raw_many([x])[0])

    def jac(x: np.ndarray) -> np.ndarray:
        f0 = fun(x)
        h = _steps(np.asarray(x, dtype=np.float64), lower, upper, diff_step)
        moved = [x + np.eye(x.size)[j] * h[j] for j in range(x.size)]
        columns = [(aligned(r) - f0) / h[j] for j, r in enumerate(raw_many(moved))]
        return np.column_stack(columns) if columns else np.zeros((f0.size, 0))

    x_start = np.clip(np.asarray(x0), lower + 1e-9, upper - 1e-9)
    result = least_squares(
        fun,
        x_start,
        jac=jac,
        bounds=(lower, upper),
        x_scale=np.asarray(scale),
        max_nfev=max_nfev,
        method="trf",
    )
    x = np.asarray(result.x, dtype=np.float64)
    r = raw_many([x])[0]
    return FitResult(
        effects=build(x),
        residual=r[np.isfinite(r) & kept],
        aligned=aligned(r),
        jacobian=np.asarray(result.jac, dtype=np.float64),
        x=x,
        names=tuple(f"{cls.name}.{pname}" for cls, pname in names),
        evaluations=len(seen),
        scored=scored,
    )


@dataclass(frozen=True)
class FitTask:
    """One candidate's fit, for an engine's worker: the data (or where :func:`fitdata.store`
    wrote it), the effects to add and where to start."""

    data: FitData | str
    base: EffectSet
    classes: tuple[type[Effect], ...]
    start: tuple[Effect, ...] | None
    max_nfev: int
    diff_step: float
    exclude: frozenset[str] = frozenset()
    """Events left out of the fit (outliers)."""

    def __str__(self) -> str:  # how an engine names the partition in an error
        return "candidate " + "+".join(cls.name for cls in self.classes)


def fit_task(task: FitTask) -> FitResult:
    """Run one :class:`FitTask` (a pure function of it: picklable, for the workers)."""
    data = task.data if isinstance(task.data, FitData) else fitdata.stored(task.data)
    calls = fitdata.kernel_calls()
    keep = _kept_seconds(data, task.exclude)
    fitted = _fit(data, task.base, task.classes, task.start, task.max_nfev, task.diff_step, keep)
    return dataclasses.replace(fitted, kernel_calls=fitdata.kernel_calls() - calls)


def _kept_seconds(data: FitData, exclude: frozenset[str]) -> np.ndarray | None:
    """(seconds of ``data``) whether each second's event is not in ``exclude``; None: all."""
    gone = [i for i, event_id in enumerate(data.event_ids) if event_id in exclude]
    return ~np.isin(data.event, gone) if gone else None


@dataclass(frozen=True)
class EvalTask:
    """Residuals of effect sets on some data (a candidate's holdout residual)."""

    data: FitData | str
    effect_sets: tuple[EffectSet, ...]

    def __str__(self) -> str:
        return "evaluation of " + ", ".join(str(e) or "none" for e in self.effect_sets)


def eval_task(task: EvalTask) -> tuple[list[np.ndarray], int]:
    """Run one :class:`EvalTask`: the residuals, and the kernel calls they took."""
    data = task.data if isinstance(task.data, FitData) else fitdata.stored(task.data)
    calls = fitdata.kernel_calls()
    return data.residuals(list(task.effect_sets)), fitdata.kernel_calls() - calls


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


def _screen_events(fit: pl.DataFrame, count: int) -> pl.DataFrame:
    """The screening subset: the earliest fit events of each wagon, taken in turn across the
    wagons (its first, then its second, ...) up to ``count`` events. Each wagon's chain is
    simulated only up to its last chosen window: early events keep the chains short."""
    if fit.height <= count:
        return fit
    ranked = fit.with_columns(_rank=pl.col("start_utc").rank("ordinal").over("wagon_id")).sort(
        "_rank", "start_utc"
    )
    return ranked.head(count).drop("_rank").sort("wagon_id", "start_utc")


class _Workers:
    """Where a run's fits go: the engine (the inline one when none), and the data it is
    handed. The local engine's workers read each data set once from a file this run writes
    (:func:`fitdata.store`), the inline engine uses the objects, Ray gets them with the
    task."""

    def __init__(self, engine: Engine | None) -> None:
        self.engine = engine
        self.files = isinstance(engine, LocalEngine)
        self._dir: tempfile.TemporaryDirectory[str] | None = None
        self._refs: dict[int, FitData | str] = {}
        self.remote = engine is not None and not isinstance(engine, InlineEngine)
        """Whether tasks run in other processes (their kernel calls counted from their
        results)."""
        self.kernel_calls = 0
        self.fits = 0
        self.timing: dict[str, float] = {}

    def ref(self, data: FitData) -> FitData | str:
        if not self.files:
            return data
        if id(data) not in self._refs:
            if self._dir is None:
                self._dir = tempfile.TemporaryDirectory(prefix="fleetbrake-closeloop-")
            path = Path(self._dir.name) / f"fitdata-{len(self._refs)}.pickle"
            self._refs[id(data)] = str(fitdata.store(data, path))
        return self._refs[id(data)]

    def _map(self, fn: Any, items: list[Any]) -> list[Any]:
        if self.engine is None or len(items) <= 1:
            return [fn(item) for item in items]
        return list(self.engine.map(fn, items))

    def fit(self, tasks: list[FitTask]) -> list[FitResult]:
        results: list[FitResult] = self._map(fit_task, tasks)
        if self.remote and len(tasks) > 1:
            self.kernel_calls += sum(r.kernel_calls for r in results)
        self.fits += len(results)
        return results

    def evaluate(self, data: FitData, effect_sets: Sequence[EffectSet]) -> list[np.ndarray]:
        ref = self.ref(data)
        out = self._map(eval_task, [EvalTask(ref, (e,)) for e in effect_sets])
        if self.remote and len(effect_sets) > 1:
            self.kernel_calls += sum(calls for _, calls in out)
        return [residuals[0] for residuals, _ in out]

    def close(self) -> None:
        if self._dir is not None:
            self._dir.cleanup()
            self._dir = None


def _finite(r: np.ndarray) -> np.ndarray:
    return r[np.isfinite(r)]


def _noise(r: np.ndarray, data: FitData, ok: np.ndarray, frame: pl.DataFrame) -> float:
    """The sensor noise from the residual's second differences within each event window
    (:func:`~fleetbrake.closeloop.selection.noise_from_residual`); from its first differences
    when too few seconds for that."""
    seconds = (data.time_utc[ok] - data.time_utc[ok].min()).astype("timedelta64[us]")
    try:
        return noise_from_residual(r, data.event[ok], seconds.astype(np.float64) / 1e6)
    except SelectionError:
        return _noise_k(frame)


def _verdict(
    chosen: Candidate | None,
    data: FitData,
    base: tuple[np.ndarray, np.ndarray],
    noise_k: float,
    current: Candidate,
) -> Adequacy:
    """Whether ``chosen`` (None: the baseline, ``base``: its residual and the seconds it is
    of) leaves a fit residual consistent with the sensor noise
    (:func:`~fleetbrake.closeloop.selection.adequacy`)."""
    if chosen is None or chosen.fitted is None:
        residual, scored = base
        effect = None
    else:
        residual, scored, effect = chosen.fitted.aligned, chosen.fitted.scored, chosen.label
    return adequacy(
        residual,
        data.blocks[scored],
        noise_k,
        _drivers(data, scored),
        before_rmse_k=current.rmse_fit_k if effect is not None else None,
        effect=effect,
    )


def _intervals(chosen: Candidate, data: FitData) -> dict[str, tuple[float, float]]:
    """95 % intervals of the chosen effects' parameters (the fit's Jacobian, inflated by the
    residual's correlation)."""
    fitted = chosen.fitted
    if fitted is None or fitted.x.size == 0:
        return {}
    blocks = data.blocks[fitted.scored]
    n_eff = effective_sample_size(fitted.aligned, blocks)
    return parameter_intervals(
        fitted.jacobian, fitted.aligned, fitted.x, fitted.parameter_names, n_eff
    )


def _drivers(data: FitData, scored: np.ndarray) -> dict[str, np.ndarray]:
    """What a residual may still correlate with, at the ``scored`` seconds of ``data``."""
    time_s = data.time_utc.astype("datetime64[us]").astype(np.int64) / 1e6
    first = np.full(len(data.event_ids), np.inf)
    np.minimum.at(first, data.event, time_s)
    named = {
        "speed": data.drivers["speed_kmh"],
        "pressure": data.drivers["brake_pressure_bar"],
        "heat input": data.drivers["flux_w_m2"],
        "ambient": data.drivers["ambient_c"],
        "time since activation": time_s - first[data.event],
        "heating phase": data.heating.astype(np.float64),
        "hour of day": (time_s % 86400.0) / 3600.0,
    }
    return {name: values[scored] for name, values in named.items()}


def _load_wagons(
    wh: Warehouse,
    wagons: Mapping[str, WagonConfig],
    events: pl.DataFrame,
    sim: SimulationConfig,
    have: Mapping[str, WagonData] | None = None,
) -> dict[str, WagonData]:
    """The samples and events of the wagons of ``events`` (those not in ``have``), each
    read once."""
    out: dict[str, WagonData] = {}
    for wagon_id in events["wagon_id"].unique(maintain_order=True).to_list():
        wagon = wagons.get(wagon_id)
        if wagon is not None and wagon_id not in (have or {}):
            out[wagon_id] = load_wagon(wh, wagon, sim)
    return out


def close_loop(
    wh: Warehouse, config: CloseLoopConfig, engine: Engine | None = None
) -> dict[str, Any]:
    """The closed loop on an open (writable) warehouse; returns the report (see module).
    ``engine``: where the candidates are fitted (and the new revision simulated and judged),
    in this process when None. The report's ``cost`` says what it took: candidates fitted,
    chain-kernel calls, seconds per phase."""
    clock = time.perf_counter()
    calls = fitdata.kernel_calls()
    workers = _Workers(engine)
    try:
        report = _close_loop(wh, config, engine, workers)
    finally:
        workers.close()
    workers.timing["total_s"] = time.perf_counter() - clock
    report["cost"] = {
        "candidates_fitted": workers.fits,
        "kernel_calls": fitdata.kernel_calls() - calls + workers.kernel_calls,
        "seconds": {k: round(v, 3) for k, v in workers.timing.items()},
    }
    return report


def _close_loop(
    wh: Warehouse, config: CloseLoopConfig, engine: Engine | None, workers: _Workers
) -> dict[str, Any]:
    clock = time.perf_counter()
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
    # each wagon read once; the fit, screening and holdout events cached as arrays once
    loaded = _load_wagons(wh, wagons, pl.concat([fit, holdout]), sim)
    fit_data = FitData.build(loaded, fit, sim, base)
    hold_data = FitData.build(loaded, holdout, sim, base) if holdout.height else None
    screen = _screen_events(fit, config.screen_events)
    screen_data = (
        fit_data if screen.height == fit.height else FitData.build(loaded, screen, sim, base)
    )
    timing = workers.timing
    timing["load_s"] = time.perf_counter() - clock

    base_predicted = fit_data.predict(base.effects)
    base_frame = fit_data.frame(base.effects, base_predicted)
    evidence = _evidence(base_frame)
    r_all = fit_data.measured_c - base_predicted
    ok = np.isfinite(r_all)
    r_base = r_all[ok]
    noise_k = _noise(r_base, fit_data, ok, base_frame)
    # one effective sample size per data set, the baseline's: the residual of a missing
    # effect is the most correlated, and candidates are compared on one count
    n_eff = {"fit": effective_sample_size(r_base, fit_data.blocks[ok])}
    if screen_data is fit_data:
        n_eff["screen"] = n_eff["fit"]
    else:
        r_screen = screen_data.residual(base.effects)
        keep = np.isfinite(r_screen)
        n_eff["screen"] = effective_sample_size(r_screen[keep], screen_data.blocks[keep])
    current = Candidate(
        base.effects, _rmse(r_base), information_criterion(r_base, 0, n_eff["fit"]), 0
    )

    present = {type(e) for e in base.effects}
    excluded: frozenset[str] = frozenset()
    outliers: dict[str, Any] = {"events": 0}
    base_kept = (r_base, ok)

    def added_of(effects: EffectSet) -> list[Effect]:
        return [e for e in effects if type(e) not in present]

    def task(
        data: FitData, classes: Sequence[type[Effect]], start: Sequence[Effect] | None, nfev: int
    ) -> FitTask:
        return FitTask(
            workers.ref(data),
            base.effects,
            tuple(classes),
            None if start is None else tuple(start),
            nfev,
            config.diff_step,
            excluded,
        )

    def candidate(fitted: FitResult, k: int, on: str) -> Candidate:
        r = fitted.residual
        bic = information_criterion(r, k, n_eff[on])
        return Candidate(fitted.effects, _rmse(r), bic, k, fitted=fitted, fitted_on=on)

    screened_on = "fit" if screen_data is fit_data else "screen"
    # screening: every effect on the earliest fit events of each wagon, carried chains
    # as the predictions' (in parallel across the engine's workers)
    classes = [cls for cls in config.candidate_classes() if cls not in present]
    t = time.perf_counter()
    results = workers.fit([task(screen_data, [cls], None, config.max_nfev) for cls in classes])
    screened = [
        candidate(res, len(cls.PARAMETER_RANGES), screened_on)
        for cls, res in zip(classes, results, strict=True)
    ]
    for c in screened:
        logger.debug("screened %s: %s rmse %.4f K", c.label, c.effects, c.rmse_fit_k)
    screened.sort(key=lambda c: c.bic)
    timing["screen_s"] = time.perf_counter() - t
    # outlier events: data the flags did not catch, far off under the best screened single
    # effect, are left out of every fit on the fit events (and of the verdict)
    t = time.perf_counter()
    if screened and config.max_outlier_fraction > 0:
        excluded, outliers = _outliers(fit_data, screened[0].effects, noise_k, config)
        kept_seconds = _kept_seconds(fit_data, excluded)
        if kept_seconds is not None:
            keep = ok & kept_seconds
            base_kept = (r_all[keep], keep)
            current = Candidate(
                base.effects,
                _rmse(r_all[keep]),
                information_criterion(r_all[keep], 0, n_eff["fit"]),
                0,
            )
    timing["outliers_s"] = time.perf_counter() - t
    # the best refitted on every fit event, from the screened parameters (the second too
    # when within the margin of it)
    t = time.perf_counter()
    top = screened[: config.refit] if screen_data is not fit_data else []
    top = [c for c in top if c.bic < screened[0].bic + config.bic_margin] or top[:1]
    refits = workers.fit(
        [
            task(
                fit_data,
                [type(e) for e in added_of(c.effects)],
                added_of(c.effects),
                max(4, config.max_nfev // 2),
            )
            for c in top
        ]
    )
    candidates = [candidate(res, c.n_parameters, "fit") for c, res in zip(top, refits, strict=True)]
    candidates += screened[len(top) :] if top else screened
    for c in candidates[: len(top)]:
        logger.debug("refitted %s: %s rmse %.4f K", c.label, c.effects, c.rmse_fit_k)
    timing["refit_s"] = time.perf_counter() - t
    # compared on the fit events only: a candidate screened only is ranked by screening
    comparable = [c for c in candidates if c.fitted_on == "fit"] or candidates
    comparable.sort(key=lambda c: c.bic)
    best = comparable[0] if comparable else None
    t = time.perf_counter()
    if (
        best is not None
        and config.max_effects >= 2
        and best.rmse_fit_k > config.pair_above_noise * noise_k
    ):
        # pairs seeded from the best single: its fitted effect, the second from its range
        first = added_of(best.effects)
        others = [
            cls
            for cls in config.candidate_classes()
            if cls not in present and cls.name not in {e.name for e in first}
        ]
        pair_results = workers.fit(
            [task(screen_data, [type(first[0]), cls], first, config.max_nfev) for cls in others]
        )
        pairs = [
            candidate(res, best.n_parameters + len(cls.PARAMETER_RANGES), screened_on)
            for cls, res in zip(others, pair_results, strict=True)
        ]
        for c in pairs:
            logger.debug("screened pair %s: rmse %.4f K", c.label, c.rmse_fit_k)
        if pairs:
            top_pair = min(pairs, key=lambda c: c.bic)
            added = added_of(top_pair.effects)
            if screened_on == "fit":  # screened on every fit event already
                refitted = top_pair
            else:
                (res,) = workers.fit(
                    [task(fit_data, [type(e) for e in added], added, max(4, config.max_nfev // 2))]
                )
                refitted = candidate(res, top_pair.n_parameters, "fit")
            logger.debug("refitted pair %s: rmse %.4f K", refitted.label, refitted.rmse_fit_k)
            candidates.append(refitted)
            comparable.append(refitted)
        comparable.sort(key=lambda c: c.bic)
        best = comparable[0]
        # a pair must beat the best single effect by the margin too
        singles = [c for c in comparable if len(c.effects) - len(present) == 1]
        if best not in singles and singles and best.bic > singles[0].bic - config.bic_margin:
            best = singles[0]
    timing["pairs_s"] = time.perf_counter() - t
    t = time.perf_counter()
    if hold_data is not None:
        fitted_all = [c for c in candidates if c.fitted_on == "fit"]
        for c, r in zip(
            fitted_all,
            workers.evaluate(hold_data, [c.effects for c in fitted_all]),
            strict=True,
        ):
            c.rmse_holdout_k = _rmse(_finite(r))
    timing["holdout_s"] = time.perf_counter() - t

    def significant_over(c: Candidate | None, than: Candidate) -> bool:
        return (
            c is not None
            and c.bic < than.bic - config.bic_margin
            and c.rmse_fit_k < (1.0 - config.min_improvement) * than.rmse_fit_k
        )

    significant = significant_over(best, current)
    # nothing physical adequate: the empirical correction, last (on the best physical effect
    # when one was significant)
    fallbacks = [
        cls
        for cls in EFFECT_ORDER
        if getattr(cls, "fallback", False) and cls not in present and config.candidates is None
    ]
    chosen = best if significant else None
    if fallbacks and not _verdict(chosen, fit_data, base_kept, noise_k, current).adequate:
        t = time.perf_counter()
        seed = added_of(chosen.effects) if chosen is not None else []
        if len(seed) < config.max_effects:
            classes = [type(e) for e in seed] + fallbacks[:1]
            (res,) = workers.fit([task(fit_data, classes, seed, max(4, config.max_nfev // 2))])
            k = sum(len(cls.PARAMETER_RANGES) for cls in classes)
            empirical = candidate(res, k, "fit")
            logger.debug("fitted %s: rmse %.4f K", empirical.label, empirical.rmse_fit_k)
            candidates.append(empirical)
            if significant_over(empirical, chosen or current):
                best, significant = empirical, True
        timing["empirical_s"] = time.perf_counter() - t
    candidates.sort(key=lambda c: (c.fitted_on != "fit", c.bic))
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
                "fitted_on": c.fitted_on,
            }
            for c in candidates
        ],
        "noise_k": round(noise_k, 5),
        "flags_judged_with": base.name,
        "solver": base.solver,
        "residual": evidence,
        "n_eff": round(n_eff["fit"], 1),
        "selection": (
            f"Bayesian information criterion on the fit events on an effective sample size of "
            f"{n_eff['fit']:.0f} independent residuals (of {r_base.size} seconds: the "
            f"baseline residual's autocorrelation within wagon-days); score = improvement over "
            f"the baseline; a candidate must "
            f"score above {config.bic_margin} and cut the fit RMSE by "
            f"{100 * config.min_improvement:.0f} %. The holdout is never used to choose."
        ),
        "exclusion": "events whose window overlaps a dragging_brake, weak_brake or "
        "sensor_fault flag of their wagon or the window of one of its events cut by a data gap "
        f"(incomplete), or starts less than {config.settle_after_flag_s:.0f} s after one ends, "
        "are left out of fit and holdout; events_all and rmse_*_all_k count every event of the "
        "set; fit events whose residual RMS under the best screened effect is far above the "
        "bulk (outliers) are left out of the parameter fit and the adequacy verdict",
        "outliers": outliers,
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
        _add_verdict(report, _verdict(None, fit_data, base_kept, noise_k, current), {})
        return report

    added = [e for e in best.effects if type(e) not in present]
    best_data = fit_data
    name = _new_revision_name(wh, best.label)
    _record_revision(wh, name, base, best)
    new_rev = Revision(name, best.effects, base.solver, base.refinement)
    simulate_events(
        wh, wagons, new_rev, sim, event_ids=all_events["event_id"].to_list(), engine=engine
    )
    # the virtual sensor re-estimated with the new revision (every wagon), its sigma_w fitted
    # first on the fit days (a property of the revision: docs/estimator.md)
    fit_revision_noise(wh, wagons, new_rev, fit, EstimationConfig(chain=sim.chain))
    estimate_wagons(wh, wagons, new_rev, EstimationConfig(chain=sim.chain), engine=engine)
    if config.reflag:
        # the flags were judged with the baseline, which lacks the effect: a fleet-wide misfit
        # looks like weak brakes or failing sensors. Judge them again with the new revision,
        # and refit on the events that are usable now.
        _reflag(wh, wagons, new_rev, sim, engine)
        fit, holdout, _ = _event_sets(wh, base.name, config)
        changed = set(fit["event_id"].to_list()) ^ set(fit_ids)
        if fit.height and len(changed) >= config.refit_changed_fraction * max(1, len(fit_ids)):
            loaded.update(_load_wagons(wh, wagons, fit, sim, have=loaded))
            refit_data = best_data = FitData.build(loaded, fit, sim, base)
            (res,) = workers.fit(
                [task(refit_data, [type(e) for e in added], added, max(1, config.max_nfev // 2))]
            )
            logger.debug("refitted on %d events after re-flagging: %s", fit.height, res.effects)
            best = candidate(res, best.n_parameters, "fit")
            added = [e for e in best.effects if type(e) not in present]
            _set_revision_effects(wh, name, best.effects)
            new_rev = Revision(name, best.effects, base.solver, base.refinement)
            simulate_events(
                wh, wagons, new_rev, sim, event_ids=all_events["event_id"].to_list(), engine=engine
            )
            fit_revision_noise(wh, wagons, new_rev, fit, EstimationConfig(chain=sim.chain))
            estimate_wagons(wh, wagons, new_rev, EstimationConfig(chain=sim.chain), engine=engine)
            _reflag(wh, wagons, new_rev, sim, engine)
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
    _add_verdict(
        report,
        _verdict(best, best_data, base_kept, noise_k, current),
        _intervals(best, best_data),
    )
    for key in ("fit", "holdout"):
        report[key].update(
            {"rmse_before_k": rmse[(key, base.name)], "rmse_after_k": rmse[(key, name)]}
        )
    _add_all_events(wh, report, sets_all, base.name, name)
    return report


def _outliers(
    data: FitData, effects: EffectSet, noise_k: float, config: CloseLoopConfig
) -> tuple[frozenset[str], dict[str, Any]]:
    """The fit events left out as outliers under ``effects`` (the best screened single), and
    what the report says of them: how many, the threshold and the worst few with their RMS."""
    rms = event_rms(data.residual(effects), data.event, len(data.event_ids))
    worst, threshold = outlier_events(
        rms,
        noise_k,
        noise_factor=config.outlier_noise_factor,
        z=config.outlier_z,
        max_fraction=config.max_outlier_fraction,
    )
    finite = rms[np.isfinite(rms)]
    for i in worst:
        logger.info("outlier event %s: residual RMS %.3f K", data.event_ids[i], rms[i])
    return frozenset(data.event_ids[i] for i in worst), {
        "events": int(worst.size),
        "threshold_k": round(threshold, 4) if math.isfinite(threshold) else None,
        "median_event_rms_k": round(float(np.median(finite)), 5) if finite.size else None,
        "judged_with": str(effects),
        "worst": [
            {"event_id": data.event_ids[i], "rms_k": round(float(rms[i]), 4)} for i in worst[:5]
        ],
    }


def _add_verdict(
    report: dict[str, Any], verdict: Adequacy, intervals: Mapping[str, tuple[float, float]]
) -> None:
    """The report's ``parameter_intervals``, ``adequate`` and ``unexplained`` (interface.md
    v2), and the figures behind the verdict (``adequacy``)."""
    report.update(
        {
            "parameter_intervals": intervals_for_json(intervals),
            "adequate": verdict.adequate,
            "unexplained": verdict.unexplained,
            "adequacy": {
                "rmse_k": round(verdict.rmse_k, 5),
                "ratio": round(verdict.ratio, 3),
                "whiteness": round(verdict.whiteness, 3),
                "explained_fraction": None
                if verdict.explained_fraction is None
                else round(verdict.explained_fraction, 4),
                "correlations": {k: round(v, 3) for k, v in verdict.correlations.items()},
            },
        }
    )


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
    wh: Warehouse,
    wagons: Mapping[str, WagonConfig],
    revision: Revision,
    sim: SimulationConfig,
    engine: Engine | None = None,
) -> None:
    """Judge every wagon's flags again with ``revision``: the simulation stage's flow, its
    timeline simulated and stored first (nothing to do for a wagon already simulated with it
    from the same data), then the flags judged from what was stored."""
    from fleetbrake.flags import raise_flags

    simulate_events(wh, wagons, revision, sim, progress=False, engine=engine)
    raise_flags(wh, wagons, revision.name, engine=engine)


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


CLOSE_LOOP_ENGINES = ("inline", "local", "ray")
"""Names ``close-loop --engine`` accepts: ``inline`` runs everything in this process."""


def _make_engine(name: str, workers: int | None, address: str | None) -> Engine:
    from fleetbrake.engine import EngineConfigError

    if name not in CLOSE_LOOP_ENGINES:
        raise EngineConfigError(
            f"--engine must be one of {', '.join(CLOSE_LOOP_ENGINES)}, got {name!r}"
        )
    if name == "inline":
        if address is not None:
            raise EngineConfigError("--address needs --engine ray")
        if workers is not None and workers < 1:
            raise EngineConfigError(f"--workers must be >= 1, got {workers}")
        return InlineEngine()
    return make_engine(name, workers, address=address, preload=("fleetbrake.closeloop.loop",))


def run_close_loop(
    db_path: str | Path,
    holdout_from: dt.date,
    json_out: str | Path,
    *,
    wait_s: float = 0.0,
    config: CloseLoopConfig | None = None,
    engine: str = "inline",
    workers: int | None = None,
    address: str | None = None,
) -> dict[str, Any]:
    """``fleetbrake close-loop``: run, write the JSON report and the Markdown report.
    ``engine``: where candidates are fitted and the new revision simulated and judged:
    ``inline`` (this process), ``local`` (``workers`` processes, default the cores) or
    ``ray`` (at ``address``, or a local instance of ``workers`` CPUs)."""
    config = config or CloseLoopConfig(holdout_from=holdout_from)
    pool = _make_engine(engine, workers, address)  # refused before the database is opened
    with pool, open_warehouse(db_path, wait_s=wait_s) as wh:
        report = close_loop(wh, config, None if isinstance(pool, InlineEngine) else pool)
        json_out = Path(json_out)
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(report, indent=2, default=str) + "\n", encoding="utf-8")
        from fleetbrake.closeloop.report import write_markdown_report

        write_markdown_report(wh, report, json_out.with_suffix(".md"))
    return report
