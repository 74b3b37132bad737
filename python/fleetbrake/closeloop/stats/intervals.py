"""How sure the fitted parameters are: the Jacobian covariance on the effective sample size,
the cluster-robust and delete-one-block jackknife intervals, the numerical term (Roache's grid
convergence index) added in quadrature, and whether a law's parameters are distinguishable
from the values at which its part vanishes (:data:`EFFECT_NULLS`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from fleetbrake.closeloop.stats.blocks import (
    SelectionError,
    as_arrays,
    block_slices,
    effective_sample_size,
)
from fleetbrake.closeloop.stats.heldout import Comparison

GCI_SAFETY_FACTOR = 3.0
"""Roache's safety factor of the grid convergence index for a study of two grids (1.25 needs
three, with the observed order of convergence)."""

GCI_ORDER = 2.0
"""The formal order of convergence the GCI assumes: quadratic (hex20) elements converge in
the flux, which is what the effects' parameters act through, at second order."""


# ---------------------------------------------------------------------------- intervals
def parameter_covariance(jacobian: np.ndarray, residual: np.ndarray, n_eff: float) -> np.ndarray:
    """The fitted parameters' covariance from the fit's Jacobian: ``s^2 (J^T J)^-1`` with
    ``s^2 = sum r^2 / (n - p)``, inflated by ``n / n_eff`` (the residual's correlation: ``n``
    correlated seconds carry the information of ``n_eff`` independent ones); ``inf`` everywhere
    when ``J^T J`` is singular (the residual does not determine the parameters)."""
    r = np.asarray(residual, dtype=np.float64).ravel()
    n = r.size
    j = np.asarray(jacobian, dtype=np.float64).reshape(n, -1)
    p = j.shape[1]
    if n <= p:
        raise SelectionError(f"{n} residuals cannot bound {p} parameters")
    s2 = float(np.sum(r * r)) / (n - p)
    inflation = n / min(max(float(n_eff), 1.0), float(n))
    try:
        return np.asarray(np.linalg.inv(j.T @ j) * s2 * inflation, dtype=np.float64)
    except np.linalg.LinAlgError:
        return np.full((p, p), np.inf)


def standard_errors(jacobian: np.ndarray, residual: np.ndarray, n_eff: float) -> np.ndarray:
    """Each parameter's standard error from the fit's Jacobian on ``n_eff`` independent
    residuals (:func:`parameter_covariance`'s diagonal; ``inf`` where the data do not
    determine it): the resolution a fit's steps are judged against
    (``CloseLoopConfig.refit_step_tolerance``)."""
    var = np.diag(parameter_covariance(jacobian, residual, n_eff))
    ok = np.isfinite(var) & (var >= 0.0)
    return np.where(ok, np.sqrt(np.where(ok, var, 0.0)), np.inf)


def parameter_intervals(
    jacobian: np.ndarray,
    residual: np.ndarray,
    x: np.ndarray,
    names: Sequence[str],
    n_eff: float,
    level: float = 0.95,
) -> dict[str, tuple[float, float]]:
    """Confidence intervals of fitted parameters ``x`` (names in order) from the fit's
    Jacobian: covariance ``s^2 (J^T J)^-1`` with ``s^2 = sum r^2 / (n - p)``, inflated by
    ``n / n_eff`` (:func:`parameter_covariance`), Student-t quantile on ``n_eff - p`` degrees
    of freedom. A parameter the residual does not determine (a singular ``J^T J``) gets
    ``(-inf, inf)``. The inflation is exact for regressors as smooth as the residual's
    correlation, conservative for faster ones."""
    from scipy.stats import t as student_t

    xs = np.asarray(x, dtype=np.float64).ravel()
    p = xs.size
    if len(names) != p:
        raise SelectionError(f"{len(names)} parameter names for {p} parameters")
    cov = parameter_covariance(jacobian, residual, n_eff)
    dof = max(float(n_eff) - p, 1.0)
    q = float(student_t.ppf(0.5 + level / 2.0, dof))
    out = {}
    for i, name in enumerate(names):
        var = cov[i, i]
        half = q * math.sqrt(var) if np.isfinite(var) and var >= 0 else math.inf
        out[name] = (float(xs[i] - half), float(xs[i] + half))
    return out


