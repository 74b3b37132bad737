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
4. **Choice** (never looks at the holdout): every addition -- the first effect over the
   current revision (singles fitted on every fit event, best criterion first), a pair over
   its single, ``empirical`` over what it corrects -- must (a) beat what it adds to by
   ``bic_margin`` on the Bayesian information criterion on the effective sample size of the
   baseline residual (:func:`~fleetbrake.closeloop.selection.effective_sample_size`: its
   autocorrelation within wagon-days) and cut the fit RMSE by ``min_improvement``, (b) cut
   the held-out RMSE of whole wagon-days (``folds``, each fit moved one Gauss-Newton step off
   its fold: nothing re-simulated) by ``held_out_margin`` and on most folds, and (c) have its
   laws' parameters distinguishable from their nulls
   (:data:`~fleetbrake.closeloop.selection.EFFECT_NULLS`) by 95 % intervals; a candidate's
   ``refused`` says which failed. Pairs are tried when the chosen single leaves the fit RMSE
   above ``pair_above_noise`` (the adequacy bar, 1.5x) times the noise. A physical answer
   that leaves the fit inadequate and explains less than ``min_explained_share`` of the
   baseline's systematic residual is a proxy for something outside the vocabulary and is
   refused; then only ``empirical`` may enter. Nothing entering: nothing is added and the
   report says so. The chosen model's residual is judged against
   the noise (``adequate``, ``unexplained``; at the end again on the report's own fit events
   from ``v_predictions``, less the outliers it names) and its parameters get 95 % intervals,
   the widest of the Jacobian one on n_eff, the cluster-robust one and the delete-one-
   wagon-day jackknife (``parameter_intervals``, ``interval_methods``; these alone decide
   entry), widened for the report by a numerical term: the chosen effects refitted through
   coarser meshes, Roache's grid convergence index of the shift added in quadrature
   (``interval_methods.numerical``), and by an input term: the chosen parameters' shift when
   the speed is read without the bias its noise (estimated from the data) puts in a
   magnitude, by quasi-Newton steps from the fit's Jacobian (a sensitivity), added in
   quadrature (``interval_methods.input``).
