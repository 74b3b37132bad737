"""Whether a model's residual is consistent with the sensor noise: the RMSE ratio, its
whiteness, what it still correlates with, and the sentence a report gives when it is not."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from fleetbrake.closeloop.stats.blocks import (
    SelectionError,
    as_arrays,
    block_slices,
    root_mean_square,
)

MAX_NOISE_RATIO = 1.5
"""A model is adequate when its fit RMSE is at most this many times the sensor noise."""


MIN_CORRELATION = 0.1
"""Drivers whose correlation with a leftover residual is weaker than this are not named."""


MIN_EXPLAINED_SHARE = 0.5
"""A physical addition that leaves the fit inadequate is named only when it explains at least
this share of the baseline's systematic residual (:func:`systematic_share`): the dominant
cause of the misfit, not a proxy absorbing part of something outside the vocabulary."""


# ---------------------------------------------------------------------------- adequacy
def ljung_box_white_fraction(
    residual: np.ndarray, blocks: np.ndarray, lags: int = 10, alpha: float = 0.05
) -> float:
    """Share of blocks whose residual passes the Ljung-Box test of whiteness (``lags`` lags,
    level ``alpha``; blocks shorter than ``5 lags`` are skipped). White noise gives about
    ``1 - alpha``; a smooth leftover gives near 0. NaN when no block is long enough."""
    from scipy.stats import chi2

    r, b = as_arrays(residual, blocks)
    order, starts, lengths = block_slices(b)
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
    r, b = as_arrays(residual, blocks)
    finite = np.isfinite(r)
    if finite.sum() == 0:
        raise SelectionError("adequacy: no finite residual")
    rmse = root_mean_square(r[finite])
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