@dataclass(frozen=True)
class BlockedIntervals:
    """The intervals of :func:`blocked_intervals` and the three they are the widest of."""

    intervals: dict[str, tuple[float, float]]
    """Per parameter, the widest of the three (what the report gives)."""
    jacobian: dict[str, tuple[float, float]]
    """``s^2 (J^T J)^-1`` inflated by ``n / n_eff`` (:func:`parameter_intervals`)."""
    sandwich: dict[str, tuple[float, float]]
    """Cluster-robust covariance, the blocks as clusters (empty with fewer than 3 blocks)."""
    jackknife: dict[str, tuple[float, float]]
    """Delete-one-block jackknife (empty with fewer than 3 blocks)."""
    blocks: int
    method: dict[str, str]
    """Per parameter, which of the three gave the reported interval."""


def _symmetric(
    x: np.ndarray, names: Sequence[str], var: np.ndarray, q: float
) -> dict[str, tuple[float, float]]:
    out = {}
    for i, name in enumerate(names):
        v = float(var[i])
        half = q * math.sqrt(v) if math.isfinite(v) and v >= 0 else math.inf
        out[name] = (float(x[i] - half), float(x[i] + half))
    return out


def blocked_intervals(
    jacobian: np.ndarray,
    residual: np.ndarray,
    x: np.ndarray,
    names: Sequence[str],
    blocks: np.ndarray,
    n_eff: float | None = None,
    level: float = 0.95,
) -> BlockedIntervals:
    """Confidence intervals of fitted parameters that see what varies from block to block (a
    reduced model's error against the world, and parameter trade-offs, shift the best
    parameters from one wagon-day to the next; a residual-based interval misses that).

    From the fit's residual ``r`` and Jacobian ``J`` at its optimum ``x`` (rows in the order
    of ``blocks``, one id per second), with ``A_g = J_g^T J_g``, ``u_g = J_g^T r_g`` per block
    g of G, ``A = sum A_g``:

    * **Jacobian**: :func:`parameter_intervals` on ``n_eff`` (computed from the residual when
      None).
    * **Sandwich** (cluster-robust): ``A^-1 (sum_g u_g u_g^T) A^-1 G / (G - 1)``, the ``u_g``
      centred (an optimum cut short by the iteration limit).
    * **Jackknife** (delete one block): the fit without block g one Gauss-Newton step from
      ``x``, ``x_g = x - (A - A_g)^-1 (J^T r - u_g)`` (nothing re-simulated), variance
      ``(G - 1) / G sum (x_g - mean)^2``; a parameter that no other block determines (``A -
      A_g`` singular) gets an unbounded interval.

    The last two use Student-t quantiles on ``G - 1`` degrees of freedom (the blocks are the
    independent units); each parameter's reported interval is the widest of the three.
    Fewer than 3 blocks: the Jacobian interval only."""
    from scipy.stats import t as student_t

    r, b = as_arrays(residual, blocks)
    xs = np.asarray(x, dtype=np.float64).ravel()
    p = xs.size
    j = np.asarray(jacobian, dtype=np.float64).reshape(r.size, p)
    if n_eff is None:
        n_eff = effective_sample_size(r, b)
    plain = parameter_intervals(j, r, xs, names, n_eff, level)
    order, starts, lengths = block_slices(b)
    g_count = int(starts.size)
    sandwich: dict[str, tuple[float, float]] = {}
    jackknife: dict[str, tuple[float, float]] = {}
    if g_count >= 3 and p > 0:
        jo, ro = j[order], r[order]
        a_g = np.empty((g_count, p, p))
        u_g = np.empty((g_count, p))
        for i, (start, length) in enumerate(zip(starts, lengths, strict=True)):
            jb, rb = jo[start : start + length], ro[start : start + length]
            a_g[i] = jb.T @ jb
            u_g[i] = jb.T @ rb
        a = a_g.sum(axis=0)
        u = u_g.sum(axis=0)
        q = float(student_t.ppf(0.5 + level / 2.0, g_count - 1))
        try:
            a_inv = np.linalg.inv(a)
            centred = u_g - u_g.mean(axis=0)
            meat = centred.T @ centred
            cov = a_inv @ meat @ a_inv * g_count / (g_count - 1)
            var_s = np.diag(cov)
        except np.linalg.LinAlgError:
            var_s = np.full(p, np.inf)
        sandwich = _symmetric(xs, names, var_s, q)
        steps = np.empty((g_count, p))
        for i in range(g_count):
            rest = a - a_g[i]
            if np.linalg.cond(rest) > 1e12:
                steps[i] = np.inf
                continue
            steps[i] = -np.linalg.solve(rest, u - u_g[i])
        if np.all(np.isfinite(steps)):
            var_j = (g_count - 1) / g_count * ((steps - steps.mean(axis=0)) ** 2).sum(axis=0)
        else:
            var_j = np.full(p, np.inf)
        jackknife = _symmetric(xs, names, var_j, q)
    reported: dict[str, tuple[float, float]] = {}
    method: dict[str, str] = {}
    for name in names:
        choices = [("jacobian", plain[name])]
        if name in sandwich:
            choices.append(("sandwich", sandwich[name]))
        if name in jackknife:
            choices.append(("jackknife", jackknife[name]))
        label, (lo, hi) = max(choices, key=lambda kv: kv[1][1] - kv[1][0])
        reported[name] = (lo, hi)
        method[name] = label
    return BlockedIntervals(
        intervals=reported,
        jacobian=plain,
        sandwich=sandwich,
        jackknife=jackknife,
        blocks=g_count,
        method=method,
    )