5. **Revision.** The chosen effects become a new model revision (the current one, predicting
   with its parent's solver: before and after compare one model form), every
   event is re-simulated with it, the flags are judged again with it (the baseline's flags
   take a fleet-wide misfit for weak brakes or failing sensors) and the effect is refitted on
   the events usable then (the intervals' numerical and input terms computed meanwhile,
   ``CloseLoopConfig.overlap``), and the JSON report (and a Markdown report with plots
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
import threading
import time
import weakref
from collections.abc import Callable, Collection, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_for
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import polars as pl

from fleetbrake.closeloop import fitdata
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.report import MarkdownReport, read_markdown_report
from fleetbrake.closeloop.selection import (
    EFFECT_NULLS,
    GCI_ORDER,
    GCI_SAFETY_FACTOR,
    MAX_NOISE_RATIO,
    MIN_EXPLAINED_SHARE,
    Adequacy,
    BlockedIntervals,
    Comparison,
    SelectionError,
    adequacy,
    block_folds,
    blocked_intervals,
    combined_half_width,
    describe_drivers,
    distinguishable_from_null,
    effective_sample_size,
    event_rms,
    grid_convergence_index,
    improves_held_out,
    information_criterion,
    intervals_for_json,
    noise_from_residual,
    outlier_events,
    standard_errors,
    systematic_share,
    with_numerical_term,
)
from fleetbrake.engine import Engine, InlineEngine, LocalEngine, make_engine
from fleetbrake.errors import ConfigError, FleetbrakeError
from fleetbrake.flags.stats import frozen_speed_brakings
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
    pair_above_noise: float = MAX_NOISE_RATIO
    """Try pairs of effects when the chosen single leaves the fit RMSE above this many times
    the estimated sensor noise: the adequacy bar (a model adequate on its own is not made
    richer)."""
    held_out_margin: float = 0.05
    """Every addition (the first effect over the baseline, a pair over its single, the
    ``empirical`` correction over what it corrects) must cut the held-out RMSE of the fit
    period's blocks (wagon-days) by at least this share, on most folds, and its parameters
    must be distinguishable from their nulls
    (:func:`~fleetbrake.closeloop.selection.improves_held_out`)."""
    folds: int = 5
    """Folds of whole wagon-days for the held-out comparison (one per block when fewer)."""
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
    refit_step_tolerance: float = 0.1
    """A refit from fitted parameters (the chosen effect on every fit event from its screened
    parameters, the re-flag refit, the numerical term's coarse-mesh refits) ends at the first
    trial step below this many standard errors in every parameter (its Jacobian's at the
    start, on the effective sample size), without evaluating it (:func:`_fit`; 0: scipy's
    default relative tolerance only). Such a step moves no parameter by more than a fifth of
    ``refit_tolerance`` (at least 0.49 standard errors) (docs/closeloop.md, "The refits'
    stopping rule")."""
    refit_tolerance: float = 0.25
    """A re-flag refit whose every parameter moved by less than this share of its 95 %
    interval's half-width (:func:`refit_moved`) keeps the revision as it was simulated,
    estimated and flagged: the new revision is re-simulated only when the refit changes the
    answer beyond the fit's own uncertainty."""
    min_explained_share: float = MIN_EXPLAINED_SHARE
    """A physical answer that leaves the fit inadequate is named only when it explains at
    least this share of the baseline's systematic residual
    (:func:`~fleetbrake.closeloop.selection.systematic_share`); otherwise it is a proxy for
    something outside the vocabulary and only the ``empirical`` correction may enter (0: no
    such rule). An adequate answer is never affected."""
    numerical_grid_ratios: tuple[float, ...] = (1.5, 2.0)
    """The reported intervals' numerical (model-form) term: the chosen effects refitted once
    per ratio, on the same fit events from the chosen parameters, through the reduced model on
    a coarser mesh (the revision's refinement divided by the ratio, cells per direction); the
    parameters' shift between each coarse mesh and the revision's as Roache's grid
    convergence index (two grids: ``gci_safety_factor`` 3, the formal order ``gci_order``),
    the largest over the coarse meshes added in quadrature to the statistical half-width
    (:func:`~fleetbrake.closeloop.selection.with_numerical_term`). Empty: no such term. Entry
    (distinguishable from the nulls) is judged on the statistical intervals alone."""
    gci_safety_factor: float = GCI_SAFETY_FACTOR
    gci_order: float = GCI_ORDER
    speed_input_term: bool = True
    """The reported intervals' input term (ASME V&V 20's u_input by its sensitivity method:
    the parameters' response to the input's systematic error taken out): the residual of the
    chosen parameters evaluated on the same fit events with the speed read as
    ``sqrt(max(v^2 - noise^2, 0))`` (:func:`~fleetbrake.closeloop.fitdata.with_speed_debiased`,
    the noise estimated from the logged speed by
    :func:`~fleetbrake.closeloop.fitdata.speed_noise_kmh`), and the parameters moved by
    quasi-Newton steps from the Jacobian the fit already has (Broyden-updated), one
    evaluation each (:func:`input_shift`; until session 10 a refit from the chosen
    parameters, about 20 evaluations); the shift per parameter added in quadrature to the statistical half-width
    with the numerical term. Why: a GPS speed is a magnitude, so where the wagon stands it
    reads about its noise, not 0, and a convection law steep at low speed turns that into a
    bias of its exponent the same on every wagon-day, which no resampling sees
    (docs/closeloop.md, session 9). False: no such term."""
    input_step_tolerance: float = 0.05
    """The input term's steps stop when a step is at most this share of the
    shift in every parameter (:func:`input_shift`)."""
    overlap: bool = True
    """With an engine of worker processes: the interval terms (numerical and input), which
    depend only on the chosen fit and its fit events, have their data built while the
    revision is made and re-flagged and are computed while the chosen effect is refitted
    (the numerical term's coarse fits on the workers, the input term's evaluations and the
    refit in this process), and computed again after it only when the refit moved the
    answer (``refit_moved``): the same report and stored values as one after another
    (False); figures in docs/benchmarks.md, session 12."""
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
        if not all(r > 1.0 for r in self.numerical_grid_ratios):
            raise CloseLoopConfigError(
                f"numerical_grid_ratios must each be > 1 (fine over coarse cells per "
                f"direction), got {self.numerical_grid_ratios}"
            )
        if not self.refit_step_tolerance >= 0.0:
            raise CloseLoopConfigError(
                f"refit_step_tolerance must be >= 0, got {self.refit_step_tolerance}"
            )
        if not self.refit_tolerance >= 0.0:
            raise CloseLoopConfigError(f"refit_tolerance must be >= 0, got {self.refit_tolerance}")

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
    held_out: dict[str, Any] | None = None
    """The held-out comparison with what it would be added to (when judged)."""
    refused: str | None = None
    """Why it did not enter (None: it entered, or was not judged)."""

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


def parameter_bounds(classes: Sequence[type[Effect]]) -> tuple[np.ndarray, np.ndarray]:
    """The fitted parameters' bounds, in the fit's order (each class's ``PARAMETER_RANGES``
    order): a law's ``LIMITS``, unbounded where it has none."""
    lo, hi = [], []
    for cls in classes:
        for pname in cls.PARAMETER_RANGES:
            lim_lo, lim_hi = cls.LIMITS.get(pname, (None, None))
            lo.append(-np.inf if lim_lo is None else lim_lo)
            hi.append(np.inf if lim_hi is None else lim_hi)
    return np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)


class _Resolved(Exception):
    """A trial step below the fit's resolution was asked for: the fit ends where it is."""


def _fit(
    evaluator: Evaluator,
    base: EffectSet,
    classes: Sequence[type[Effect]],
    start: Sequence[Effect] | None,
    max_nfev: int,
    diff_step: float = 0.05,
    keep: np.ndarray | None = None,
    step_tolerance: float = 0.0,
    blocks: np.ndarray | None = None,
) -> FitResult:
    """Fit the parameters of ``classes`` (added to ``base``) by bounded least squares (trf),
    the Jacobian by forward differences with every perturbed vector of a step evaluated in
    one pass over the cached data (``evaluator.residuals``). ``keep``: (evaluator seconds)
    the seconds fitted and scored (None: all; outlier events left out).

    ``step_tolerance`` > 0 (a refit from fitted parameters): the fit ends, without evaluating
    it, at the first trial point that is within ``step_tolerance`` standard errors of the
    current point in every parameter, the standard errors those of the Jacobian at the start
    (:func:`~fleetbrake.closeloop.selection.standard_errors`, on the effective sample size of
    the start's residual over ``blocks``, evaluator seconds; every second its own block when
    None): such a step, accepted or not, moves no parameter by more than that share of its
    own uncertainty (docs/closeloop.md, "The refits' stopping rule")."""
    from scipy.optimize import least_squares

    names: list[tuple[type[Effect], str]] = []
    x0, scale = [], []
    starting = {type(e): e for e in (start or [])}
    for cls in classes:
        for pname, (a, b) in cls.PARAMETER_RANGES.items():
            names.append((cls, pname))
            init = starting[cls].parameters[pname] if cls in starting else 0.5 * (a + b)
            x0.append(init)
            scale.append(b - a)
    lower, upper = parameter_bounds(classes)

    def build(x: np.ndarray) -> EffectSet:
        return effects_at(base, classes, x)

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

    # trf's current point is the lowest cost its ``fun`` has seen (a trial is accepted only
    # when it lowers the cost); the Jacobian kept per point for a fit ended by the rule
    current: dict[str, Any] = {"x": None, "cost": math.inf, "sigma": None}
    jacobians: dict[bytes, np.ndarray] = {}

    def value(x: np.ndarray) -> np.ndarray:
        f = aligned(raw_many([x])[0])
        cost = float(f @ f)
        if cost < current["cost"]:
            current.update(x=np.array(x, dtype=np.float64), cost=cost)
        return f

    def fun(x: np.ndarray) -> np.ndarray:
        """trf's points: its start, then its trial steps (the rule asks before each)."""
        sigma, here = current["sigma"], current["x"]
        if sigma is not None and here is not None and not np.array_equal(x, here):
            if np.all(np.abs(x - here) < sigma):
                raise _Resolved
        return value(x)

    def jac(x: np.ndarray) -> np.ndarray:
        f0 = value(x)
        h = _steps(np.asarray(x, dtype=np.float64), lower, upper, diff_step)
        moved = [x + np.eye(x.size)[j] * h[j] for j in range(x.size)]
        columns = [(aligned(r) - f0) / h[j] for j, r in enumerate(raw_many(moved))]
        got = np.column_stack(columns) if columns else np.zeros((f0.size, 0))
        jacobians[np.asarray(x, dtype=np.float64).tobytes()] = got
        if step_tolerance > 0.0 and current["sigma"] is None and got.shape[1]:
            n_eff = (
                float(f0.size)
                if blocks is None
                else effective_sample_size(f0, np.asarray(blocks)[scored])
            )
            current["sigma"] = step_tolerance * standard_errors(got, f0, n_eff)
        return got

    x_start = np.clip(np.asarray(x0), lower + 1e-9, upper - 1e-9)
    try:
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
        jacobian = np.asarray(result.jac, dtype=np.float64)
    except _Resolved:
        x = current["x"]
        jacobian = jacobians[x.tobytes()]
    r = raw_many([x])[0]
    return FitResult(
        effects=build(x),
        residual=r[np.isfinite(r) & kept],
        aligned=aligned(r),
        jacobian=jacobian,
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
    step_tolerance: float = 0.0
    """A refit from fitted parameters ends at a trial step below this many standard errors
    in every parameter (:func:`_fit`; 0: scipy's own stopping only)."""

    def __str__(self) -> str:  # how an engine names the partition in an error
        return "candidate " + "+".join(cls.name for cls in self.classes)


def fit_task(task: FitTask) -> FitResult:
    """Run one :class:`FitTask` (a pure function of it: picklable, for the workers)."""
    data = task.data if isinstance(task.data, FitData) else fitdata.stored(task.data)
    calls = fitdata.kernel_calls()
    keep = _kept_seconds(data, task.exclude)
    fitted = _fit(
        data,
        task.base,
        task.classes,
        task.start,
        task.max_nfev,
        task.diff_step,
        keep,
        task.step_tolerance,
        data.blocks,
    )
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
    wh: Warehouse,
    revision: str,
    config: CloseLoopConfig,
    unknown_heat: Collection[str] = frozenset(),
) -> tuple[pl.DataFrame, pl.DataFrame, dict[str, list[str]]]:
    """The fit and holdout events the exclusion rule leaves (flags as they stand now, less
    the ``unknown_heat`` events: :func:`_unknown_heat_events`), and the ids of every event of
    each set."""
    every = _used_events(wh, revision, config.settle_after_flag_s)
    cutoff = dt.datetime.combine(config.holdout_from, dt.time())
    before = pl.col("start_utc") < cutoff
    sets_all = {
        "fit": every.filter(before)["event_id"].to_list(),
        "holdout": every.filter(~before)["event_id"].to_list(),
    }
    used = every.filter(~pl.col("flagged") & ~pl.col("event_id").is_in(list(unknown_heat)))
    return used.filter(before), used.filter(~before), sets_all


def _unknown_heat_events(loaded: Mapping[str, WagonData]) -> frozenset[str]:
    """Events braking over a frozen GPS speed (``flags.stats.frozen_speed_brakings``, the
    rule by which the flags call a block unsure): the logged speed is not the wagon's, so
    the heat input the model is given is not the one the block got (one such braking of a
    generated fleet left 17-30 K of residual and decided an adequacy verdict alone)."""
    out: set[str] = set()
    for data in loaded.values():
        for series in data.spans:
            frozen = frozen_speed_brakings(series)
            if not frozen:
                continue
            for event_id, a, b, _complete in series.events:
                if any(first <= b and last > a for first, last in frozen):
                    out.add(event_id)
    return frozenset(out)


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


@dataclass(frozen=True)
class _Key:
    """A task's place in its batch, named as the task is (an engine's error names it)."""

    index: int
    name: str

    def __str__(self) -> str:
        return self.name


class _Workers:
    """Where a run's fits go: the engine (the inline one when none), and the data it is
    handed. Work that runs in this process (no engine, or a single task: an engine is not
    worth one) gets the data objects; the local engine's workers read each data set once
    from a file this run writes (:func:`fitdata.store`, only when tasks go to them), Ray gets
    them with the task. Safe to use from two threads at once (the interval terms beside the
    re-flag refit: ``CloseLoopConfig.overlap``)."""

    def __init__(self, engine: Engine | None) -> None:
        self.engine = engine
        self.files = isinstance(engine, LocalEngine)
        self._dir: tempfile.TemporaryDirectory[str] | None = None
        self._refs: dict[int, FitData | str] = {}
        self._lock = threading.Lock()
        self._stored = 0
        self.ahead: _TermsAhead | None = None
        """The interval terms started ahead (``CloseLoopConfig.overlap``), until used."""
        self.remote = engine is not None and not isinstance(engine, InlineEngine)
        """Whether tasks run in other processes (their kernel calls counted from their
        results)."""
        self.kernel_calls = 0
        self.fits = 0
        self.timing: dict[str, float] = {}
        self.evaluations: dict[str, int] = {}
        """Model evaluations (passes over a data set's events) per phase, the Jacobians'
        perturbed vectors included: the report's ``cost.evaluations``."""

    def count(self, phase: str, evaluations: int) -> None:
        with self._lock:
            self.evaluations[phase] = self.evaluations.get(phase, 0) + evaluations

    def ref(self, data: FitData | str) -> FitData | str:
        """What an engine's task is handed for ``data``: the object, or with the local
        engine the file it is stored in (written once per data set)."""
        if not self.files or isinstance(data, str):
            return data
        with self._lock:  # one file per data set (its id forgotten when it is freed)
            if id(data) not in self._refs:
                if self._dir is None:
                    self._dir = tempfile.TemporaryDirectory(prefix="fleetbrake-closeloop-")
                path = Path(self._dir.name) / f"fitdata-{self._stored}.pickle"
                self._stored += 1
                self._refs[id(data)] = str(fitdata.store(data, path))
                weakref.finalize(data, self._refs.pop, id(data), None)
            return self._refs[id(data)]

    def _inline(self, items: list[Any]) -> bool:
        return self.engine is None or len(items) <= 1

    def _map(self, fn: Any, items: list[Any]) -> list[Any]:
        """``fn`` of each item, in the items' order; on an engine taken as they finish (a
        long fit at the head of the queue does not hold back the next submissions)."""
        if self._inline(items):
            return [fn(item) for item in items]
        out: list[Any] = [None] * len(items)
        keyed = [(_Key(i, str(item)), item) for i, item in enumerate(items)]
        for key, result in self.engine.map_unordered(fn, keyed):  # type: ignore[union-attr]
            out[key.index] = result
        return out

    def shipped(self, tasks: list[FitTask]) -> list[FitTask]:
        """``tasks`` as the engine is handed them: with the local engine's workers, their
        data written now (:meth:`ref`)."""
        if self._inline(tasks):
            return tasks
        return [dataclasses.replace(t, data=self.ref(t.data)) for t in tasks]

    def fit(self, tasks: list[FitTask], phase: str) -> list[FitResult]:
        tasks = self.shipped(tasks)
        results: list[FitResult] = self._map(fit_task, tasks)
        self.count(phase, sum(r.evaluations for r in results))
        with self._lock:
            if self.remote and len(tasks) > 1:
                self.kernel_calls += sum(r.kernel_calls for r in results)
            self.fits += len(results)
        return results

    def evaluate(
        self, data: FitData, effect_sets: Sequence[EffectSet], phase: str
    ) -> list[np.ndarray]:
        self.count(phase, len(effect_sets))
        tasks = [EvalTask(data, (e,)) for e in effect_sets]
        if not self._inline(tasks):
            tasks = [dataclasses.replace(t, data=self.ref(data)) for t in tasks]
        out = self._map(eval_task, tasks)
        if self.remote and len(effect_sets) > 1:
            with self._lock:
                self.kernel_calls += sum(calls for _, calls in out)
        return [residuals[0] for residuals, _ in out]

    def close(self) -> None:
        if self.ahead is not None:  # an error before they were used: not waited for
            self.ahead.drop(wait=False)
            self.ahead = None
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
        periods=DRIVER_PERIODS,
    )


