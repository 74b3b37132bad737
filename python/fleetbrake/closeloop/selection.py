"""The close loop's statistics: how many independent residuals there are, whether a candidate
improves what it was not fitted on, how sure its parameters are, and whether the chosen model
is adequate (issue 13; the method and its reasons: ``docs/closeloop.md``).

Pure numpy on arrays (no database, no simulation): a residual is one value per second, in time
order within each *block* (``blocks``: an id per second, integers or any sortable labels
such as event ids, for a wagon-day or an event chain). Nothing here looks across a block boundary: the seconds of one block are correlated,
blocks are taken as independent of each other.

* :func:`effective_sample_size` -- ``n / tau`` with ``tau = 1 + 2 sum rho_k`` from the
  residual's autocorrelation pooled over blocks, truncated by Geyer's initial monotone
  positive sequence; bounded by ``[n_blocks, n]``.
* :func:`information_criterion` -- BIC on that effective sample size.
* :func:`block_folds`, :func:`held_out_residual`, :func:`blocked_cv_rmse`,
  :func:`improves_held_out` -- blocked cross-validation: whole blocks per fold; a fitted
  candidate's held-out residual from its Jacobian (one Gauss-Newton step from the fit on all
  blocks to the fit without the fold: exact for a model linear in its parameters), so that
  the comparison costs no re-simulation.
* :func:`parameter_intervals`, :func:`distinguishable_from_null` -- Gauss-Newton covariance
  ``s^2 (J^T J)^-1`` inflated by ``n / n_eff``, Student-t intervals on ``n_eff - p`` degrees
  of freedom; :func:`refusal` says why a candidate does not enter (not by the margin on the
  held-out blocks, or a parameter not distinguishable from its null).
* :func:`blocked_intervals` -- the intervals the close loop reports: the wider of the
  ``n_eff`` Jacobian interval, a cluster-robust (sandwich) interval with the blocks as
  clusters and a delete-one-block jackknife (one Gauss-Newton step per block from the
  optimum with the fit's Jacobian), the last two with Student-t quantiles on ``blocks - 1``
  degrees of freedom; :data:`EFFECT_NULLS` the values at which each law's part vanishes.
* :func:`grid_convergence_index`, :func:`with_numerical_term` -- the numerical (model-form)
  term the resampling cannot see: Roache's GCI of the parameters refitted through coarser
  meshes, added in quadrature to the statistical half-width (ASME V&V 20's combination).
* :func:`noise_from_residual` -- white sensor noise from the residual's second differences
  within blocks (median absolute deviation).
* :func:`adequacy` -- the chosen model's residual against the noise: RMSE ratio, whiteness,
  what it still correlates with, and the sentence the report gives when it is not adequate.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from fleetbrake.errors import FleetbrakeError
from fleetbrake.model.estimator import noise_from_second_differences

__all__ = [
    "EFFECT_NULLS",
    "GCI_ORDER",
    "GCI_SAFETY_FACTOR",
    "HELD_OUT_MARGIN",
    "MAX_NOISE_RATIO",
    "MIN_EXPLAINED_SHARE",
    "Adequacy",
    "BlockedIntervals",
    "Comparison",
    "SelectionError",
    "adequacy",
    "autocorrelation",
    "block_folds",
    "blocked_cv_rmse",
    "blocked_intervals",
    "circular_linear_correlation",
    "describe_drivers",
    "distinguishable_from_null",
    "effective_sample_size",
    "event_rms",
    "grid_convergence_index",
    "held_out_residual",
    "improves_held_out",
    "information_criterion",
    "intervals_for_json",
    "ljung_box_white_fraction",
    "noise_from_residual",
    "outlier_events",
    "parameter_covariance",
    "parameter_intervals",
    "refusal",
    "standard_errors",
    "systematic_share",
    "with_numerical_term",
]

HELD_OUT_MARGIN = 0.05
"""Default practical margin: the relative cut of the held-out RMSE a richer candidate must
bring over a simpler one (5 %). The close loop states its own in its configuration."""

MAX_NOISE_RATIO = 1.5
"""A model is adequate when its fit RMSE is at most this many times the sensor noise."""

OUTLIER_NOISE_FACTOR = 5.0
"""An event is an outlier only when its residual RMS is above this many times the noise..."""

OUTLIER_Z = 5.0
"""... and this many robust standard deviations (1.4826 MAD) above the events' median RMS."""

