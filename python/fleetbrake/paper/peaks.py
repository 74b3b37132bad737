"""The maximum of a sampled curve, refined between its samples (the sensor's time to peak)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["Peak", "find_peak", "peak_times"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Peak:
    """The maximum of a sampled curve, refined by a parabola through the 3 samples around it."""

    time_s: float
    value_c: float
    index: int
    """The sample holding the largest value."""
    interior: bool
    """False when the largest sample is the first or the last (no maximum inside the horizon)."""


def peak_times(
    time_s: FloatArray, values: FloatArray
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Refined maxima of each column of ``values`` (n, P) sampled at equally spaced ``time_s``.

    Returns (times, values, interior) of shape (P,). Where the largest sample is the first or
    the last, that sample is returned as it is and ``interior`` is False.
    """
    y = np.asarray(values, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    n = y.shape[0]
    if n < 3:
        raise ValueError("peak_times needs at least 3 samples")
    dt = float(time_s[1] - time_s[0])
    i = np.argmax(y, axis=0)
    cols = np.arange(y.shape[1])
    interior = (i > 0) & (i < n - 1)
    j = np.clip(i, 1, n - 2)
    y0, y1, y2 = y[j - 1, cols], y[j, cols], y[j + 1, cols]
    curvature = y0 - 2.0 * y1 + y2
    with np.errstate(divide="ignore", invalid="ignore"):
        offset = np.where(curvature < 0, 0.5 * (y0 - y2) / curvature, 0.0)
    offset = np.where(interior, np.clip(offset, -0.5, 0.5), 0.0)
    t = np.asarray(time_s, dtype=np.float64)[i] + offset * dt
    v = np.where(interior, y1 - 0.25 * (y0 - y2) * offset, y[i, cols])
    return t, v, interior


def find_peak(time_s: FloatArray, values: FloatArray) -> Peak:
    """The refined maximum of one curve (see :func:`peak_times`)."""
    t, v, interior = peak_times(time_s, np.asarray(values, dtype=np.float64).reshape(-1, 1))
    index = int(np.argmax(values))
    return Peak(time_s=float(t[0]), value_c=float(v[0]), index=index, interior=bool(interior[0]))