def _law(effect: Effect) -> str:
    """``name[law]``: the vocabulary name and the law (``convection_speed[flat_plate]``)."""
    return f"{effect.name}[{effect.law}]"


def _law_label(c: Candidate, present: set[type[Effect]]) -> str:
    """The candidate's added laws, ``+``-joined (the report's candidate ``label``; its
    ``effect`` stays the vocabulary names)."""
    return "+".join(_law(e) for e in c.effects if type(e) not in present) or "none"


def _report_key(name: str, qualified: bool) -> str:
    """A fitted parameter's key in the report (``name`` is ``effect.parameter``): the
    parameter's own name when one effect was added, ``effect.parameter`` when several (two
    effects' parameters never collide)."""
    return name if qualified else name.split(".", 1)[1]


def report_parameters(added: Sequence[Effect]) -> dict[str, float]:
    """The report's flat ``parameters`` map (interface.md: parameter -> value) of the added
    effects, keyed as :func:`_report_key` does."""
    qualified = len(added) > 1
    return {
        _report_key(f"{e.name}.{k}", qualified): v for e in added for k, v in e.parameters.items()
    }


def _blocked(fitted: FitResult, data: FitData) -> BlockedIntervals:
    """95 % intervals of a fit's parameters keyed ``effect.parameter``
    (:func:`~fleetbrake.closeloop.selection.blocked_intervals`, wagon-days as blocks)."""
    return blocked_intervals(
        fitted.jacobian, fitted.aligned, fitted.x, fitted.names, data.blocks[fitted.scored]
    )


def _intervals(chosen: Candidate, data: FitData) -> BlockedIntervals | None:
    """95 % intervals of the chosen effects' parameters, keyed as the report's ``parameters``:
    the widest of the Jacobian interval on the effective sample size, the cluster-robust one
    and the delete-one-wagon-day jackknife (:func:`_blocked`)."""
    fitted = chosen.fitted
    if fitted is None or fitted.x.size == 0:
        return None
    got = _blocked(fitted, data)
    qualified = len({name.split(".", 1)[0] for name in fitted.names}) > 1

    def keyed(d: Mapping[str, Any]) -> dict[str, Any]:
        return {_report_key(k, qualified): v for k, v in d.items()}

    return BlockedIntervals(
        intervals=keyed(got.intervals),
        jacobian=keyed(got.jacobian),
        sandwich=keyed(got.sandwich),
        jackknife=keyed(got.jackknife),
        blocks=got.blocks,
        method=keyed(got.method),
    )