MAX_OUTLIER_FRACTION = 0.05
"""At most this share of the events is left out as outliers (the worst ones): more is a
misfit of the model, not bad data."""

MIN_CORRELATION = 0.1
"""Drivers whose correlation with a leftover residual is weaker than this are not named."""

GCI_SAFETY_FACTOR = 3.0
"""Roache's safety factor of the grid convergence index for a study of two grids (1.25 needs
three, with the observed order of convergence)."""

GCI_ORDER = 2.0
"""The formal order of convergence the GCI assumes: quadratic (hex20) elements converge in
the flux, which is what the effects' parameters act through, at second order."""

MIN_EXPLAINED_SHARE = 0.5
"""A physical addition that leaves the fit inadequate is named only when it explains at least
this share of the baseline's systematic residual (:func:`systematic_share`): the dominant
cause of the misfit, not a proxy absorbing part of something outside the vocabulary."""


class SelectionError(FleetbrakeError, ValueError):
    """The residual cannot support the statistic asked for (too few seconds or blocks, arrays
    of different lengths); the message says which and how many."""


# ---------------------------------------------------------------------------- blocks
def _as_arrays(residual: np.ndarray, blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r = np.asarray(residual, dtype=np.float64).ravel()
    b = np.asarray(blocks).ravel()
    if r.shape != b.shape:
        raise SelectionError(
            f"residual has {r.size} seconds but blocks has {b.size} block ids: one id per second"
        )
    return r, b


def _block_slices(blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(order, starts, lengths): ``order`` sorts the seconds by block keeping their order
    within a block; block ``i`` is ``order[starts[i]:starts[i] + lengths[i]]``."""
    order = np.argsort(blocks, kind="stable")
    sorted_ids = blocks[order]
    if sorted_ids.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return order, empty, empty
    change = np.flatnonzero(sorted_ids[1:] != sorted_ids[:-1]) + 1
    starts = np.concatenate(([0], change)).astype(np.int64)
    lengths = np.diff(np.concatenate((starts, [sorted_ids.size]))).astype(np.int64)
    return order, starts, lengths


def _autocovariance_sums(values: np.ndarray, blocks: np.ndarray, max_lag: int) -> np.ndarray:
    """``C[k] = sum over blocks, sum_t v[t] v[t+k]`` (both seconds in the block), k = 0..max_lag,
    by FFT: blocks grouped by length (powers of two), each group zero-padded to twice its
    longest and transformed at once, so that no product spans two blocks."""
    order, starts, lengths = _block_slices(blocks)
    v = values[order]
    out = np.zeros(max_lag + 1)
    if lengths.size == 0:
        return out
    group = np.ceil(np.log2(np.maximum(lengths, 1))).astype(np.int64)
    for g in np.unique(group):
        members = np.flatnonzero(group == g)
        longest = int(lengths[members].max())
        size = 1 << math.ceil(math.log2(max(2 * longest, 2)))
        # at most ~4 M values per transform
        per_batch = max(1, (1 << 22) // size)
        for first in range(0, members.size, per_batch):
            batch = members[first : first + per_batch]
            padded = np.zeros((batch.size, size))
            for row, i in enumerate(batch):
                padded[row, : lengths[i]] = v[starts[i] : starts[i] + lengths[i]]
            spectrum = np.fft.rfft(padded, axis=1)
            acov = np.fft.irfft(spectrum * np.conj(spectrum), n=size, axis=1).sum(axis=0)
            upto = min(max_lag + 1, longest)
            out[:upto] += acov[:upto]
    return out


def autocorrelation(residual: np.ndarray, blocks: np.ndarray, max_lag: int) -> np.ndarray:
    """The residual's autocorrelation ``rho_0..rho_max_lag`` pooled over blocks (products only
    within a block, about the residual's overall mean, divided by the pooled variance: the
    biased, positive-definite estimator). A constant offset that differs between blocks counts
    as correlation within each block, as it should: it is not noise."""
    r, b = _as_arrays(residual, blocks)
    if r.size < 2:
        raise SelectionError(f"autocorrelation needs at least 2 seconds, got {r.size}")
    d = r - r.mean()
    c = _autocovariance_sums(d, b, max_lag)
    if c[0] <= 0.0:
        rho = np.zeros(max_lag + 1)
        rho[0] = 1.0
        return rho
    return c / c[0]


def _geyer_tau(rho: np.ndarray) -> float:
    """Integrated autocorrelation time ``1 + 2 sum_{k>=1} rho_k`` truncated by Geyer's
    initial monotone positive sequence: pair sums ``G_m = rho_2m + rho_2m+1`` are added while
    positive, each capped at the previous one (the true sequence is positive and decreasing for
    a reversible process; the estimated tail is noise)."""
    pairs = rho[: 2 * (rho.size // 2)].reshape(-1, 2).sum(axis=1)
    total = 0.0
    previous = math.inf
    for g in pairs:
        if g <= 0.0:
            break
        g = min(float(g), previous)
        total += g
        previous = g
    return max(2.0 * total - 1.0, 0.0)


def effective_sample_size(residual: np.ndarray, blocks: np.ndarray) -> float:
    """How many independent residuals the seconds are worth: ``n / tau``, ``tau`` the
    integrated autocorrelation time of the residual pooled over blocks (lags up to the longest
    block, within blocks only), truncated by Geyer's initial monotone positive sequence.
    Bounded by ``[n_blocks, n]``: blocks are independent, and a residual is never worth more
    than one sample per second. White noise gives about ``n``; AR(1) with coefficient ``rho``
    about ``n (1 - rho) / (1 + rho)``."""
    r, b = _as_arrays(residual, blocks)
    n = r.size
    if n == 0:
        raise SelectionError("effective_sample_size: an empty residual")
    n_blocks = int(np.unique(b).size)
    if n < 4:
        return float(n)
    _, _, lengths = _block_slices(b)
    max_lag = int(min(lengths.max() - 1, n - 1))
    if max_lag < 1:
        return float(n)
    tau = _geyer_tau(autocorrelation(r, b, max_lag))
    if tau <= 0.0:
        return float(n)
    return float(min(max(n / tau, n_blocks), n))


def information_criterion(residual: np.ndarray, n_parameters: int, n_eff: float) -> float:
    """The Bayesian information criterion of a Gaussian residual on ``n_eff`` independent
    samples: ``n_eff log(mean r^2) + p log(n_eff)`` (lower is better). Compare candidates on
    one ``n_eff`` (the smallest of theirs: the most correlated residual sets how many
    independent samples the comparison has)."""
    r = np.asarray(residual, dtype=np.float64)
    if r.size == 0:
        raise SelectionError("information_criterion: an empty residual")
    n = max(float(n_eff), n_parameters + 2.0)
    mse = max(float(np.mean(r * r)), 1e-12)
    return n * math.log(mse) + n_parameters * math.log(n)


# ---------------------------------------------------------------------------- cross-validation
def block_folds(blocks: np.ndarray, k: int, seed: int = 0) -> list[np.ndarray]:
    """``k`` boolean held-out masks over the seconds, each holding whole blocks (a block is
    never split), every block in exactly one fold. Blocks are shuffled (``seed``) and dealt,
    longest first, to the fold with the fewest seconds so far (folds of similar size).
    ``k`` larger than the number of blocks gives one fold per block."""
    b = np.asarray(blocks).ravel()
    ids, inverse, counts = np.unique(b, return_inverse=True, return_counts=True)
    if ids.size < 2:
        raise SelectionError(
            f"blocked cross-validation needs at least 2 blocks (wagon-days or event chains), "
            f"got {ids.size}"
        )
    if k < 2:
        raise SelectionError(f"blocked cross-validation needs k >= 2 folds, got {k}")
    k = min(k, ids.size)
    rng = np.random.default_rng(seed)
    shuffled = rng.permutation(ids.size)
    order = shuffled[np.argsort(-counts[shuffled], kind="stable")]
    load = np.zeros(k, dtype=np.int64)
    fold_of = np.empty(ids.size, dtype=np.int64)
    for i in order:
        f = int(np.argmin(load))
        fold_of[i] = f
        load[f] += counts[i]
    per_second = fold_of[inverse]
    return [per_second == f for f in range(k)]


def held_out_residual(
    residual: np.ndarray, jacobian: np.ndarray | None, folds: Sequence[np.ndarray]
) -> np.ndarray:
    """Each second's residual as the fit *without its fold* would leave it, from a least-squares
    fit on every fold: ``residual`` = f(x) and ``jacobian`` = df/dx (n x p, e.g.
    ``scipy.optimize.least_squares``'s ``fun`` and ``jac`` at the solution). The fit without
    fold F is one Gauss-Newton step from x on the other folds, ``dx = -(J_T^T J_T)^+ J_T^T
    f_T``; the held-out residual is ``f_F + J_F dx``. Exact for a model linear in its
    parameters, a first-order approximation otherwise; costs O(n p^2), no re-simulation. A
    model without parameters (``jacobian`` None or n x 0) is its residual."""
    r = np.asarray(residual, dtype=np.float64).ravel()
    out = r.copy()
    if jacobian is None:
        return out
    j = np.asarray(jacobian, dtype=np.float64).reshape(r.size, -1)
    if j.shape[1] == 0:
        return out
    for mask in folds:
        held = np.asarray(mask, dtype=bool)
        if held.shape != r.shape:
            raise SelectionError(
                f"a fold mask has {held.size} seconds, the residual {r.size}: one per second"
            )
        train = ~held
        jt, ft = j[train], r[train]
        dx = -np.linalg.lstsq(jt, ft, rcond=None)[0] if jt.shape[0] else np.zeros(j.shape[1])
        out[held] = r[held] + j[held] @ dx
    return out


def blocked_cv_rmse(
    residual_fn: Callable[[np.ndarray], np.ndarray], folds: Sequence[np.ndarray]
) -> float:
    """Blocked cross-validation by refitting: ``residual_fn(train_mask)`` fits on the seconds
    of ``train_mask`` and returns the residual of every second; the result is the RMSE over
    each fold's held-out seconds pooled. (:func:`improves_held_out` does the same from one fit's
    Jacobian, without refitting.)"""
    total, count = 0.0, 0
    for mask in folds:
        held = np.asarray(mask, dtype=bool)
        r = np.asarray(residual_fn(~held), dtype=np.float64).ravel()[held]
        r = r[np.isfinite(r)]
        total += float(np.sum(r * r))
        count += r.size
    if count == 0:
        raise SelectionError("blocked_cv_rmse: no held-out seconds")
    return math.sqrt(total / count)


def _rmse(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")


@dataclass(frozen=True)
class Comparison:
    """Blocked cross-validation of a candidate ``b`` against a simpler ``a`` (both fitted on
    every block of the fit period, the held-out residuals from their Jacobians)."""

    rmse_a_k: float
    """Held-out RMSE of ``a`` (pooled over the folds)."""
    rmse_b_k: float
    gain: float
    """Relative cut of the held-out RMSE, ``1 - rmse_b / rmse_a``."""
    margin: float
    folds_improved: int
    """How many folds ``b`` has the lower held-out RMSE on."""
    folds: int
    fold_gains: tuple[float, ...] = field(default=())

    @property
    def improves(self) -> bool:
        """``b`` cuts the held-out RMSE by at least the margin, and on most folds (not on
        the strength of one block)."""
        return self.gain >= self.margin and 2 * self.folds_improved > self.folds

    def describe(self) -> str:
        return (
            f"held-out RMSE {self.rmse_a_k:.4f} -> {self.rmse_b_k:.4f} K "
            f"({100 * self.gain:+.1f} %, margin {100 * self.margin:.0f} %), better on "
            f"{self.folds_improved} of {self.folds} folds"
        )


def improves_held_out(
    residual_a: np.ndarray,
    jacobian_a: np.ndarray | None,
    residual_b: np.ndarray,
    jacobian_b: np.ndarray | None,
    folds: Sequence[np.ndarray],
    margin: float = HELD_OUT_MARGIN,
) -> Comparison:
    """Does candidate ``b`` improve the held-out blocks over ``a`` by at least ``margin``
    (relative cut of the held-out RMSE)? Both residuals are over the same seconds in the same
    order (the close loop aligns them by event and second); the Jacobians are those of their
    fits (None for the current revision, which has nothing fitted)."""
    ra = np.asarray(residual_a, dtype=np.float64).ravel()
    rb = np.asarray(residual_b, dtype=np.float64).ravel()
    if ra.shape != rb.shape:
        raise SelectionError(
            f"the residuals compared cover {ra.size} and {rb.size} seconds: align them first"
        )
    ha = held_out_residual(ra, jacobian_a, folds)
    hb = held_out_residual(rb, jacobian_b, folds)
    held = np.zeros(ra.size, dtype=bool)
    gains, improved = [], 0
    for mask in folds:
        m = np.asarray(mask, dtype=bool)
        held |= m
        fa, fb = _rmse(ha[m]), _rmse(hb[m])
        gains.append(1.0 - fb / fa if fa > 0 else 0.0)
        improved += int(fb < fa)
    a, b = _rmse(ha[held]), _rmse(hb[held])
    return Comparison(
        rmse_a_k=a,
        rmse_b_k=b,
        gain=1.0 - b / a if a > 0 else 0.0,
        margin=margin,
        folds_improved=improved,
        folds=len(folds),
        fold_gains=tuple(gains),
    )


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
    """Confidence intervals of fitted parameters that see what varies from block to block
    (issue 13: a reduced model's error against the world, and parameter trade-offs, shift the
    best parameters from one wagon-day to the next; a residual-based interval misses that).

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

    r, b = _as_arrays(residual, blocks)
    xs = np.asarray(x, dtype=np.float64).ravel()
    p = xs.size
    j = np.asarray(jacobian, dtype=np.float64).reshape(r.size, p)
    if n_eff is None:
        n_eff = effective_sample_size(r, b)
    plain = parameter_intervals(j, r, xs, names, n_eff, level)
    order, starts, lengths = _block_slices(b)
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


# ---------------------------------------------------------------------------- noise
def noise_from_residual(
    residual: np.ndarray, blocks: np.ndarray, time_s: np.ndarray | None = None
) -> float:
    """White sensor noise (K, one sigma) from the residual's second differences within blocks:
    ``r[t+1] - 2 r[t] + r[t-1]`` of white noise has variance ``6 sigma^2``, a smooth model
    error contributes only its curvature (far less than to first differences, which carry its
    slope), and the scale is the median absolute deviation (x 1.4826), so that the few seconds
    where the model error turns sharply (a braking's onset) do not count. ``time_s`` (optional,
    seconds): differences only over three equally spaced seconds (a gap is not a step)."""
    r, b = _as_arrays(residual, blocks)
    order = np.argsort(b, kind="stable")
    rs, bs = r[order], b[order]
    same = (bs[2:] == bs[1:-1]) & (bs[1:-1] == bs[:-2])
    if time_s is not None:
        ts = np.asarray(time_s, dtype=np.float64).ravel()[order]
        h1, h2 = ts[1:-1] - ts[:-2], ts[2:] - ts[1:-1]
        step = np.nanmin(np.where(same, h1, np.inf)) if same.any() else np.inf
        same &= np.isclose(h1, step) & np.isclose(h2, step)
    d2 = (rs[2:] - 2.0 * rs[1:-1] + rs[:-2])[same] if rs.size >= 3 else np.zeros(0)
    d2 = d2[np.isfinite(d2)]
    if d2.size < 10:
        raise SelectionError(
            f"noise_from_residual: {d2.size} second differences within blocks; need 10"
        )
    return noise_from_second_differences(d2)


# ---------------------------------------------------------------------------- adequacy
def ljung_box_white_fraction(
    residual: np.ndarray, blocks: np.ndarray, lags: int = 10, alpha: float = 0.05
) -> float:
    """Share of blocks whose residual passes the Ljung-Box test of whiteness (``lags`` lags,
    level ``alpha``; blocks shorter than ``5 lags`` are skipped). White noise gives about
    ``1 - alpha``; a smooth leftover gives near 0. NaN when no block is long enough."""
    from scipy.stats import chi2

    r, b = _as_arrays(residual, blocks)
    order, starts, lengths = _block_slices(b)
    rs = r[order]
    passed = tested = 0
    threshold = float(chi2.ppf(1.0 - alpha, lags))
    for start, length in zip(starts, lengths, strict=True):
        if length < 5 * lags:
            continue
        x = rs[start : start + length]
        x = x - x.mean()
        c0 = float(np.dot(x, x))
        if c0 <= 0.0:
            continue
        rho = np.array([np.dot(x[:-k], x[k:]) / c0 for k in range(1, lags + 1)])
        q = length * (length + 2) * float(np.sum(rho * rho / (length - np.arange(1, lags + 1))))
        tested += 1
        passed += int(q <= threshold)
    return passed / tested if tested else float("nan")


@dataclass(frozen=True)
class Adequacy:
    """Is the chosen model's fit residual consistent with the sensor noise?"""

    adequate: bool
    noise_k: float
    rmse_k: float
    ratio: float
    """``rmse_k / noise_k``; adequate when at most the ``max_ratio`` asked for."""
    whiteness: float
    """Share of blocks whose residual passes a Ljung-Box test of whiteness (10 lags, 5 %):
    about 0.95 for white noise. Reported, not a condition: with thousands of seconds per block
    the test rejects model errors far below the noise."""
    explained_fraction: float | None
    """``1 - rmse_after^2 / rmse_before^2`` when the RMSE before is given."""
    correlations: dict[str, float]
    """Pearson correlation of the residual with each driver (a phase, such as the hour of
    day: the circular-linear one, 0..1)."""
    unexplained: str | None
    """When not adequate: what was explained and what the rest correlates with."""


def _correlation(r: np.ndarray, x: np.ndarray) -> float | None:
    x = np.asarray(x, dtype=np.float64).ravel()
    if x.shape != r.shape:
        raise SelectionError(f"a driver has {x.size} values, the residual {r.size}")
    ok = np.isfinite(x) & np.isfinite(r)
    if ok.sum() < 10:
        return None
    xa, ra = x[ok], r[ok]
    if np.std(xa) == 0.0 or np.std(ra) == 0.0:
        return None
    return float(np.corrcoef(xa, ra)[0, 1])


def circular_linear_correlation(r: np.ndarray, x: np.ndarray, period: float) -> float | None:
    """Mardia's circular-linear correlation (0..1) of ``r`` with the phase of ``x`` on
    ``period`` (hour of day on 24 h): the multiple correlation of ``r`` on ``cos`` and ``sin``
    of the phase, so a bump at any time of day counts, not only a trend from midnight to
    midnight (Mardia & Jupp, *Directional Statistics*, 2000, sec. 11.2)."""
    x = np.asarray(x, dtype=np.float64).ravel()
    r = np.asarray(r, dtype=np.float64).ravel()
    phase = 2.0 * np.pi * x / period
    rc = _correlation(r, np.cos(phase))
    rs = _correlation(r, np.sin(phase))
    cs = _correlation(np.cos(phase), np.sin(phase))
    if rc is None or rs is None or cs is None or abs(cs) >= 1.0:
        return None
    squared = (rc * rc + rs * rs - 2.0 * rc * rs * cs) / (1.0 - cs * cs)
    return float(math.sqrt(min(max(squared, 0.0), 1.0)))


def systematic_share(before_rmse_k: float, after_rmse_k: float, noise_k: float) -> float:
    """The share of the systematic residual (its mean square above the sensor noise's)
    that an addition explains: ``1 - (after^2 - noise^2) / (before^2 - noise^2)``, each
    floored at 0; 1.0 when nothing systematic was left before. Unlike the plain explained
    fraction it does not count the noise, which no model explains, in what is left."""
    before = max(before_rmse_k**2 - noise_k**2, 0.0)
    after = max(after_rmse_k**2 - noise_k**2, 0.0)
    if before == 0.0:
        return 1.0
    return float(1.0 - after / before)


def describe_drivers(correlations: Mapping[str, float], top: int = 3) -> str:
    """``correlated with speed (r = +0.41) and ...``: the ``top`` strongest of the residual's
    correlations with the drivers (those with |r| >= ``MIN_CORRELATION``)."""
    return _named_drivers(correlations, top)


def _named_drivers(correlations: Mapping[str, float], top: int = 3) -> str:
    strong = sorted(
        ((k, v) for k, v in correlations.items() if abs(v) >= MIN_CORRELATION),
        key=lambda kv: -abs(kv[1]),
    )[:top]
    if not strong:
        return f"correlated with none of the drivers (|r| < {MIN_CORRELATION})"
    parts = [f"{name} (r = {value:+.2f})" for name, value in strong]
    joined = parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]
    return f"correlated with {joined}"


