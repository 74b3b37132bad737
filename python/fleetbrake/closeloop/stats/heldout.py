"""Blocked cross-validation: whole blocks per fold, a fitted candidate's held-out residual
from its Jacobian (one Gauss-Newton step off the fold), and whether a richer candidate cuts
the held-out RMSE of a simpler one by the practical margin."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from fleetbrake.closeloop.stats.blocks import SelectionError, root_mean_square

HELD_OUT_MARGIN = 0.05
"""Default practical margin: the relative cut of the held-out RMSE a richer candidate must
bring over a simpler one (5 %). The close loop states its own in its configuration."""


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
        fa, fb = root_mean_square(ha[m]), root_mean_square(hb[m])
        gains.append(1.0 - fb / fa if fa > 0 else 0.0)
        improved += int(fb < fa)
    a, b = root_mean_square(ha[held]), root_mean_square(hb[held])
    return Comparison(
        rmse_a_k=a,
        rmse_b_k=b,
        gain=1.0 - b / a if a > 0 else 0.0,
        margin=margin,
        folds_improved=improved,
        folds=len(folds),
        fold_gains=tuple(gains),
    )