def _on_seconds(
    c: Candidate, n: int, base: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(residual, mask, Jacobian) of a candidate over every second of the fit data (NaN and
    zero rows where it is not scored); the baseline (nothing fitted) from ``base``."""
    r = np.full(n, np.nan)
    if c.fitted is None:
        residual, mask = base
        r[mask] = residual
        return r, np.asarray(mask, dtype=bool), None
    mask = np.asarray(c.fitted.scored, dtype=bool)
    r[mask] = c.fitted.aligned
    j = np.zeros((n, c.fitted.jacobian.shape[1]))
    j[mask] = c.fitted.jacobian
    return r, mask, j


def _held_out(
    c: Candidate,
    over: Candidate,
    data: FitData,
    base: tuple[np.ndarray, np.ndarray],
    config: CloseLoopConfig,
) -> Comparison:
    """Blocked cross-validation of ``c`` against ``over`` on the seconds both are scored on:
    whole wagon-days per fold, each fit moved one Gauss-Newton step off the fold
    (:func:`~fleetbrake.closeloop.selection.improves_held_out`)."""
    n = data.measured_c.size
    ra, ma, ja = _on_seconds(over, n, base)
    rb, mb, jb = _on_seconds(c, n, base)
    common = ma & mb & np.isfinite(ra) & np.isfinite(rb)
    folds = block_folds(data.blocks[common], config.folds)
    return improves_held_out(
        ra[common],
        None if ja is None else ja[common],
        rb[common],
        None if jb is None else jb[common],
        folds,
        config.held_out_margin,
    )


DRIVER_PERIODS: dict[str, float] = {"hour of day": 24.0}
"""Drivers that are phases (hours on a 24 h clock), correlated with a leftover residual by
the circular-linear correlation: sunshine peaking at noon has next to no Pearson correlation
with the hour counted from midnight."""


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
    # the evaluations made in this process (a single fit, the outliers, the holdout, the
    # input term) split their spans across as many threads as the engine has workers, which
    # are idle then (but for the coarse fits beside the re-flag refit); the same results
    threads = engine.workers if isinstance(engine, LocalEngine) else 1
    try:
        with fitdata.parallel(threads):
            report = _close_loop(wh, config, engine, workers)
    finally:
        workers.close()
    _judge_on_report(wh, report, config)
    workers.timing["total_s"] = time.perf_counter() - clock
    report["cost"] = {
        "candidates_fitted": workers.fits,
        "kernel_calls": fitdata.kernel_calls() - calls + workers.kernel_calls,
        "evaluations": dict(workers.evaluations),
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
    all_events = wh.con.sql(sql("q_closeloop_events")).pl()
    sim = config.simulation
    # each wagon read once (every wagon with events: the flags judged again may free the
    # events of one); the fit, screening and holdout events cached as arrays once
    loaded = _load_wagons(wh, wagons, all_events, sim)
    unknown_heat = _unknown_heat_events(loaded)
    fit, holdout, sets_all = _event_sets(wh, base.name, config, unknown_heat)
    if fit.height == 0:
        raise CloseLoopError(
            f"{wh.path}: no unflagged event with predictions before {config.holdout_from}"
        )
    fit_data = FitData.build(loaded, fit, sim, base)
    hold_data = FitData.build(loaded, holdout, sim, base) if holdout.height else None
    screen = _screen_events(fit, config.screen_events)
    screen_data = (
        fit_data if screen.height == fit.height else FitData.build(loaded, screen, sim, base)
    )
    timing = workers.timing
    timing["load_s"] = time.perf_counter() - clock

    base_predicted = fit_data.predict(base.effects)
    workers.count("load", 1)
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
        workers.count("load", 1)
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
        data: FitData,
        classes: Sequence[type[Effect]],
        start: Sequence[Effect] | None,
        nfev: int,
        refit: bool = False,
    ) -> FitTask:
        """A fit of ``classes`` from ``start``; ``refit``: every parameter starts fitted (the
        refits' stopping rule applies, ``config.refit_step_tolerance``)."""
        return FitTask(
            data,
            base.effects,
            tuple(classes),
            None if start is None else tuple(start),
            nfev,
            config.diff_step,
            excluded,
            config.refit_step_tolerance if refit else 0.0,
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
    results = workers.fit(
        [task(screen_data, [cls], None, config.max_nfev) for cls in classes], "screen"
    )
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
        workers.count("outliers", 1)
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
                refit=True,
            )
            for c in top
        ],
        "refit",
    )
    candidates = [candidate(res, c.n_parameters, "fit") for c, res in zip(top, refits, strict=True)]
    candidates += screened[len(top) :] if top else screened
    for c in candidates[: len(top)]:
        logger.debug("refitted %s: %s rmse %.4f K", c.label, c.effects, c.rmse_fit_k)
    timing["refit_s"] = time.perf_counter() - t
    # compared on the fit events only: a candidate screened only is ranked by screening
    # compared on the fit events only: a candidate screened only is ranked by screening
    comparable = [c for c in candidates if c.fitted_on == "fit"] or candidates
    comparable.sort(key=lambda c: c.bic)

    def significant_over(c: Candidate | None, than: Candidate) -> bool:
        return (
            c is not None
            and c.bic < than.bic - config.bic_margin
            and c.rmse_fit_k < (1.0 - config.min_improvement) * than.rmse_fit_k
        )

    def admit(c: Candidate, over: Candidate) -> bool:
        """Whether ``c`` enters over ``over`` (the baseline, or the model it adds to): the
        criterion by its margin, the held-out wagon-days by the stated margin, and the added
        laws' parameters distinguishable from their nulls (issue 13). Says why not in
        ``c.refused``."""
        if not significant_over(c, over):
            c.refused = (
                f"criterion: score {over.bic - c.bic:.1f} over {_law_label(over, present)} "
                f"(needs {config.bic_margin:g}) and fit RMSE {c.rmse_fit_k:.4f} K against "
                f"{over.rmse_fit_k:.4f} K (needs a {100 * config.min_improvement:.0f} % cut)"
            )
            return False
        reasons = []
        try:
            comparison = _held_out(c, over, fit_data, base_kept, config)
        except SelectionError as exc:
            c.held_out = {"error": str(exc)}
            logger.warning("held-out comparison of %s not possible: %s", c.label, exc)
        else:
            c.held_out = {
                "over": _law_label(over, present),
                "rmse_over_k": round(comparison.rmse_a_k, 5),
                "rmse_k": round(comparison.rmse_b_k, 5),
                "gain": round(comparison.gain, 4),
                "margin": comparison.margin,
                "folds_improved": comparison.folds_improved,
                "folds": comparison.folds,
            }
            if not comparison.improves:
                reasons.append(comparison.describe())
        if c.fitted is not None:
            before = {type(e) for e in over.effects}
            iv = _blocked(c.fitted, fit_data).intervals
            for e in c.effects:
                if type(e) in before or type(e) in present:
                    continue
                nulls = {f"{e.name}.{k}": v for k, v in EFFECT_NULLS.get(_law(e), {}).items()}
                any_of = e.name == "empirical"
                if not distinguishable_from_null(iv, nulls, any_of=any_of):
                    inside = ", ".join(
                        f"{k.split('.', 1)[1]} = {v:g} within "
                        f"[{iv.get(k, (-math.inf, math.inf))[0]:.4g}, "
                        f"{iv.get(k, (-math.inf, math.inf))[1]:.4g}]"
                        for k, v in nulls.items()
                    )
                    reasons.append(f"{_law(e)} not distinguishable from its null: {inside}")
        c.refused = "; ".join(reasons) or None
        if c.refused:
            logger.info("%s does not enter: %s", _law_label(c, present), c.refused)
        return c.refused is None

    # the first effect over the baseline: the singles fitted on every fit event, best
    # criterion first, the first that enters
    best: Candidate | None = None
    for c in comparable:
        if c.fitted_on == "fit" and admit(c, current):
            best = c
            break
    t = time.perf_counter()
    if (
        best is not None
        and config.max_effects >= 2
        and best.rmse_fit_k > config.pair_above_noise * noise_k
    ):
        # pairs seeded from the chosen single: its fitted effect, the second from its range
        first = added_of(best.effects)
        others = [
            cls
            for cls in config.candidate_classes()
            if cls not in present and cls.name not in {e.name for e in first}
        ]
        pair_results = workers.fit(
            [task(screen_data, [type(first[0]), cls], first, config.max_nfev) for cls in others],
            "pairs",
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
                    [
                        task(
                            fit_data,
                            [type(e) for e in added],
                            added,
                            max(4, config.max_nfev // 2),
                            refit=True,
                        )
                    ],
                    "pairs",
                )
                refitted = candidate(res, top_pair.n_parameters, "fit")
            logger.debug("refitted pair %s: rmse %.4f K", refitted.label, refitted.rmse_fit_k)
            candidates.append(refitted)
            # a pair enters over its single by the same rule as the single over the baseline
            if admit(refitted, best):
                best = refitted
    timing["pairs_s"] = time.perf_counter() - t
    t = time.perf_counter()
    if hold_data is not None:
        fitted_all = [c for c in candidates if c.fitted_on == "fit"]
        for c, r in zip(
            fitted_all,
            workers.evaluate(hold_data, [c.effects for c in fitted_all], "holdout"),
            strict=True,
        ):
            c.rmse_holdout_k = _rmse(_finite(r))
    timing["holdout_s"] = time.perf_counter() - t

    # an inadequate physical answer is named only when it is the dominant cause of the misfit:
    # with the truth outside the vocabulary, an effect correlated with it passes the criterion
    # and the held-out folds against a baseline that is itself wrong, and its parameter then
    # describes the missing term, not its own law; such a proxy gives way to the empirical
    # correction alone (or nothing)
    if best is not None and config.min_explained_share > 0:
        verdict = _verdict(best, fit_data, base_kept, noise_k, current)
        share = systematic_share(current.rmse_fit_k, best.rmse_fit_k, noise_k)
        if not verdict.adequate and share < config.min_explained_share:
            best.refused = (
                f"proxy: leaves the fit inadequate ({verdict.ratio:.2f}x the noise) and "
                f"explains {100 * max(share, 0.0):.0f} % of the systematic residual (needs "
                f"{100 * config.min_explained_share:.0f} %): not the cause of the misfit"
            )
            logger.info("%s is not named: %s", _law_label(best, present), best.refused)
            best = None
    significant = best is not None
    # nothing physical adequate: the empirical correction, last (on the chosen physical
    # effect when one entered), entering over what it corrects by the same rule
    fallbacks = [
        cls
        for cls in EFFECT_ORDER
        if getattr(cls, "fallback", False) and cls not in present and config.candidates is None
    ]
    chosen = best
    if fallbacks and not _verdict(chosen, fit_data, base_kept, noise_k, current).adequate:
        t = time.perf_counter()
        seed = added_of(chosen.effects) if chosen is not None else []
        if len(seed) < config.max_effects:
            classes = [type(e) for e in seed] + fallbacks[:1]
            (res,) = workers.fit(
                [task(fit_data, classes, seed, max(4, config.max_nfev // 2))], "empirical"
            )
            k = sum(len(cls.PARAMETER_RANGES) for cls in classes)
            empirical = candidate(res, k, "fit")
            logger.debug("fitted %s: rmse %.4f K", empirical.label, empirical.rmse_fit_k)
            candidates.append(empirical)
            if admit(empirical, chosen or current):
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
                "label": _law_label(c, present),
                "parameters": {e.name: e.parameters for e in c.effects if type(e) not in present},
                "rmse_fit_k": round(c.rmse_fit_k, 5),
                "rmse_holdout_k": None if c.rmse_holdout_k is None else round(c.rmse_holdout_k, 5),
                "score": round(current.bic - c.bic, 3),
                "fitted_on": c.fitted_on,
                "held_out": c.held_out,
                "refused": c.refused,
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
            f"the baseline. Every addition (the first effect over the baseline, a pair over "
            f"its single, empirical over what it corrects) must score {config.bic_margin:g} "
            f"above what it adds to, cut the fit RMSE by "
            f"{100 * config.min_improvement:.0f} %, cut the held-out RMSE of whole wagon-days "
            f"({config.folds} folds, each fit moved one Gauss-Newton step off its fold) by the "
            f"practical margin of {100 * config.held_out_margin:.0f} % and on most folds, and "
            f"have each added law's parameters distinguishable from their nulls (95 % "
            f"intervals, the widest of Jacobian on n_eff, cluster-robust and delete-one-"
            f"wagon-day jackknife); a candidate's 'refused' says why it did not enter. Pairs "
            f"are tried when the single leaves the fit RMSE above "
            f"{config.pair_above_noise:g}x the noise. The holdout is never used to choose."
        ),
        "exclusion": "events whose window overlaps a dragging_brake, weak_brake or "
        "sensor_fault flag of their wagon or the window of one of its events cut by a data gap "
        f"(incomplete), or starts less than {config.settle_after_flag_s:.0f} s after one ends, "
        "are left out of fit and holdout, and so are brakings over a frozen GPS speed (their "
        "heat input is unknown: unknown_heat); events_all and rmse_*_all_k count every event "
        "of the "
        "set; fit events whose residual RMS under the best screened effect is far above the "
        "bulk (outliers) are left out of the parameter fit and the adequacy verdict",
        "outliers": outliers,
        "unknown_heat": {"events": len(unknown_heat), "event_ids": sorted(unknown_heat)},
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
    best_data, best_events = fit_data, fit
    name = _new_revision_name(wh, best.label)
    _record_revision(wh, name, base, best)
    new_rev = Revision(name, best.effects, base.solver, base.refinement)
    event_ids = all_events["event_id"].to_list()

    def terms(
        chosen: Candidate,
        events: pl.DataFrame,
        wagons_loaded: Mapping[str, WagonData],
        started: _TermsAhead | None,
    ) -> tuple[Numerical | None, InputTerm | None]:
        """The interval terms of ``chosen`` fitted on ``events``: those ``started`` ahead
        when they were started for the same (else they are waited for and dropped)."""
        if started is not None:
            workers.ahead = None
            if started.same(chosen, events, wagons_loaded):
                clock = time.perf_counter()
                numerical, inputs = started.result()
                timing["terms_wait_s"] = time.perf_counter() - clock
                return numerical, inputs
            started.drop()
        return (
            _numerical_phase(chosen, events, wagons_loaded, base, present, config, workers, task),
            _input_phase(chosen, events, wagons_loaded, base, present, config, workers),
        )

    # the interval terms depend on the chosen fit and its events only: their data built
    # while the revision is made and re-flagged (this process is mostly idle then: the
    # workers estimate and judge), their work done while it is refitted (the refit in this
    # process, the coarse fits on the workers), used when the refit leaves the answer as it was
    ahead = None
    flags_judged = threading.Event()
    if config.overlap and workers.remote:
        chosen, snapshot, ready = best, dict(loaded), flags_judged.wait
        ahead = workers.ahead = _TermsAhead(
            chosen,
            best_events,
            snapshot,
            lambda: _numerical_phase(
                chosen, best_events, snapshot, base, present, config, workers, task, ready
            ),
            lambda: _input_phase(
                chosen, best_events, snapshot, base, present, config, workers, ready
            ),
        )
    t = time.perf_counter()
    try:
        _make_revision(wh, wagons, new_rev, sim, event_ids, fit, engine)
    except BaseException:
        flags_judged.set()
        raise
    timing["revision_s"] = time.perf_counter() - t
    if not config.reflag:
        flags_judged.set()
    if config.reflag:
        # the flags were judged with the baseline, which lacks the effect: a fleet-wide misfit
        # looks like weak brakes or failing sensors. Judge them again with the new revision,
        # and refit on the events that are usable now.
        t = time.perf_counter()
        try:
            _reflag(wh, wagons, new_rev, sim, engine)
        finally:  # the terms' work may start (the workers are the flags' until now)
            flags_judged.set()
        fit, holdout, _ = _event_sets(wh, base.name, config, unknown_heat)
        timing["reflag_s"] = time.perf_counter() - t
        changed = set(fit["event_id"].to_list()) ^ set(fit_ids)
        if fit.height and len(changed) >= config.refit_changed_fraction * max(1, len(fit_ids)):
            t = time.perf_counter()
            loaded.update(_load_wagons(wh, wagons, fit, sim, have=loaded))
            refit_events = fit
            refit_data = FitData.build(loaded, refit_events, sim, base)
            (res,) = workers.fit(
                [
                    task(
                        refit_data,
                        [type(e) for e in added],
                        added,
                        max(1, config.max_nfev // 2),
                        refit=True,
                    )
                ],
                "reflag_refit",
            )
            moved = refit_moved(best, res, _blocked(res, refit_data), config.refit_tolerance)
            timing["reflag_refit_s"] = time.perf_counter() - t
            logger.debug(
                "refitted on %d events after re-flagging: %s, chosen %s (moved beyond "
                "tolerance: %s)",
                fit.height,
                res.effects,
                best.effects,
                ", ".join(moved) or "none",
            )
            if moved:
                # the answer changed: the revision made again with the refitted parameters
                t = time.perf_counter()
                best_data, best_events = refit_data, refit_events
                best = candidate(res, best.n_parameters, "fit")
                added = [e for e in best.effects if type(e) not in present]
                _set_revision_effects(wh, name, best.effects)
                new_rev = Revision(name, best.effects, base.solver, base.refinement)
                _make_revision(wh, wagons, new_rev, sim, event_ids, fit, engine)
                _reflag(wh, wagons, new_rev, sim, engine)
                fit, holdout, _ = _event_sets(wh, base.name, config, unknown_heat)
                timing["remake_s"] = time.perf_counter() - t
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
            "parameters": report_parameters(added),
            "effects": [e.to_dict() for e in added],
        }
    )
    numerical, inputs = terms(best, best_events, loaded, ahead)
    _add_verdict(
        report,
        _verdict(best, best_data, base_kept, noise_k, current),
        _intervals(best, best_data),
        numerical,
        inputs,
    )
    for key in ("fit", "holdout"):
        report[key].update(
            {"rmse_before_k": rmse[(key, base.name)], "rmse_after_k": rmse[(key, name)]}
        )
    _add_all_events(wh, report, sets_all, base.name, name)
    return report


def _numerical_phase(
    best: Candidate,
    events: pl.DataFrame,
    loaded: Mapping[str, WagonData],
    base: Revision,
    present: set[type[Effect]],
    config: CloseLoopConfig,
    workers: _Workers,
    task: Callable[..., FitTask],
    ready: Callable[[], object] | None = None,
) -> Numerical | None:
    """The chosen effects through coarser meshes, on the same fit events (``events``), from
    the chosen parameters: the numerical term of the reported intervals (None when not asked
    for or nothing was fitted). The coarse fits run on the engine's workers, once ``ready()``
    returns (their data built and written for the workers before)."""
    if not (config.numerical_grid_ratios and best.fitted is not None and best.fitted.x.size):
        return None
    t = time.perf_counter()
    added_now = [e for e in best.effects if type(e) not in present]
    coarse_bases = [
        dataclasses.replace(base, refinement=base.refinement / ratio)
        for ratio in config.numerical_grid_ratios
    ]
    tasks = workers.shipped(
        [
            task(
                FitData.build(loaded, events, config.simulation, coarse_base),
                [type(e) for e in added_now],
                added_now,
                max(4, config.max_nfev // 2),
                refit=True,
            )
            for coarse_base in coarse_bases
        ]
    )
    waited = _wait(ready)
    coarse_fits = workers.fit(tasks, "numerical")
    numerical = _numerical_term(best.fitted, coarse_fits, base, config)
    workers.timing["numerical_s"] = time.perf_counter() - t - waited
    return numerical


def _input_phase(
    best: Candidate,
    events: pl.DataFrame,
    loaded: Mapping[str, WagonData],
    base: Revision,
    present: set[type[Effect]],
    config: CloseLoopConfig,
    workers: _Workers,
    ready: Callable[[], object] | None = None,
) -> InputTerm | None:
    """The chosen parameters' residual with the speed's magnitude bias taken out, on the same
    fit events (``events``), and the parameters' response to it by the fit's Jacobian: the
    input term of the reported intervals (None when not asked for, nothing was fitted or the
    speed has no noise). Its evaluations run in this process, one after another, once
    ``ready()`` returns (its data built before)."""
    speed_noise = fitdata.speed_noise_kmh(loaded) if config.speed_input_term else math.nan
    if not (best.fitted is not None and best.fitted.x.size and speed_noise > 0.0):
        return None
    t = time.perf_counter()
    added_now = [e for e in best.effects if type(e) not in present]
    debiased_data = FitData.build(
        fitdata.with_speed_debiased(loaded, speed_noise), events, config.simulation, base
    )
    fitted_now, classes_now = best.fitted, [type(e) for e in added_now]
    lower, upper = parameter_bounds(classes_now)

    def residual_at(x: np.ndarray) -> np.ndarray:
        moved = [effects_at(fitted_now.effects, classes_now, x)]
        return workers.evaluate(debiased_data, moved, "input")[0]

    waited = _wait(ready)
    shift, steps = input_shift(fitted_now, residual_at, lower, upper, config.input_step_tolerance)
    inputs = _input_term(fitted_now, shift, speed_noise, steps)
    workers.timing["input_s"] = time.perf_counter() - t - waited
    return inputs


def _wait(ready: Callable[[], object] | None) -> float:
    """Seconds spent in ``ready()`` (none when None)."""
    if ready is None:
        return 0.0
    t = time.perf_counter()
    ready()
    return time.perf_counter() - t


class _TermsAhead:
    """The interval terms of a chosen fit (``chosen`` on ``events``, the wagons ``loaded``),
    on two threads of this process (``CloseLoopConfig.overlap``): their data built while the
    revision is made and re-flagged, their work done while it is refitted (the numerical
    term's thread hands its coarse fits to the engine's workers, the input term's evaluates
    here). Neither touches the warehouse (the
    parent stays its single writer) nor data the refit evaluates."""

    def __init__(
        self,
        chosen: Candidate,
        events: pl.DataFrame,
        loaded: Mapping[str, WagonData],
        numerical: Callable[[], Numerical | None],
        inputs: Callable[[], InputTerm | None],
    ) -> None:
        self.chosen, self.events, self.loaded = chosen, events, loaded
        self._pool = ThreadPoolExecutor(2, thread_name_prefix="closeloop-terms")
        self._numerical: Future[Numerical | None] = self._pool.submit(numerical)
        self._inputs: Future[InputTerm | None] = self._pool.submit(inputs)

    def same(
        self, chosen: Candidate, events: pl.DataFrame, loaded: Mapping[str, WagonData]
    ) -> bool:
        """Whether these terms are the ones of ``chosen`` on ``events`` (the refit moved
        nothing and loaded no other wagon)."""
        return (
            chosen is self.chosen and events is self.events and loaded.keys() == self.loaded.keys()
        )

    def result(self) -> tuple[Numerical | None, InputTerm | None]:
        """Both terms (an error in either raised here, as the sequential run would)."""
        try:
            return self._numerical.result(), self._inputs.result()
        finally:
            self._pool.shutdown(wait=True)

    def drop(self, wait: bool = True) -> None:
        """Not used: waited for (``wait``; their errors dropped) or left to end."""
        if wait:
            futures: list[Future[Any]] = [self._numerical, self._inputs]
            wait_for(futures)
        self._pool.shutdown(wait=wait, cancel_futures=True)


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
        "event_ids": sorted(data.event_ids[i] for i in worst),
        "worst": [
            {"event_id": data.event_ids[i], "rms_k": round(float(rms[i]), 4)} for i in worst[:5]
        ],
    }


@dataclass(frozen=True)
class Numerical:
    """The reported intervals' numerical term: the chosen parameters fitted through the
    revision's mesh and through coarser ones, and Roache's grid convergence index of each
    shift; ``half_width`` the largest per parameter (keyed as the report's ``parameters``)."""

    refinement: float
    grids: list[dict[str, Any]]
    """Per coarse mesh: ``ratio``, ``refinement``, the refitted parameters (``coarse``), their
    ``shift`` from the revision's and its ``gci``."""
    order: float
    safety_factor: float
    half_width: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        def g(value: Any) -> Any:
            if isinstance(value, dict):
                return {k: g(v) for k, v in value.items()}
            return float(f"{value:.6g}") if isinstance(value, float) else value

        return {
            "method": (
                "grid convergence index (Roache; ASME V&V 20's u_num): the chosen effects "
                "refitted on the same fit events through the reduced model on coarser meshes; "
                "per mesh gci = safety_factor |coarse - fine| / (ratio^order - 1), the largest "
                "added in quadrature to the statistical half-width"
            ),
            "refinement": self.refinement,
            "order": self.order,
            "safety_factor": self.safety_factor,
            "grids": [g(grid) for grid in self.grids],
            "half_width": g(self.half_width),
        }


def _numerical_term(
    fine: FitResult, coarse: Sequence[FitResult], base: Revision, config: CloseLoopConfig
) -> Numerical:
    """The numerical term of the chosen parameters (``fine``, fitted through ``base``'s mesh)
    from their refits through the coarser meshes of ``config.numerical_grid_ratios``
    (:func:`~fleetbrake.closeloop.selection.grid_convergence_index`, the largest per
    parameter), keyed as the report's ``parameters``."""
    qualified = len({name.split(".", 1)[0] for name in fine.names}) > 1
    keys = [_report_key(name, qualified) for name in fine.names]
    grids: list[dict[str, Any]] = []
    half = np.zeros(fine.x.size)
    for ratio, fit in zip(config.numerical_grid_ratios, coarse, strict=True):
        by_name = dict(zip(fit.names, fit.x, strict=True))
        x_coarse = np.array([by_name[name] for name in fine.names])
        gci = grid_convergence_index(
            fine.x, x_coarse, ratio, config.gci_order, config.gci_safety_factor
        )
        half = np.maximum(half, gci)
        grids.append(
            {
                "ratio": float(ratio),
                "refinement": base.refinement / ratio,
                "coarse": dict(zip(keys, map(float, x_coarse), strict=True)),
                "shift": dict(zip(keys, map(float, x_coarse - fine.x), strict=True)),
                "gci": dict(zip(keys, map(float, gci), strict=True)),
                "evaluations": fit.evaluations,
            }
        )
    return Numerical(
        refinement=base.refinement,
        grids=grids,
        order=config.gci_order,
        safety_factor=config.gci_safety_factor,
        half_width=dict(zip(keys, map(float, half), strict=True)),
    )


@dataclass(frozen=True)
class InputTerm:
    """The reported intervals' input term: the chosen parameters moved by the speed's
    magnitude bias taken out (the logged speed's noise ``speed_noise_kmh``; quasi-Newton
    steps from the fit's Jacobian, :func:`input_shift`), the moved parameters, their
    ``shift`` from the chosen ones, and ``half_width`` its size (keyed as the report's
    ``parameters``)."""

    speed_noise_kmh: float
    debiased: dict[str, float]
    shift: dict[str, float]
    evaluations: int

    @property
    def half_width(self) -> dict[str, float]:
        return {k: abs(v) for k, v in self.shift.items()}

    def to_json(self) -> dict[str, Any]:
        def g(value: dict[str, float]) -> dict[str, float]:
            return {k: float(f"{v:.6g}") for k, v in value.items()}

        return {
            "method": (
                "sensitivity to the input's systematic error (ASME V&V 20's u_input): the "
                "chosen parameters' residual on the same fit events with the speed read as "
                "sqrt(max(v^2 - noise^2, 0)) (a GPS speed is a magnitude: at standstill it "
                "reads its noise), the noise from the logged speed's second differences where "
                "the wagon moves, and the parameters' shift where the changed residual meets "
                "the fit's normal equations, by quasi-Newton steps from the fit's Jacobian "
                "(Broyden-updated); the shift added in quadrature to the statistical half-width"
            ),
            "speed_noise_kmh": float(f"{self.speed_noise_kmh:.6g}"),
            "debiased": g(self.debiased),
            "shift": g(self.shift),
            "evaluations": self.evaluations,
            "half_width": g(self.half_width),
        }


def _normal_change(fitted: FitResult, moved: np.ndarray) -> np.ndarray:
    """``J^T (r_moved - r)`` on the fit's scored seconds: how far ``moved`` (a residual on the
    evaluator's seconds) is from satisfying the fit's normal equations as the fit's own
    residual ``r`` (``fitted.aligned``) does; a second it does not predict counts as
    unchanged."""
    if moved.shape != fitted.scored.shape:
        raise CloseLoopError(
            f"the moved residual has {moved.size} seconds, the fit {fitted.scored.size}: "
            "not the fit's events"
        )
    change = moved[fitted.scored] - fitted.aligned
    change = np.where(np.isfinite(change), change, 0.0)
    return np.asarray(fitted.jacobian.T @ change, dtype=np.float64)


def _bounded_step(
    normal: np.ndarray,
    g: np.ndarray,
    x: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    norms: np.ndarray,
) -> np.ndarray:
    """The step ``dx`` solving ``normal dx = -g`` (``normal``: p x p, the normal matrix of the
    parameters' response), scaled by ``norms`` (parameters of very different sizes in one
    solve); a parameter on a bound the step would cross stays there, and ``x + dx`` is kept
    within ``lower`` .. ``upper``."""
    free = np.ones(x.size, dtype=bool)
    step = np.zeros(x.size)
    for _ in range(x.size + 1):  # a bound leaves a parameter at a time
        step[:] = 0.0
        if free.any():
            n = norms[free]
            scaled = normal[np.ix_(free, free)] / np.outer(n, n)
            step[free] = np.linalg.lstsq(scaled, -g[free] / n, rcond=None)[0] / n
        crossing = free & (((x <= lower) & (step < 0.0)) | ((x >= upper) & (step > 0.0)))
        if not crossing.any():
            break
        free &= ~crossing
    return np.asarray(np.clip(x + step, lower, upper) - x, dtype=np.float64)


def _column_norms(jacobian: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(jacobian, axis=0)
    return np.asarray(np.where(norms > 0.0, norms, 1.0), dtype=np.float64)


def gauss_newton_shift(
    fitted: FitResult, moved: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> np.ndarray:
    """One Gauss-Newton step of the fitted parameters' response to a change of the data or an
    input: from ``fitted.x`` with the fit's own Jacobian, ``dx = -J^+ (r_moved - r)`` on the
    fit's scored seconds (``moved``: the residual at ``fitted.x`` with the input changed, on
    the evaluator's seconds, ``r`` the fit's own residual ``fitted.aligned``; a second it does
    not predict counts as unchanged). To first order this is the refit's shift (the fit's
    residual being orthogonal to J at its optimum); a parameter on a bound the step would
    cross stays there, and the step is kept within ``lower`` .. ``upper``."""
    jac = fitted.jacobian
    return _bounded_step(
        jac.T @ jac, _normal_change(fitted, moved), fitted.x, lower, upper, _column_norms(jac)
    )


def effects_at(base: EffectSet, classes: Sequence[type[Effect]], x: np.ndarray) -> EffectSet:
    """``base`` with an effect of each of ``classes`` at the parameters ``x`` (in the fit's
    order: class by class, each in its ``PARAMETER_RANGES`` order), replacing one of the same
    name: how :func:`_fit` builds each candidate point, and the input term a fitted one."""
    wanted = sum(len(cls.PARAMETER_RANGES) for cls in classes)
    if len(x) != wanted:
        raise CloseLoopError(f"{len(x)} parameters for the {wanted} of {classes}")
    values = iter(map(float, x))
    effects = base
    for cls in classes:
        effects = effects.with_effect(
            cls.from_parameters({name: next(values) for name in cls.PARAMETER_RANGES})
        )
    return effects


MAX_BROYDEN_CONDITION = 1e8
"""An update of the input term's normal matrix (:func:`input_shift`) that would leave it worse
conditioned than this (scaled by the Jacobian's column norms) is not taken."""


def input_shift(
    fitted: FitResult,
    residual_at: Callable[[np.ndarray], np.ndarray],
    lower: np.ndarray,
    upper: np.ndarray,
    tolerance: float = 0.05,
    max_steps: int = 5,
) -> tuple[np.ndarray, int]:
    """The fitted parameters' shift when an input changes (``residual_at(x)``: the residual
    at parameters ``x`` with the input changed, on the evaluator's seconds): the ``x`` where
    the changed residual satisfies the fit's normal equations as the fit's own residual does,
    ``J^T (r_moved(x) - r) = 0`` (``J`` the fit's Jacobian), by quasi-Newton steps on those
    p equations, one evaluation each. The first step is the Gauss-Newton one with ``J^T J``
    (:func:`gauss_newton_shift`, the linear sensitivity); after each, the p x p matrix is
    corrected by Broyden's update along the step taken with the change of ``J^T r`` it
    brought (no new evaluation: the response over the shift as measured, not as the fit's
    Jacobian says). Stops when a step is at most ``tolerance`` of the shift in every
    parameter (or after ``max_steps`` evaluations).

    Why not the chord alone (``J^T J`` every step, until session 11): the fit's Jacobian is a
    forward difference of 5 % (a secant on the scale of a convection quantum,
    ``H_QUANTUM_W_M2K``); over the input term's much smaller shift a convection law's
    residual responds by 30-50 % of what that Jacobian says (a convection varying inside a
    piece is rounded, so on that scale the residual is a step function of the parameters),
    and the chord then contracts by only 0.5-0.7 a step: on the bench fleet it ran to its 5
    steps 5 % short of its own limit (docs/closeloop.md, session 11). A parameter on a bound
    the step would cross stays there. Returns the shift and the evaluations spent."""
    jac = fitted.jacobian
    norms = _column_norms(jac)
    normal = jac.T @ jac
    x = fitted.x.copy()
    floor = 1e-12 * (1.0 + np.abs(fitted.x))
    evaluations = 0
    g_last: np.ndarray | None = None
    step = np.zeros(x.size)
    while evaluations < max_steps:
        g = _normal_change(fitted, residual_at(x))
        evaluations += 1
        if g_last is not None and float(step @ step) > 0.0:
            updated = normal + np.outer(g - g_last - normal @ step, step) / float(step @ step)
            if np.linalg.cond(updated / np.outer(norms, norms)) < MAX_BROYDEN_CONDITION:
                normal = updated
        g_last = g
        step = _bounded_step(normal, g, x, lower, upper, norms)
        x = x + step
        logger.debug(
            "input term: evaluation %d, |J^T dr| %.4g, step %s, shift %s",
            evaluations,
            float(np.linalg.norm(g)),
            np.array2string(step, precision=6),
            np.array2string(x - fitted.x, precision=6),
        )
        if np.all(np.abs(step) <= tolerance * np.abs(x - fitted.x) + floor):
            break
    return x - fitted.x, evaluations


def _input_term(
    fitted: FitResult, shift: np.ndarray, noise_kmh: float, evaluations: int
) -> InputTerm:
    """The input term of the chosen parameters (``fitted``) from their ``shift`` with the
    speed debiased by ``noise_kmh`` (:func:`input_shift`, in ``evaluations``)."""
    qualified = len({name.split(".", 1)[0] for name in fitted.names}) > 1
    keys = [_report_key(name, qualified) for name in fitted.names]
    return InputTerm(
        noise_kmh,
        dict(zip(keys, map(float, fitted.x + shift), strict=True)),
        dict(zip(keys, map(float, shift), strict=True)),
        evaluations,
    )


def _add_verdict(
    report: dict[str, Any],
    verdict: Adequacy,
    intervals: BlockedIntervals | Mapping[str, tuple[float, float]] | None,
    numerical: Numerical | None = None,
    inputs: InputTerm | None = None,
) -> None:
    """The report's ``parameter_intervals``, ``adequate`` and ``unexplained`` (interface.md
    v2), the figures behind the verdict (``adequacy``) and the three statistical intervals
    the reported ones are the widest of (``interval_methods``), and the numerical and input
    terms added to them in quadrature (``interval_methods.numerical`` and ``.input``, when
    computed)."""
    if isinstance(intervals, BlockedIntervals):
        report["interval_methods"] = {
            "blocks": intervals.blocks,
            "widest": intervals.method,
            "jacobian": intervals_for_json(intervals.jacobian),
            "sandwich": intervals_for_json(intervals.sandwich),
            "jackknife": intervals_for_json(intervals.jackknife),
            "statistical": intervals_for_json(intervals.intervals),
        }
        intervals = intervals.intervals
        terms: list[Mapping[str, float]] = []
        if numerical is not None:
            report["interval_methods"]["numerical"] = numerical.to_json()
            terms.append(numerical.half_width)
        if inputs is not None:
            report["interval_methods"]["input"] = inputs.to_json()
            terms.append(inputs.half_width)
        if terms:
            intervals = with_numerical_term(
                intervals, report.get("parameters") or {}, combined_half_width(terms)
            )
    report.update(
        {
            "parameter_intervals": intervals_for_json(intervals or {}),
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


def _judge_on_report(wh: Warehouse, report: dict[str, Any], config: CloseLoopConfig) -> None:
    """The verdict judged on the figure the report shows: the fit RMSE of the revision the
    report ends with, from ``v_predictions`` over the fit events as they stand after the
    re-flagging, less only the outlier events the report names (the fit's verdict was judged
    on the events of the choice, before the re-flagging; they differ when the flags moved).
    ``adequacy`` gives both figures: ``rmse_fit_k`` (every unflagged fit event, the report's
    ``fit.rmse_after_k``) and ``rmse_judged_k`` (less the outliers: what ``adequate`` is
    judged on), with ``ratio`` = ``rmse_judged_k / noise_k``."""
    noise = report.get("noise_k")
    ad = report.get("adequacy")
    if not noise or ad is None:
        return
    revision = report.get("new_revision") or report["baseline_revision"]
    unknown_heat = report.get("unknown_heat", {}).get("event_ids", ())
    fit, _, _ = _event_sets(wh, report["baseline_revision"], config, unknown_heat)
    fit_ids = fit["event_id"].to_list()
    outliers = set(report.get("outliers", {}).get("event_ids", ()))
    kept = [e for e in fit_ids if e not in outliers]
    judged = rmse_from_predictions(wh, revision, kept) if kept else float("nan")
    if not math.isfinite(judged):
        return
    ratio = judged / noise
    adequate = bool(ratio <= MAX_NOISE_RATIO)
    ad.update(
        {
            "rmse_choice_k": ad.get("rmse_k"),
            "rmse_k": round(judged, 5),
            "rmse_judged_k": round(judged, 5),
            "rmse_fit_k": report["fit"].get("rmse_after_k"),
            "ratio": round(ratio, 3),
            "max_ratio": MAX_NOISE_RATIO,
            "judged_on": (
                f"v_predictions of {revision} over the {len(kept)} fit events of the report "
                f"less the {len(fit_ids) - len(kept)} outlier events (fit.rmse_after_k counts "
                "them too)"
            ),
        }
    )
    if adequate == report.get("adequate"):
        return
    report["adequate"] = adequate
    if adequate:
        report["unexplained"] = None
        return
    before = report["fit"].get("rmse_before_k")
    rest = (
        f"{judged:.2g} K remains against {noise:.2g} K of sensor noise, "
        f"{describe_drivers(ad.get('correlations', {}))}"
    )
    if report.get("new_revision"):
        share = (
            f" explains {100 * max(1.0 - (judged / before) ** 2, 0.0):.0f} % of the residual"
            if before
            else " was added"
        )
        report["unexplained"] = f"partly explained: {report['effect']}{share}; {rest}"
    else:
        report["unexplained"] = f"not explained: {rest}"


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


def _make_revision(
    wh: Warehouse,
    wagons: Mapping[str, WagonConfig],
    revision: Revision,
    sim: SimulationConfig,
    event_ids: Sequence[str],
    fit: pl.DataFrame,
    engine: Engine | None,
) -> None:
    """Simulate ``event_ids`` with the new ``revision`` and re-estimate the virtual sensor
    with it (every wagon), its sigma_w fitted first on the days of the ``fit`` events (a
    property of the revision: docs/estimator.md).

    The simulation and the estimate are independent (the estimate and the sigma_w fit read
    the samples, not the predictions; they write other tables), so the simulation runs on a
    second connection (a cursor of ``wh``'s, its writes on its own writer thread) in a thread
    of its own while sigma_w is fitted and the wagons are estimated: the partitions of both
    share the engine's workers, which no longer wait between the three steps for the
    parent's reads and last commits. The same rows as the three one after the other (the
    same pure functions of the same partitions); the simulation's progress bar is not shown
    (one live display at a time)."""
    config = EstimationConfig(chain=sim.chain)
    ids = list(event_ids)
    cursor = wh.con.cursor()
    try:
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="revision-simulation") as pool:
            simulated = pool.submit(
                simulate_events,
                Warehouse(wh.path, cursor, None),
                wagons,
                revision,
                sim,
                event_ids=ids,
                progress=False,
                engine=engine,
            )
            try:
                fit_revision_noise(wh, wagons, revision, fit, config, engine=engine)
                estimate_wagons(wh, wagons, revision, config, engine=engine)
            finally:
                # the thread ends before anything is raised: the estimate's error, else the
                # simulation's
                wait_for([simulated])
            simulated.result()
    finally:
        cursor.close()


def refit_moved(
    chosen: Candidate, refit: FitResult, intervals: BlockedIntervals, tolerance: float
) -> list[str]:
    """The parameters (``effect.parameter``) of the re-flag ``refit`` that moved from the
    ``chosen`` candidate's by more than ``tolerance`` times the half-width of their 95 %
    interval (``intervals``, the refit's own, keyed as its names): a move inside that is
    within the fit's uncertainty and leaves the revision as it was made. A parameter the
    chosen candidate lacks counts as moved; one whose interval is not finite never does (the
    data do not determine it: its move changes nothing)."""
    before = {f"{e.name}.{k}": v for e in chosen.effects for k, v in e.parameters.items()}
    moved = []
    for name, value in zip(refit.names, refit.x, strict=True):
        if name not in before:
            moved.append(name)
            continue
        lo, hi = intervals.intervals.get(name, (-math.inf, math.inf))
        half = 0.5 * (hi - lo)
        if math.isfinite(half) and abs(float(value) - before[name]) > tolerance * half:
            moved.append(name)
    return moved


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
    # the workers import what a fit runs (least_squares is imported when a fit starts)
    preload = ("fleetbrake.closeloop.loop", "scipy.optimize")
    return make_engine(name, workers, address=address, preload=preload)


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
    with pool, ThreadPoolExecutor(max_workers=1, thread_name_prefix="closeloop-report") as side:
        with open_warehouse(db_path, wait_s=wait_s) as wh:
            # the workers start and import the close loop while the wagons are loaded, not at
            # the screening's first fit (about a processor-second each)
            pool.start()
            report = close_loop(wh, config, None if isinstance(pool, InlineEngine) else pool)
            json_out = Path(json_out)
            json_out.parent.mkdir(parents=True, exist_ok=True)
            text = json.dumps(report, indent=2, default=str) + "\n"
            json_out.write_text(text, encoding="utf-8")
            markdown = read_markdown_report(wh, report, json_out.with_suffix(".md"))
            # the Markdown report's plots are drawn on a worker, and the workers stopped,
            # while the warehouse closes (DuckDB's checkpoint merges the new revision's row
            # groups: about 1.5 processor-s of its own)
            written = side.submit(_write_and_stop, markdown, pool)
        written.result()
    return report


def _write_and_stop(markdown: MarkdownReport, engine: Engine) -> None:
    """Write the Markdown report (its plots drawn on one of ``engine``'s workers), then stop
    the engine's workers: it has no more work."""
    try:
        markdown.write(engine)
    finally:
        engine.close()
