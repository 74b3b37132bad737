"""The reported intervals' two terms beyond the statistical one: the numerical term (the chosen
effects refitted through coarser meshes, Roache's grid convergence index of the shift:
:func:`numerical_term`) and the input term (the chosen parameters' shift when the speed is read
without the bias its noise puts in a magnitude, by quasi-Newton steps from the fit's Jacobian:
:func:`input_shift`, :func:`input_term`)."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.errors import CloseLoopError
from fleetbrake.closeloop.leastsquares import FitResult
from fleetbrake.closeloop.stats import grid_convergence_index
from fleetbrake.model.estimator import noise_from_second_differences
from fleetbrake.simulation.predictions import Revision, WagonData
from fleetbrake.simulation.series import FloatArray

__all__ = [
    "InputTerm",
    "Numerical",
    "gauss_newton_shift",
    "input_shift",
    "input_term",
    "numerical_term",
    "speed_noise_kmh",
    "with_speed_debiased",
]

logger = logging.getLogger(__name__)


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


def numerical_term(
    fine: FitResult, coarse: Sequence[FitResult], base: Revision, config: CloseLoopConfig
) -> Numerical:
    """The numerical term of the chosen parameters (``fine``, fitted through ``base``'s mesh)
    from their refits through the coarser meshes of ``config.numerical_grid_ratios``
    (:func:`~fleetbrake.closeloop.stats.grid_convergence_index`, the largest per
    parameter), keyed as the report's ``parameters``."""
    keys = fine.report_keys
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

    Why not the chord alone (``J^T J`` every step): the fit's Jacobian is a
    forward difference of 5 % (a secant on the scale of a convection quantum,
    ``H_QUANTUM_W_M2K``); over the input term's much smaller shift a convection law's
    residual responds by 30-50 % of what that Jacobian says (a convection varying inside a
    piece is rounded, so on that scale the residual is a step function of the parameters),
    and the chord then contracts by only 0.5-0.7 a step: on the bench fleet it runs to its 5
    steps 5 % short of its own limit. A parameter on a bound
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


def input_term(
    fitted: FitResult, shift: np.ndarray, noise_kmh: float, evaluations: int
) -> InputTerm:
    """The input term of the chosen parameters (``fitted``) from their ``shift`` with the
    speed debiased by ``noise_kmh`` (:func:`input_shift`, in ``evaluations``)."""
    keys = fitted.report_keys
    return InputTerm(
        noise_kmh,
        dict(zip(keys, map(float, fitted.x + shift), strict=True)),
        dict(zip(keys, map(float, shift), strict=True)),
        evaluations,
    )


MOVING_KMH = 5.0
"""km/h: :func:`speed_noise_kmh` reads the GPS speed's noise where the logged speed is above
this on three consecutive seconds (a wagon that moves: its speed changes smoothly)."""


def speed_noise_kmh(loaded: Mapping[str, WagonData], moving_kmh: float = MOVING_KMH) -> float:
    """The logged GPS speed's white noise (km/h), from the data: the second differences of the
    logged speed (``speed_raw_kmh``) over three consecutive logged seconds all above
    ``moving_kmh``, of every span of every wagon, scaled robustly
    (:func:`~fleetbrake.model.estimator.noise_from_second_differences`: 1.4826 MAD / sqrt 6;
    a train's speed changes smoothly, so its second differences are the noise's). NaN when no
    such seconds."""
    parts: list[FloatArray] = []
    for data in loaded.values():
        for series in data.spans:
            v = series.speed_raw_kmh
            if v.size < 3:
                continue
            d2 = v[2:] - 2.0 * v[1:-1] + v[:-2]
            ok = np.isfinite(d2) & (v[2:] > moving_kmh) & (v[1:-1] > moving_kmh)
            ok &= v[:-2] > moving_kmh
            parts.append(d2[ok])
    d2 = np.concatenate(parts) if parts else np.zeros(0)
    return noise_from_second_differences(d2) if d2.size >= 3 else math.nan


def with_speed_debiased(loaded: Mapping[str, WagonData], noise_kmh: float) -> dict[str, WagonData]:
    """The wagons with their speed (logged and interpolated) read without the bias its noise
    puts in a magnitude: ``sqrt(max(v^2 - noise^2, 0))`` (a GPS speed is ``|v + e|``, whose
    mean square is ``v^2 + noise^2``: at standstill it reads about its noise, not 0; at
    running speeds the correction is nothing). The input's systematic error, for the
    sensitivity of a fit to it (the reported intervals' input term). The
    running median the model is driven by commutes with it (it is monotone), so the driving
    speed is debiased alike."""

    def debiased(v: FloatArray) -> FloatArray:
        with np.errstate(invalid="ignore"):
            return np.where(
                np.isfinite(v), np.sqrt(np.maximum(v * v - noise_kmh * noise_kmh, 0.0)), v
            )

    return {
        wagon_id: dataclasses.replace(
            data,
            spans=[
                dataclasses.replace(
                    s, speed_kmh=debiased(s.speed_kmh), speed_raw_kmh=debiased(s.speed_raw_kmh)
                )
                for s in data.spans
            ],
        )
        for wagon_id, data in loaded.items()
    }
