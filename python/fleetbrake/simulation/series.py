"""One wagon's samples on a 1 Hz grid: what the chain simulation runs on and the flags judge.

::

    from fleetbrake.simulation.series import WagonSeries

    spans = WagonSeries.spans_from_frame("SGG-0001", samples, ambient_default_c=10.0,
                                         events=events, bridge_max_s=6 * 3600)
    series = spans[0]
    series.present, series.measured_c, series.events     # arrays on the grid, seconds since t0

Seconds without a sample row are on the grid too (``present`` false): their speed, pressure
and air interpolated between the rows around them, their reading NaN. A wagon's samples are
cut into *spans* where two rows are more than ``bridge_max_s`` apart
(:class:`fleetbrake.simulation.chains.ChainParams`): the block is simulated through every shorter
gap, and starts afresh after a longer one.
"""

from __future__ import annotations

import datetime as dt
import itertools
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.ndimage import median_filter

__all__ = [
    "BoolArray",
    "FloatArray",
    "WagonSeries",
    "interpolate_missing",
    "merge_spans",
    "nan_running_mean",
    "running_median",
    "runs",
    "seconds_since",
    "strictly_increasing",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

_US_PER_S = 1_000_000


def seconds_since(times: pl.Series, t0: dt.datetime) -> IntArray:
    """Whole seconds from ``t0`` to each of ``times``, truncated toward zero as polars'
    ``(times - t0).dt.total_seconds()`` has them, in numpy (that expression is three polars
    queries, and the flags make it for every span)."""
    if times.dtype != pl.Datetime("us", None) or times.has_nulls():
        return (times - t0).dt.total_seconds().to_numpy().astype(np.int64)
    us = (times.to_numpy() - np.datetime64(t0, "us")).astype(np.int64)
    return np.sign(us) * (np.abs(us) // _US_PER_S)


def strictly_increasing(times: pl.Series) -> bool:
    """``times`` (no nulls) strictly increase: sorting them, or keeping the first row of each
    time, would leave them as they are."""
    if times.has_nulls():
        return False
    values = times.to_numpy()
    return bool(values.size < 2 or (values[1:] > values[:-1]).all())


@dataclass
class WagonSeries:
    """A wagon's samples on a 1 Hz grid from its first to its last sample (``time_s`` are
    seconds since ``t0``); seconds without a row are ``present = False``, their speed,
    pressure and air interpolated, their reading NaN."""

    wagon_id: str
    t0: dt.datetime
    present: BoolArray
    speed_kmh: FloatArray
    pressure_bar: FloatArray
    ambient_c: FloatArray
    measured_c: FloatArray
    """Valid readings; NaN where missing or out of range."""
    fault: BoolArray
    """The reading was out of range (``block_temp_fault``)."""
    raw_c: FloatArray
    """The out-of-range value where ``fault``."""
    speed_raw_kmh: FloatArray
    """The speed as logged (NaN where missing)."""
    events: list[tuple[str, int, int, bool]] = field(default_factory=list)
    """(event_id, activation, release, complete), seconds since t0, by activation."""

    @property
    def n(self) -> int:
        return int(self.present.size)

    def utc(self, k: float) -> dt.datetime:
        return self.t0 + dt.timedelta(seconds=float(k))

    def index(self, t: dt.datetime) -> int:
        """Seconds from ``t0`` to ``t`` (whole seconds: the grid's)."""
        return int((t - self.t0).total_seconds())

    @classmethod
    def spans_from_frame(
        cls,
        wagon_id: str,
        samples: pl.DataFrame,
        *,
        ambient_default_c: float,
        bridge_max_s: float,
        events: pl.DataFrame | None = None,
    ) -> list[WagonSeries]:
        """One series per stretch of the samples without a gap longer than ``bridge_max_s``
        (each event in the stretch holding its activation)."""
        if samples.height == 0:
            return []
        frame = (
            samples  # as the warehouse's queries hand them: sorting would leave them as they are
            if strictly_increasing(samples["time_utc"])
            else samples.sort("time_utc", maintain_order=True).unique(
                "time_utc", keep="first", maintain_order=True
            )
        )
        gap = frame["time_utc"].diff().dt.total_seconds().fill_null(0).to_numpy()
        cuts = [0, *(np.flatnonzero(gap[1:] > bridge_max_s) + 1).tolist(), frame.height]
        parts = [frame.slice(a, b - a) for a, b in itertools.pairwise(cuts)]  # no copies
        out = []
        for part in parts:
            t0, t1 = part["time_utc"][0], part["time_utc"][-1]
            own = None
            if events is not None:
                own = events.filter((pl.col("start_utc") >= t0) & (pl.col("start_utc") <= t1))
            out.append(
                cls.from_frame(
                    wagon_id, part, ambient_default_c=ambient_default_c, events=own, ordered=True
                )
            )
        return out

    @classmethod
    def from_frame(
        cls,
        wagon_id: str,
        samples: pl.DataFrame,
        *,
        ambient_default_c: float,
        events: pl.DataFrame | None = None,
        ordered: bool = False,
    ) -> WagonSeries:
        """From ``samples`` rows (``time_utc``, ``speed_kmh``, ``brake_pressure_bar``,
        ``block_temp_c``, optional ``block_temp_fault``, ``block_temp_raw_c``,
        ``ambient_temp_c``) and optional ``events`` (``event_id``, ``start_utc``,
        ``end_utc``, optional ``complete``). ``ordered``: the rows are already sorted by
        time, one row per time (as :meth:`spans_from_frame` cuts them), so not sorted again."""
        if samples.height == 0:
            raise ValueError(f"wagon {wagon_id}: no samples")
        frame = (
            samples
            if ordered or strictly_increasing(samples["time_utc"])
            else samples.sort("time_utc", maintain_order=True).unique(
                "time_utc", keep="first", maintain_order=True
            )
        )
        t0 = frame["time_utc"][0]
        k = seconds_since(frame["time_utc"], t0)
        n = int(k[-1]) + 1
        floats = frame.select(  # one polars query for every column
            pl.col(name).cast(pl.Float64) for name in _FLOAT_COLUMNS if name in frame.columns
        )

        def column(name: str) -> FloatArray:
            out = np.full(n, np.nan)
            if name in floats.columns:
                out[k] = floats[name].to_numpy()
            return out

        present = np.zeros(n, dtype=bool)
        present[k] = True
        fault = np.zeros(n, dtype=bool)
        if "block_temp_fault" in frame.columns:
            fault[k] = frame["block_temp_fault"].fill_null(False).to_numpy()
        speed_raw = column("speed_kmh")
        series = cls(
            wagon_id=wagon_id,
            t0=t0,
            present=present,
            speed_kmh=np.maximum(interpolate_missing(speed_raw, 0.0), 0.0),
            pressure_bar=np.maximum(interpolate_missing(column("brake_pressure_bar"), 0.0), 0.0),
            ambient_c=interpolate_missing(column("ambient_temp_c"), ambient_default_c),
            measured_c=np.where(fault, np.nan, column("block_temp_c")),
            fault=fault,
            raw_c=column("block_temp_raw_c"),
            speed_raw_kmh=speed_raw,
        )
        if events is not None and events.height:
            complete = (
                events["complete"].to_list()
                if "complete" in events.columns
                else [True] * events.height
            )
            for event_id, start, end, whole in zip(
                events["event_id"], events["start_utc"], events["end_utc"], complete, strict=True
            ):
                a = int((start - t0).total_seconds())
                b = int((end - t0).total_seconds())
                if b >= 0 and a < n:
                    series.events.append((event_id, a, b, bool(whole)))
            series.events.sort(key=lambda e: e[1])
        return series


_FLOAT_COLUMNS = (
    "speed_kmh",
    "brake_pressure_bar",
    "ambient_temp_c",
    "block_temp_c",
    "block_temp_raw_c",
)
"""The sample columns :meth:`WagonSeries.from_frame` puts on the grid as floats."""


def interpolate_missing(values: FloatArray, default: float) -> FloatArray:
    """NaN filled linearly between valid values (held at the ends); ``default`` if none."""
    ok = np.isfinite(values)
    if not ok.any():
        return np.full(values.size, float(default))
    k = np.arange(values.size)
    return np.interp(k, k[ok], values[ok])


def runs(mask: BoolArray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True."""
    if mask.size == 0:
        return []
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def merge_spans(spans: Iterable[tuple[int, int]], gap: int) -> list[tuple[int, int]]:
    """[start, stop) spans, those at most ``gap`` apart joined."""
    out: list[list[int]] = []
    for a, b in sorted(spans):
        if out and a - out[-1][1] <= gap:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def running_median(values: FloatArray, width: int) -> FloatArray:
    """Centred running median over ``width`` samples (the ends padded with the end values)."""
    if width <= 1 or values.size < width:
        return values.copy()
    if width % 2 and np.isfinite(values).all():
        # an odd window's median is its middle value: the rank filter picks the same one
        # (``nearest``: the ends padded with the end values), without sorting every window
        return np.asarray(median_filter(values, size=width, mode="nearest"), dtype=np.float64)
    half = width // 2
    padded = np.pad(values, half, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, width)
    return np.asarray(np.median(windows, axis=1), dtype=np.float64)[: values.size]


def nan_running_mean(values: FloatArray, width: int) -> FloatArray:
    """Centred running mean over ``width`` samples, ignoring NaN (NaN where none valid)."""
    ok = np.isfinite(values)
    if width <= 1:
        return np.where(ok, values, np.nan)
    kernel = np.ones(width)
    total = np.convolve(np.where(ok, values, 0.0), kernel, mode="same")
    count = np.convolve(ok.astype(np.float64), kernel, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)