def adequacy(
    residual: np.ndarray,
    blocks: np.ndarray,
    noise_k: float,
    drivers: Mapping[str, np.ndarray],
    *,
    before_rmse_k: float | None = None,
    effect: str | None = None,
    max_ratio: float = MAX_NOISE_RATIO,
    periods: Mapping[str, float] | None = None,
) -> Adequacy:
    """Judge a fit residual (the chosen model's, on the fit events) against the sensor noise
    ``noise_k`` (from :func:`noise_from_residual`): adequate when its RMSE is at most
    ``max_ratio`` times the noise. ``drivers``: what the model is driven by, one value per
    second (speed, pressure, ambient, hour of day...), to name what a leftover correlates
    with. ``before_rmse_k``: the RMSE before anything was added, for the explained share;
    ``effect``: what was added (None: nothing). ``periods``: drivers that are phases (hour of
    day: 24.0), correlated by :func:`circular_linear_correlation` (0..1)."""
    r, b = _as_arrays(residual, blocks)
    finite = np.isfinite(r)
    if finite.sum() == 0:
        raise SelectionError("adequacy: no finite residual")
    rmse = _rmse(r[finite])
    ratio = rmse / noise_k if noise_k > 0 else math.inf
    white = ljung_box_white_fraction(r[finite], b[finite])
    explained = None
    if before_rmse_k is not None and before_rmse_k > 0:
        explained = 1.0 - (rmse / before_rmse_k) ** 2
    correlations = {}
    for name, values in drivers.items():
        period = (periods or {}).get(name)
        if period is None:
            c = _correlation(r, values)
        else:
            c = circular_linear_correlation(r, values, period)
        if c is not None:
            correlations[name] = c
    ok = bool(ratio <= max_ratio)
    unexplained = None
    if not ok:
        rest = (
            f"{rmse:.2g} K remains against {noise_k:.2g} K of sensor noise, "
            f"{_named_drivers(correlations)}"
        )
        if effect is not None:
            share = (
                f" explains {100 * max(explained, 0.0):.0f} % of the residual"
                if explained is not None
                else " was added"
            )
            unexplained = f"partly explained: {effect}{share}; {rest}"
        else:
            unexplained = f"not explained: {rest}"
    return Adequacy(
        adequate=ok,
        noise_k=float(noise_k),
        rmse_k=rmse,
        ratio=ratio,
        whiteness=white,
        explained_fraction=explained,
        correlations=correlations,
        unexplained=unexplained,
    )