def grid_convergence_index(
    x_fine: np.ndarray,
    x_coarse: np.ndarray,
    ratio: float,
    order: float = GCI_ORDER,
    safety: float = GCI_SAFETY_FACTOR,
) -> np.ndarray:
    """Roache's grid convergence index of parameters fitted through two meshes, as a
    half-width in the parameters' units: ``safety |x_coarse - x_fine| / (ratio^order - 1)``,
    ``ratio`` > 1 the fine mesh's cells per direction over the coarse one's (P. J. Roache,
    *Verification and Validation in Computational Science and Engineering*, 1998, ch. 5;
    ASME V&V 20-2009, sec. 5). It bounds the fine mesh's numerical error with about 95 %
    confidence: the estimate V&V 20 calls ``u_num`` (expanded)."""
    fine = np.asarray(x_fine, dtype=np.float64).ravel()
    coarse = np.asarray(x_coarse, dtype=np.float64).ravel()
    if fine.shape != coarse.shape:
        raise SelectionError(f"{fine.size} fine and {coarse.size} coarse parameters")
    if not (math.isfinite(ratio) and ratio > 1.0):
        raise SelectionError(f"grid ratio must be > 1 (fine over coarse), got {ratio}")
    if not (order > 0.0 and safety > 0.0):
        raise SelectionError(f"order and safety must be > 0, got {order}, {safety}")
    return safety * np.abs(coarse - fine) / (ratio**order - 1.0)


def with_numerical_term(
    intervals: Mapping[str, tuple[float, float]],
    x: Mapping[str, float],
    half_widths: Mapping[str, float],
) -> dict[str, tuple[float, float]]:
    """The intervals widened by a numerical (model-form) half-width: ``x +- sqrt(h_stat^2 +
    h_num^2)``, ``h_stat`` the statistical interval's half-width about ``x`` (its larger
    side), as ASME V&V 20 combines independent uncertainties (root sum of squares). A
    parameter without a numerical term keeps its interval; an unbounded one stays so."""
    out = {}
    for name, (lo, hi) in intervals.items():
        h_num = float(half_widths.get(name, 0.0))
        if name not in x or not math.isfinite(h_num) or h_num == 0.0:
            out[name] = (lo, hi)
            continue
        centre = float(x[name])
        h_stat = max(centre - lo, hi - centre, 0.0)
        half = math.hypot(h_stat, h_num) if math.isfinite(h_stat) else math.inf
        out[name] = (centre - half, centre + half)
    return out


