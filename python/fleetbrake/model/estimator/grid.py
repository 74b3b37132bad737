"""A wagon's series on the estimator's time grid: the series checked
(:class:`~fleetbrake.model.estimator.problem.EstimatorInputError` naming the wagon, the column
and the first row concerned) and its logged seconds with the seconds of short unlogged gaps
filled in (:class:`Grid`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fleetbrake.model.estimator.config import EstimatorConfig
from fleetbrake.model.estimator.problem import EstimatorInputError, FloatArray, WagonSeries

__all__ = ["Grid", "series_grid"]


@dataclass(frozen=True)
class Grid:
    """The time grid of a series: its logged samples plus the seconds filled into short gaps
    (N samples), the inputs interpolated on it and the readings NaN in the fills."""

    time_s: FloatArray
    logged: NDArray[np.bool_]
    """Which samples are logged ones (not filled)."""
    gap: NDArray[np.bool_]
    """(N-1): which steps are unlogged standstills (gaps longer than
    ``max_interpolated_gap_s``, stepped whole)."""
    p_bar: FloatArray
    speed_kmh: FloatArray
    ambient_c: FloatArray
    reading_c: FloatArray

    @property
    def size(self) -> int:
        return int(self.time_s.size)


def series_grid(series: WagonSeries, config: EstimatorConfig) -> Grid:
    """The series checked and on its time grid."""
    _check_series(series)
    return _grid(series, config)


def _check_series(series: WagonSeries) -> None:
    """Raise :class:`EstimatorInputError` for a series the estimator cannot take."""
    who = f"wagon {series.wagon_id!r}" if series.wagon_id else "the series"
    n = series.time_s.size
    if n < 1:
        raise EstimatorInputError(f"{who}: no samples to estimate from")
    for name in ("p_bar", "speed_kmh", "ambient_c", "reading_c"):
        values = getattr(series, name)
        if values.shape != (n,):
            raise EstimatorInputError(
                f"{who}: {name} has {values.size} values, time_s has {n} (one per sample)"
            )
    for name in ("time_s", "p_bar", "speed_kmh", "ambient_c"):
        bad = np.flatnonzero(~np.isfinite(getattr(series, name)))
        if bad.size:
            raise EstimatorInputError(
                f"{who}: {name} is missing or not finite in {bad.size} row(s), the first at "
                f"row {int(bad[0])}; fill gaps in the inputs first"
            )
    negative = np.flatnonzero(series.speed_kmh < 0)
    if negative.size:
        raise EstimatorInputError(
            f"{who}: speed_kmh is negative in row {int(negative[0])} "
            f"({series.speed_kmh[negative[0]]!r})"
        )
    infinite = np.flatnonzero(np.isinf(series.reading_c))
    if infinite.size:
        raise EstimatorInputError(
            f"{who}: reading_c is infinite in row {int(infinite[0])} (NaN marks no reading)"
        )
    steps = np.diff(series.time_s)
    back = np.flatnonzero(steps <= 0)
    if back.size:
        raise EstimatorInputError(
            f"{who}: time_s does not increase at row {int(back[0]) + 1} "
            f"({series.time_s[back[0]]!r} then {series.time_s[back[0] + 1]!r})"
        )


def _grid(series: WagonSeries, config: EstimatorConfig) -> Grid:
    """The time grid: logged samples plus the seconds filled into short gaps."""
    dt = config.dt_s
    who = f"wagon {series.wagon_id!r}" if series.wagon_id else "the series"
    ticks = (series.time_s - series.time_s[0]) / dt
    whole = np.rint(ticks)
    off = np.flatnonzero(np.abs(ticks - whole) > 1e-6)
    if off.size:
        raise EstimatorInputError(
            f"{who}: time_s at row {int(off[0])} is not a whole number of {dt} s steps from "
            "the first sample"
        )
    tick = whole.astype(np.int64)
    jump = np.diff(tick)
    fill = (jump > 1) & (jump * dt <= config.max_interpolated_gap_s)
    # grid: each logged sample, then the filled seconds after it
    extra = np.where(fill, jump - 1, 0)
    n_grid = tick.size + int(extra.sum())
    pos = np.arange(tick.size) + np.concatenate(([0], np.cumsum(extra)))
    grid_tick = np.empty(n_grid, dtype=np.int64)
    logged = np.zeros(n_grid, dtype=bool)
    logged[pos] = True
    grid_tick[pos] = tick
    for i in np.flatnonzero(fill):
        grid_tick[pos[i] + 1 : pos[i + 1]] = tick[i] + np.arange(1, jump[i])
    reading = np.full(n_grid, np.nan)
    reading[pos] = series.reading_c
    return Grid(
        time_s=series.time_s[0] + grid_tick * dt,
        logged=logged,
        gap=np.diff(grid_tick) > 1,
        p_bar=np.interp(grid_tick, tick, series.p_bar),
        speed_kmh=np.interp(grid_tick, tick, series.speed_kmh),
        ambient_c=np.interp(grid_tick, tick, series.ambient_c),
        reading_c=reading,
    )
