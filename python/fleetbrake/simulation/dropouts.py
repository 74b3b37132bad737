"""The speed across a GPS dropout, from what the log knows: the speeds at both ends and the
distance covered.

While a unit has no fix its speed cells are empty and its distance is held; when the fix
returns the distance jumps by what the wagon covered meanwhile (``fleet-data.md``). The
friction heat of a braking is the block force times the distance slid, so a profile that
ignores the distance (a straight line between the two speeds) puts the wrong work into the
block: a train that stopped 40 s into a 150 s dropout, interpolated linearly from 60 km/h to 0,
covers 1,250 m instead of 333 m.

:func:`speed_across_dropouts` fills each run of empty speeds between two valid ones with the
smoothest profile (least ``∫ (dv/dt)² dt``) that meets both speeds and covers the logged
distance ``D`` over the run's ``T`` seconds:

* ``v(s) = v0 + (v1 - v0) s + 6 c s (1 - s)``, ``s = t / T``, ``c = (D - T (v0 + v1) / 2) / T``
  (the Euler-Lagrange solution under the distance constraint: a parabola), when it stays
  at or above zero;
* otherwise the wagon stood still inside the dropout: a constant deceleration from ``v0`` to
  rest over ``t_a``, a standstill, a constant acceleration to ``v1`` over ``t_b``, with
  ``v0 t_a + v1 t_b = 2 D`` and ``t_a / t_b = sqrt(v0 / v1)`` (the least ``∫ (dv/dt)²``
  among such profiles).

Where the distance cannot say (missing at an end, decreasing: a new session, or covering
more than the fastest of the two speeds could), the run is filled linearly, as before the
fix returned.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

__all__ = ["dropout_runs", "speed_across_dropouts", "speed_profile"]

FloatArray = NDArray[np.float64]

KMH_PER_M_S = 3.6

MAX_SPEED_FACTOR = 3.0
"""A dropout's mean speed above this many times the larger of its two end speeds (and above
``MAX_MEAN_SPEED_KMH``) is not a wagon's: the distance is taken as wrong and the run is
filled linearly."""

MAX_MEAN_SPEED_KMH = 160.0
"""km/h: above a freight wagon's fastest (120 km/h) with a margin."""


def dropout_runs(speed_kmh: FloatArray) -> list[tuple[int, int]]:
    """The runs of missing speeds with a valid speed on both sides, as ``(i0, i1)``: the
    last valid index before the run and the first valid one after."""
    valid = np.isfinite(speed_kmh)
    idx = np.flatnonzero(valid)
    if idx.size < 2:
        return []
    gaps = np.flatnonzero(np.diff(idx) > 1)
    return [(int(idx[g]), int(idx[g + 1])) for g in gaps]


def speed_profile(v0_kmh: float, v1_kmh: float, distance_m: float, duration_s: float) -> FloatArray:
    """The speeds (km/h) at the whole seconds ``1 .. duration_s - 1`` between two valid
    readings ``duration_s`` seconds apart, covering ``distance_m`` (module docstring)."""
    n = round(duration_s)
    t_s = np.arange(1, n, dtype=np.float64)
    v0, v1 = v0_kmh / KMH_PER_M_S, v1_kmh / KMH_PER_M_S
    s = t_s / n
    linear = v0 + (v1 - v0) * s
    c = (distance_m - n * (v0 + v1) / 2.0) / n
    smooth = linear + 6.0 * c * s * (1.0 - s)
    if _parabola_min(v0, v1, c) >= 0:
        return np.maximum(smooth, 0.0) * KMH_PER_M_S
    return _stop_inside(v0, v1, distance_m, float(n), t_s) * KMH_PER_M_S


def _parabola_min(v0: float, v1: float, c: float) -> float:
    """The smallest speed of the parabola over the whole run (not only at whole seconds)."""
    # v(s) = v0 + (v1 - v0 + 6c) s - 6c s²: a minimum inside (0, 1) only for c < 0
    a, b = -6.0 * c, v1 - v0 + 6.0 * c
    if a <= 0:
        return min(v0, v1)
    s_star = min(max(-b / (2.0 * a), 0.0), 1.0)
    return v0 + b * s_star + a * s_star**2


def _stop_inside(
    v0: float, v1: float, distance_m: float, duration_s: float, t_s: FloatArray
) -> FloatArray:
    """Decelerate, stand, accelerate (m/s at ``t_s``): a stop inside the dropout."""
    if v0 <= 0:
        t_a, t_b = 0.0, 2.0 * distance_m / v1
    else:
        ratio = math.sqrt(v1 / v0)
        t_a = 2.0 * distance_m / (v0 + v1 * ratio)
        t_b = ratio * t_a
    t_a = min(t_a, duration_s)
    t_b = min(t_b, duration_s - t_a)
    out = np.zeros_like(t_s)
    if t_a > 0:
        out = np.where(t_s < t_a, v0 * (1.0 - t_s / t_a), out)
    if t_b > 0:
        start = duration_s - t_b
        out = np.where(t_s > start, v1 * (t_s - start) / t_b, out)
    return out


def speed_across_dropouts(
    time_s: FloatArray, speed_kmh: FloatArray, distance_m: FloatArray
) -> FloatArray:
    """``speed_kmh`` with each run of missing speeds between two valid ones filled by
    :func:`speed_profile` from the distance logged at its ends, on a grid of whole seconds
    (``time_s``, increasing). Runs the distance cannot fill stay missing (the caller
    interpolates them); leading and trailing missing speeds stay missing."""
    out = np.array(speed_kmh, dtype=np.float64, copy=True)
    dist = np.asarray(distance_m, dtype=np.float64)
    for i0, i1 in dropout_runs(out):
        duration_s = float(time_s[i1] - time_s[i0])
        covered_m = float(dist[i1] - dist[i0])
        v0, v1 = float(out[i0]), float(out[i1])
        if not _distance_usable(covered_m, duration_s, v0, v1):
            continue
        inside = (time_s[i0 + 1 : i1] - time_s[i0]).astype(np.int64)
        profile = speed_profile(v0, v1, covered_m, duration_s)
        out[i0 + 1 : i1] = profile[inside - 1]
    return out


def _distance_usable(covered_m: float, duration_s: float, v0_kmh: float, v1_kmh: float) -> bool:
    if not (math.isfinite(covered_m) and covered_m >= 0 and duration_s >= 2):
        return False
    mean_kmh = covered_m / duration_s * KMH_PER_M_S
    return mean_kmh <= max(MAX_SPEED_FACTOR * max(v0_kmh, v1_kmh), MAX_MEAN_SPEED_KMH)
