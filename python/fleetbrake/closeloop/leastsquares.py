"""The effects' parameters fitted by bounded least squares on cached fit data: the fit
(:func:`fit_parameters`), its result (:class:`FitResult`), and the tasks an engine's workers run
(:class:`FitTask`, :class:`EvalTask`: pure functions of their data, picklable)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from fleetbrake.closeloop import fitdata
from fleetbrake.closeloop.errors import CloseLoopError
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.stats import (
    BlockedIntervals,
    blocked_intervals,
    effective_sample_size,
    standard_errors,
)
from fleetbrake.model.effects import Effect, EffectSet

__all__ = [
    "EvalTask",
    "Evaluator",
    "FitResult",
    "FitTask",
    "effects_at",
    "eval_task",
    "fit_intervals",
    "fit_parameters",
    "fit_task",
    "kept_seconds",
    "parameter_bounds",
    "report_key",
]


class Evaluator(Protocol):
    """What a fit evaluates: measured - predicted at fixed seconds for each effect set (NaN
    where a candidate predicts nothing); :class:`~fleetbrake.closeloop.fitdata.FitData`."""

    def residuals(self, effect_sets: Sequence[EffectSet]) -> list[np.ndarray]: ...


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

    @property
    def report_keys(self) -> list[str]:
        """The parameters' keys in the report, in the fit's order (:func:`report_key`:
        ``effect.parameter`` when the fit holds several effects)."""
        qualified = len({name.split(".", 1)[0] for name in self.names}) > 1
        return [report_key(name, qualified) for name in self.names]


def forward_steps(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, rel: float) -> np.ndarray:
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


def fit_parameters(
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
    (:func:`~fleetbrake.closeloop.stats.standard_errors`, on the effective sample size of
    the start's residual over ``blocks``, evaluator seconds; every second its own block when
    None): such a step, accepted or not, moves no parameter by more than that share of its
    own uncertainty (docs/closeloop.md, "3. Fit": "Refits stop at the fit's resolution")."""
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
        h = forward_steps(np.asarray(x, dtype=np.float64), lower, upper, diff_step)
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
    in every parameter (:func:`fit_parameters`; 0: scipy's own stopping only)."""

    def __str__(self) -> str:  # how an engine names the partition in an error
        return "candidate " + "+".join(cls.name for cls in self.classes)


def fit_task(task: FitTask) -> FitResult:
    """Run one :class:`FitTask` (a pure function of it: picklable, for the workers)."""
    data = task.data if isinstance(task.data, FitData) else fitdata.stored(task.data)
    calls = fitdata.kernel_calls()
    keep = kept_seconds(data, task.exclude)
    fitted = fit_parameters(
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


def kept_seconds(data: FitData, exclude: frozenset[str]) -> np.ndarray | None:
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


def effects_at(base: EffectSet, classes: Sequence[type[Effect]], x: np.ndarray) -> EffectSet:
    """``base`` with an effect of each of ``classes`` at the parameters ``x`` (in the fit's
    order: class by class, each in its ``PARAMETER_RANGES`` order), replacing one of the same
    name: how :func:`fit_parameters` builds each candidate point, and the input term a fitted
    one."""
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


def report_key(name: str, qualified: bool) -> str:
    """A fitted parameter's key in the report (``name`` is ``effect.parameter``): the
    parameter's own name when one effect was added, ``effect.parameter`` when several (two
    effects' parameters never collide)."""
    return name if qualified else name.split(".", 1)[1]


def fit_intervals(fitted: FitResult, data: FitData) -> BlockedIntervals:
    """95 % intervals of a fit's parameters keyed ``effect.parameter``
    (:func:`~fleetbrake.closeloop.stats.blocked_intervals`, wagon-days as blocks)."""
    return blocked_intervals(
        fitted.jacobian, fitted.aligned, fitted.x, fitted.names, data.blocks[fitted.scored]
    )
