"""Whether a fitted parameter changes over the calendar: the fit refitted per wagon-day and
per day, and the wagon-days' values regressed on time.

Each block's (a wagon-day's) parameters are one Gauss-Newton step from the fit on every
block, on that block's rows of the fit's residual and Jacobian (nothing re-simulated; exact
for a model linear in its parameters, the same step as the blocked cross-validation's). A
parameter's drift is the slope of its wagon-day values on the blocks' mid-times, weighted by
the information each block holds on it (the diagonal of ``J_g^T J_g``), its standard error
from the values' own scatter about the line (what varies from one wagon-day to the next: the
reduced model's error against the world, the duty, the trade-offs between parameters), with a
Student t on ``blocks - 2`` degrees of freedom: the wagon-days are the independent units, not
the seconds. The parameter *changes over the period* when the slope's 95 % interval excludes
zero. The report also gives each UTC day's values (one step on the day's rows) with the day's
95 % interval by :func:`~fleetbrake.closeloop.stats.blocked_intervals`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fleetbrake.closeloop.stats.intervals import blocked_intervals

__all__ = ["DriftReport", "ParameterDrift", "PeriodFit", "parameter_drift"]

SECONDS_PER_DAY = 86_400.0

MIN_PERIOD_SECONDS = 600
"""Fewer fit seconds than this in a day: the day is not a period of its own (too little to
fit on)."""


@dataclass(frozen=True)
class PeriodFit:
    """One period's parameters: its first day, its seconds, values and 95 % intervals."""

    start: str
    seconds: int
    values: dict[str, float]
    intervals: dict[str, tuple[float, float]]


@dataclass(frozen=True)
class ParameterDrift:
    """A parameter's change over the calendar: slope per day, its 95 % interval, and whether
    that excludes zero."""

    rate_per_day: float
    rate_interval: tuple[float, float]
    changes: bool


@dataclass(frozen=True)
class DriftReport:
    """The periods and each parameter's drift (keyed as the report's ``parameters``)."""

    period: str
    periods: list[PeriodFit]
    parameters: dict[str, ParameterDrift]


def parameter_drift(
    jacobian: np.ndarray,
    residual: np.ndarray,
    x: np.ndarray,
    names: Sequence[str],
    blocks: np.ndarray,
    time_utc: np.ndarray,
) -> DriftReport | None:
    """The drift of the parameters ``x`` (``names``) fitted on rows with ``residual``,
    ``jacobian``, wagon-day ``blocks`` and ``time_utc`` (datetime64); None with fewer than
    two days or fewer than four wagon-days."""
    day = time_utc.astype("datetime64[D]")
    days, counts = np.unique(day, return_counts=True)
    days = days[counts >= MIN_PERIOD_SECONDS]
    if days.size < 2 or x.size == 0:
        return None
    periods = [_period(jacobian, residual, x, names, blocks, day == d, str(d)) for d in days]
    values, weights, mids = [], [], []
    for g in np.unique(blocks):
        rows = blocks == g
        if int(np.sum(rows)) < MIN_PERIOD_SECONDS:
            continue
        j = jacobian[rows]
        step, *_ = np.linalg.lstsq(j, -residual[rows], rcond=None)
        values.append(x + step)
        weights.append(np.einsum("ij,ij->j", j, j))
        mids.append(_days(time_utc[rows]))
    if len(values) < 4:
        return None
    value_arr, weight_arr, t = np.array(values), np.array(weights), np.array(mids)
    drifts = {name: _slope(t, value_arr[:, i], weight_arr[:, i]) for i, name in enumerate(names)}
    return DriftReport(period="day", periods=periods, parameters=drifts)


def _days(time_utc: np.ndarray) -> float:
    """The mean time of ``time_utc`` in days since the epoch."""
    return float(np.mean(time_utc.astype("datetime64[us]").astype(np.float64))) / (
        SECONDS_PER_DAY * 1e6
    )


def _period(
    jacobian: np.ndarray,
    residual: np.ndarray,
    x: np.ndarray,
    names: Sequence[str],
    blocks: np.ndarray,
    rows: np.ndarray,
    start: str,
) -> PeriodFit:
    """One day's parameters (a Gauss-Newton step on its rows) and their 95 % intervals."""
    j, r = jacobian[rows], residual[rows]
    step, *_ = np.linalg.lstsq(j, -r, rcond=None)
    x_d = x + step
    got = blocked_intervals(j, r + j @ step, x_d, names, blocks[rows])
    return PeriodFit(
        start=start,
        seconds=int(np.sum(rows)),
        values={n: float(v) for n, v in zip(names, x_d, strict=True)},
        intervals={n: got.intervals[n] for n in names},
    )


def _slope(t: np.ndarray, y: np.ndarray, w: np.ndarray) -> ParameterDrift:
    """The weighted least-squares slope of ``y`` on ``t``, its 95 % interval from the
    scatter about the line (Student t on ``n - 2``), and whether that excludes zero."""
    from scipy.stats import t as student_t

    unknown = ParameterDrift(math.nan, (-math.inf, math.inf), False)
    ok = np.isfinite(y) & np.isfinite(w) & (w > 0)
    t, y, w = t[ok], y[ok], w[ok]
    n = t.size
    if n < 4:
        return unknown
    w = w / np.sum(w)
    t_bar = float(np.sum(w * t))
    sxx = float(np.sum(w * (t - t_bar) ** 2))
    if sxx <= 0:
        return unknown
    y_bar = float(np.sum(w * y))
    rate = float(np.sum(w * (t - t_bar) * (y - y_bar)) / sxx)
    scatter = float(np.sum(w * (y - y_bar - rate * (t - t_bar)) ** 2)) * n / (n - 2)
    rate_se = math.sqrt(scatter / (n * sxx))
    q = float(student_t.ppf(0.975, n - 2))
    low, high = rate - q * rate_se, rate + q * rate_se
    return ParameterDrift(rate, (low, high), bool(low > 0 or high < 0))