# ---------------------------------------------------------------------------- outliers
def event_rms(residual: np.ndarray, event: np.ndarray, n_events: int) -> np.ndarray:
    """(n_events) RMS of the finite ``residual`` of each event (``event``: each second's
    index into the events); NaN for an event with no finite second."""
    r = np.asarray(residual, dtype=np.float64).ravel()
    e = np.asarray(event).ravel()
    if r.size != e.size:
        raise SelectionError(f"event_rms: {r.size} residuals but {e.size} event indices")
    ok = np.isfinite(r)
    sums = np.bincount(e[ok], weights=r[ok] * r[ok], minlength=n_events)
    counts = np.bincount(e[ok], minlength=n_events).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.where(counts > 0, sums / np.maximum(counts, 1.0), np.nan))


def outlier_events(
    rms_k: np.ndarray,
    noise_k: float,
    *,
    noise_factor: float = OUTLIER_NOISE_FACTOR,
    z: float = OUTLIER_Z,
    max_fraction: float = MAX_OUTLIER_FRACTION,
) -> tuple[np.ndarray, float]:
    """Which events' residual RMS (``rms_k``, one per event, from :func:`event_rms`) is far
    above the bulk: above ``noise_factor`` x the sensor noise and above the median by ``z``
    robust standard deviations (1.4826 x the median absolute deviation). Data the flags did
    not catch (a reading gone wild, an unlogged braking) then leaves the fit instead of
    biasing it; a model that misfits every event leaves none out (the bulk moves with it).
    At most ``max_fraction`` of the events, the worst. Returns the outliers' indices, worst
    first, and the threshold (K)."""
    rms = np.asarray(rms_k, dtype=np.float64).ravel()
    finite = np.isfinite(rms)
    if finite.sum() < 3:
        return np.zeros(0, dtype=np.int64), math.inf
    median = float(np.median(rms[finite]))
    spread = 1.4826 * float(np.median(np.abs(rms[finite] - median)))
    threshold = max(noise_factor * noise_k if math.isfinite(noise_k) else 0.0, median + z * spread)
    above = np.flatnonzero(finite & (rms > threshold))
    worst = above[np.argsort(-rms[above], kind="stable")]
    return worst[: int(max_fraction * int(finite.sum()))].astype(np.int64), threshold