def combined_half_width(terms: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Independent half-widths of the same parameters combined by root sum of squares (ASME
    V&V 20: the numerical and the input uncertainty); a parameter missing from a term has
    none from it."""
    names = [name for term in terms for name in term]
    return {
        name: math.sqrt(sum(float(term.get(name, 0.0)) ** 2 for term in terms))
        for name in dict.fromkeys(names)
    }


EFFECT_NULLS: dict[str, dict[str, float]] = {
    "friction_temperature[linear]": {"fade_per_k": 0.0},
    "heat_partition[effusivity]": {"contact_factor": 1.0},
    "convection_speed[power]": {"gain": 0.0},
    "convection_speed[flat_plate]": {"multiplier": 0.0},
    "holder_conduction[conductance]": {"h_holder_extra_w_m2k": 0.0},
    "ambient_offset[offset]": {"offset_k": 0.0},
    "sensor_lag[first_order]": {"tau_s": 0.0},
    "empirical[linear]": {
        "flux_gain": 0.0,
        "flux_speed_gain": 0.0,
        "h_extra_w_m2k": 0.0,
        "h_speed_w_m2k": 0.0,
    },
}
"""Per law (``name[law]``), the parameter values at which its part of the model vanishes
(the declared model again): a fade of 0, the declared contact (factor 1), no added
convection, conductance or offset, no lag, no correction. A law without an entry (Karwatzki's
friction, which replaces the registry's mu rather than scaling it; the partition given as
alpha, whose null is each block's declared alpha) is judged by the held-out blocks alone.
``empirical`` vanishes only when all four are null: it is distinguishable when any one is
(``distinguishable_from_null(any_of=True)``)."""


def distinguishable_from_null(
    intervals: Mapping[str, tuple[float, float]],
    nulls: Mapping[str, float],
    *,
    any_of: bool = False,
) -> bool:
    """True when every parameter given a null value (the value at which its part of the effect
    vanishes: a scale of 0, a lag of 0 s, the registry's own partition) has an interval that
    excludes it (``any_of``: at least one of them, for an effect that vanishes only when all
    its parameters are null). A parameter without an interval is not distinguishable. No
    nulls: True (nothing to test)."""
    if not nulls:
        return True
    outside = []
    for name, null in nulls.items():
        lo, hi = intervals.get(name, (-math.inf, math.inf))
        outside.append(null < lo or null > hi)
    return any(outside) if any_of else all(outside)


def refusal(
    comparison: Comparison,
    intervals: Mapping[str, tuple[float, float]],
    nulls: Mapping[str, float],
    *,
    any_of: bool = False,
) -> str | None:
    """Why a candidate does not enter over a simpler model, or None when it does: it must
    improve the held-out blocks by the margin (:func:`improves_held_out`) and its parameters
    must be distinguishable from their nulls (:func:`distinguishable_from_null`)."""
    reasons = []
    if not comparison.improves:
        reasons.append(comparison.describe())
    if not distinguishable_from_null(intervals, nulls, any_of=any_of):
        near = [
            f"{name} = {null:g} within [{intervals[name][0]:.3g}, {intervals[name][1]:.3g}]"
            if name in intervals
            else f"{name} undetermined"
            for name, null in nulls.items()
            if not (name in intervals and (null < intervals[name][0] or null > intervals[name][1]))
        ]
        reasons.append("not distinguishable from its null: " + ", ".join(near))
    return "; ".join(reasons) if reasons else None


def intervals_for_json(
    intervals: Mapping[str, tuple[float, float]], digits: int = 6
) -> dict[str, list[float | None]]:
    """The intervals as the JSON report writes them (``parameter_intervals``): ``[low,
    high]`` rounded to ``digits`` significant digits, an unbounded side as null (JSON has no
    infinity)."""

    def value(v: float) -> float | None:
        return float(f"{v:.{digits}g}") if math.isfinite(v) else None

    return {name: [value(lo), value(hi)] for name, (lo, hi) in intervals.items()}
