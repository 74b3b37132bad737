"""Flags: the anomalies of a wagon's brake block that a maintainer should act on.

::

    from fleetbrake.flags.detect import FlagConfig, load_flag_config, raise_flags

    config = load_flag_config("flags.toml")            # or FlagConfig() for the defaults
    report = raise_flags(wh, registry, "declared", config)   # every wagon with samples
    report = raise_flags(wh, registry, "declared", wagons=["SGG-0002"])
    report.flags                                        # what was stored in ``flags``

Kinds (``shared/spec/interface.md``, ``v_flags``): ``sensor_fault``, ``weak_brake``,
``dragging_brake``, ``overheating``. ``docs/flags.md`` explains each, its thresholds and how to
change them; every threshold is a field of :class:`FlagConfig`.

How a wagon is judged (each step uses only readings the steps before found good):

1. **Sensor, from the readings alone.** Out of range (``samples.block_temp_fault``), frozen
   (the reading unchanged to within its resolution for minutes while it is noisy elsewhere
   or the model says the block must change), dropping out (readings missing for minutes while
   the logger recorded the rest of the row).
2. **Watch simulation.** The wagon's whole timeline is simulated with the model revision's
   effects, continuously through data gaps of up to ``bridge_max_s`` (speed and pressure
   interpolated across them: the unit sleeps while the wagon stands; a long gap in steps of
   ``GAP_STEP_S``), and cut into *segments*: each braking (activation to ``after_release_s``
   after release), the quiet stretches between brakings in windows of about ``window_s``,
   and the gaps. At the start of every segment the simulated field is re-anchored as
   ``pipeline.simulate_events`` does at an activation (shifted uniformly by the mean of
   measured - predicted over the ``anchor_s`` seconds before), so within a segment measured -
   predicted starts at zero and what it does then is what the model cannot explain; a sensor
   lag of the revision is carried across. Segments right after a data gap during which the
   wagon may have braked, or after a braking whose GPS speed was frozen, are not judged for
   ``settle_s``.
3. **Sensor, against the model.** Loose: in a quiet window the reading falls towards the air
   much faster than the block can cool, or in a braking it does not rise while it reads the
   air. Drifting: measured - predicted changes at a steady rate, of one sign, segment after
   segment, in a way no braking's aftermath and no heat flow explains.
4. **Brakes**, with the readings of steps 1 and 3 left out. Dragging: in a quiet window the
   block heats while the model, with no cylinder pressure, says it cools; or in a braking the
   block heats far more than predicted. Weak: in brakings (the ``predictions`` of the
   revision) the measured rise from activation to the peak is far below the predicted one;
   consecutive weak brakings are one flag. Overheating: the predicted contact maximum of a
   braking over ``contact_limit_c``.

Flags are recomputed per wagon and the wagon's rows of ``flags`` replaced in one transaction;
``flag_id`` is ``<kind>-<wagon>-<start as YYYYMMDDTHHMMSS>`` (``-2``, ... if taken), so the
same data gives the same ids, and a flag found again keeps its ``detected_utc``.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import difflib
import itertools
import math
import tomllib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
from numpy.typing import NDArray

from fleetbrake.errors import ConfigError
from fleetbrake.fleet.registry import Registry, WagonConfig
from fleetbrake.ingest.files import BLOCK_TEMP_VALID_C
from fleetbrake.model.effects import EffectSet
from fleetbrake.warehouse.connection import Warehouse

__all__ = [
    "CONFIG_KEYS",
    "FLAG_KINDS",
    "GAP_STEP_S",
    "SEVERITIES",
    "EventStat",
    "Finding",
    "Flag",
    "FlagConfig",
    "FlagConfigError",
    "FlagReport",
    "Segment",
    "WagonSeries",
    "event_stats",
    "find_dragging",
    "find_drift",
    "find_dropouts",
    "find_frozen",
    "find_loose",
    "find_out_of_range",
    "find_overheating",
    "find_weak",
    "heat_flow_corrected",
    "judge_wagon",
    "load_flag_config",
    "merge_sensor_faults",
    "raise_flags",
    "segment_bounds",
    "segment_stats",
    "watch_simulation",
]

GAP_STEP_S = 60
"""s: the step a long data gap is simulated with (the inputs are interpolated across it)."""

FLAG_KINDS: tuple[str, ...] = ("dragging_brake", "weak_brake", "sensor_fault", "overheating")
SEVERITIES: tuple[str, ...] = ("info", "warning", "alarm")

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


# --------------------------------------------------------------------------------------------
# Configuration


class FlagConfigError(ConfigError):
    """A flag configuration file that cannot be used; the message names the file and key."""


@dataclass(frozen=True)
class FlagConfig:
    """Every threshold of the flags, with its unit. ``docs/flags.md`` explains each.

    A TOML file for :func:`load_flag_config` sets any of these by name, at the top level::

        contact_limit_c = 380.0
        weak_ratio = 0.7
    """

    # ---- data handling (all kinds)
    p_quiet_bar: float = 0.05
    """bar: cylinder pressure at or below which the brake counts as released (the events'
    baseline)."""
    max_gap_s: int = 10
    """s: missing seconds up to this are a data hiccup; a longer run is a gap."""
    bridge_max_s: int = 6 * 3600
    """s: a gap up to this is simulated through (speed and pressure interpolated across it);
    after a longer one the block starts afresh, uniform at its first reading."""
    anchor_s: int = 30
    """s: a segment's prediction is shifted by the mean of measured - predicted over this
    many seconds before it (after it, at the start of the data or after a fault)."""
    window_s: int = 600
    """s: quiet stretches are judged in windows of about this length."""
    min_segment_s: int = 120
    """s: a segment shorter than this is simulated but not judged."""
    edge_s: int = 30
    """s: the readings averaged at each end of a segment for its start and end values."""
    after_release_s: int = 120
    """s: a quiet window starts this long after a release (a braking segment ends there): the
    heat of the braking still spreading to the sensor (and any sensor lag) is the braking's."""
    settle_s: int = 900
    """s: after a data gap in which the wagon may have braked, or a braking with frozen GPS
    speed, segments and brakings starting within this are not judged (the simulated block is
    unsure)."""
    speed_frozen_s: int = 10
    """s: GPS speed repeating one value at least this long while moving is frozen (a braking
    over it has an unknown heat input)."""
    smooth_s: int = 15
    """s: the measured peak of a braking is taken after a running mean over this many seconds."""

    # ---- sensor_fault
    fault_merge_gap_s: int = 600
    """s: sensor faults of one wagon closer than this are one flag (out-of-range runs closer
    than this are one run)."""
    frozen_min_s: int = 120
    """s: a reading unchanged at least this long may be frozen."""
    frozen_resolution_k: float = 0.01
    """K: readings differing by less than this count as unchanged (the logging resolution)."""
    frozen_min_change_k: float = 0.5
    """K: ... it is frozen if the model predicts a change of at least this meanwhile, ..."""
    frozen_noise_k: float = 0.03
    """K: ... or if the same sensor's noise within an hour around the run (estimated from the
    median reading-to-reading difference) is at least this: a live reading would have moved."""
    dropout_min_s: int = 60
    """s: readings missing at least this long, in rows that have their other values, are a
    dropout."""
    loose_min_contrast_k: float = 3.0
    """K: a quiet window is judged for a loose sensor if the reading starts at least this far
    above the air."""
    loose_min_drop_k: float = 2.0
    """K: ... and falls by at least this, and by this much more than the model says the block
    cools, ..."""
    loose_min_fraction: float = 0.3
    """... covering this much more of the way to the air than the block does (0-1)."""
    loose_ambient_k: float = 3.0
    """K: a reading within this of the air reads the air (a loose sensor's, after a while)."""
    detached_ratio: float = 0.25
    """A braking whose measured rise is below this share of the predicted one while the
    reading is at the air temperature shows a sensor not touching the block."""
    responsive_ratio: float = 0.5
    """A braking whose measured rise is at least this share of the predicted one shows a
    sensor in contact (a loose-sensor flag ends before it)."""
    drift_min_rate_k_per_h: float = 2.0
    """K/h: a quiet window whose measured - predicted changes at least this fast, steadily,
    may be drifting ..."""
    drift_max_rate_k_per_h: float = 30.0
    """K/h: ... up to this (faster is not a calibration drift)."""
    drift_max_rms_k: float = 0.3
    """K: ... when measured - predicted stays within this (rms) of a straight line."""
    drift_min_windows: int = 3
    """Consecutive drifting segments (of one sign, at least one a quiet window) needed for a
    flag ..."""
    drift_min_duration_s: int = 1500
    """s: ... spanning at least this, ..."""
    drift_min_change_k: float = 1.5
    """K: ... adding up to at least this, with at least one window starting ``settle_after_
    braking_s`` after the last release (the block has settled: no braking explains it)."""
    drift_heat_flow_ratio: float = 0.35
    """A run whose rates a rate proportional to the block's excess over the air fits with
    less than this share of the squared error of a constant rate is a heat flow the model has
    wrong (convection, conduction), not a drift (0-1)."""
    drift_heat_flow_min_spread: float = 2.0
    """... a test made only when the block's excess over the air within the run varies by at
    least this factor (over a narrower range a constant rate and a proportional one cannot be
    told apart)."""
    heat_flow_min_windows: int = 12
    """Quiet windows long after a braking needed to fit (and take out) the model's heat-flow
    error of a wagon before drifts are judged (fewer: nothing taken out)."""
    settle_after_braking_s: int = 600
    """s: a quiet window starting this long after a release has a settled block."""
    sensor_warning_s: int = 60
    """s: a sensor fault shorter than this is ``info`` (a glitch), longer ``warning`` ..."""
    sensor_alarm_s: int = 3600
    """s: ... and ``alarm`` from this long (the block has gone unwatched that long)."""

    # ---- weak_brake
    weak_ratio: float = 0.75
    """A braking is weak when measured rise / predicted rise is below this ..."""
    weak_min_predicted_rise_k: float = 1.0
    """K: ... and the predicted rise is at least this (smaller ones are not judged)."""
    weak_alarm_ratio: float = 0.5
    """A weak-brake flag whose brakings' median ratio is below this is ``alarm``, else
    ``warning``."""
    weak_min_events: int = 2
    """Consecutive weak brakings needed for a flag (no normal braking between them)."""
    min_valid_fraction: float = 0.8
    """A braking or window is judged only if at least this share of its readings is valid."""

    # ---- dragging_brake
    drag_min_speed_kmh: float = 10.0
    """km/h: a quiet window is judged for dragging only at this mean speed or more (a block
    cannot be heated by friction at a standstill)."""
    drag_min_rise_k: float = 1.0
    """K: the block must heat by at least this over the window, ..."""
    drag_min_excess_k: float = 3.0
    """K: ... and by at least this more than the model, with no cylinder pressure, predicts."""
    drag_unsure_excess_k: float = 10.0
    """K: within ``settle_s`` after a data gap in which the wagon may have braked, a window
    needs this much heating beyond the model (an unsure simulation is off by a few kelvin at
    most)."""
    drag_event_ratio: float = 1.5
    """A braking heating more than this times the predicted rise ..."""
    drag_event_excess_k: float = 5.0
    """K: ... and by at least this much more is dragging too."""
    drag_merge_gap_s: int = 1800
    """s: dragging windows and brakings closer than this are one flag."""
    drag_alarm_excess_k: float = 15.0
    """K: a dragging flag whose heating beyond the model adds up to this is ``alarm``, else
    ``warning``."""

    # ---- overheating
    contact_limit_c: float = 400.0
    """degC: predicted wheel-block contact maximum above which a braking is overheating
    (see docs/flags.md for where 400 degC comes from)."""
    overheat_warning_margin_k: float = 20.0
    """K: over the limit by less than this is ``info``, ..."""
    overheat_alarm_margin_k: float = 100.0
    """K: ... by this or more ``alarm``, in between ``warning``."""

    def __post_init__(self) -> None:
        problems = []
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            problem = _check_field(f.name, f.type, value)
            if problem is not None:
                problems.append(f"{f.name} {problem}")
        if not problems:
            if not self.weak_alarm_ratio <= self.weak_ratio:
                problems.append("weak_alarm_ratio must not exceed weak_ratio")
            if not self.detached_ratio < self.responsive_ratio:
                problems.append("detached_ratio must be below responsive_ratio")
            if not self.drift_min_rate_k_per_h < self.drift_max_rate_k_per_h:
                problems.append("drift_min_rate_k_per_h must be below drift_max_rate_k_per_h")
            if not self.overheat_warning_margin_k <= self.overheat_alarm_margin_k:
                problems.append("overheat_warning_margin_k must not exceed overheat_alarm_margin_k")
            if not self.sensor_warning_s <= self.sensor_alarm_s:
                problems.append("sensor_warning_s must not exceed sensor_alarm_s")
            if not self.edge_s * 2 <= self.min_segment_s:
                problems.append("min_segment_s must be at least twice edge_s")
        if problems:
            raise ValueError("FlagConfig: " + "; ".join(problems))
        for f in dataclasses.fields(self):
            if f.type == "float":
                object.__setattr__(self, f.name, float(getattr(self, f.name)))


_FRACTIONS = {
    "loose_min_fraction",
    "drift_heat_flow_ratio",
    "detached_ratio",
    "responsive_ratio",
    "weak_alarm_ratio",
    "min_valid_fraction",
}
_MAY_BE_ZERO = {"p_quiet_bar", "settle_s", "after_release_s", "fault_merge_gap_s"}


def _check_field(name: str, kind: object, value: object) -> str | None:
    """Why ``value`` cannot be field ``name`` (declared type ``kind``), or None."""
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            return f"must be an integer, got {_shown(value)}"
    elif isinstance(value, bool) or not isinstance(value, int | float):
        return f"must be a number, got {_shown(value)}"
    number = float(value)
    if not math.isfinite(number):
        return f"must be finite, got {_shown(value)}"
    if name in _FRACTIONS:
        return None if 0.0 < number <= 1.0 else f"must be in (0, 1], got {_shown(value)}"
    if name == "contact_limit_c":
        return None if 0.0 < number < 1500.0 else f"must be in (0, 1500) degC, got {_shown(value)}"
    if name in _MAY_BE_ZERO:
        return None if number >= 0.0 else f"must be >= 0, got {_shown(value)}"
    return None if number > 0.0 else f"must be > 0, got {_shown(value)}"


def _shown(value: object) -> str:
    if isinstance(value, bool):
        return f"{'true' if value else 'false'} (a boolean)"
    if isinstance(value, str):
        return f'"{value}" (a string)'
    if isinstance(value, int):
        return f"{value} (an integer)"
    if isinstance(value, float):
        return f"{value!r} (a float)"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "an array"
    return f"{value!r}"


CONFIG_KEYS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(FlagConfig))


def load_flag_config(path: str | Path) -> FlagConfig:
    """The :class:`FlagConfig` of a TOML file: the defaults, with the keys the file sets.

    Keys are the field names of :class:`FlagConfig`, at the top level. Raises
    :class:`FlagConfigError` naming the file (and the key) for a missing or unreadable file,
    bad TOML, an unknown key, or a value of the wrong type or range.
    """
    path = Path(path)
    try:
        with path.open("rb") as handle:
            data = tomllib.load(handle)
    except FileNotFoundError:
        raise FlagConfigError(f"{path}: flag configuration file not found") from None
    except IsADirectoryError:
        raise FlagConfigError(f"{path}: is a directory, not a flag configuration file") from None
    except OSError as error:
        raise FlagConfigError(f"{path}: cannot read it: {error.strerror or error}") from None
    except UnicodeDecodeError as error:
        raise FlagConfigError(f"{path}: not a TOML file (not UTF-8: {error.reason})") from None
    except tomllib.TOMLDecodeError as error:
        raise FlagConfigError(f"{path}: not a valid TOML file: {error}") from None
    types = {f.name: f.type for f in dataclasses.fields(FlagConfig)}
    problems = []
    values: dict[str, Any] = {}
    for key, value in data.items():
        if key not in types:
            close = difflib.get_close_matches(key, CONFIG_KEYS, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            problems.append(f"{path}: key {key}: unknown key{hint}")
            continue
        problem = _check_field(key, types[key], value)
        if problem is not None:
            problems.append(f"{path}: key {key}: {problem}")
            continue
        values[key] = value
    if problems:
        raise FlagConfigError("; ".join(problems))
    try:
        return FlagConfig(**values)
    except ValueError as error:
        message = str(error).removeprefix("FlagConfig: ")
        raise FlagConfigError(f"{path}: {message}") from None


# --------------------------------------------------------------------------------------------
# Records


@dataclass(frozen=True)
class Finding:
    """One anomaly found in one wagon's series, before it becomes a stored :class:`Flag`."""

    kind: str
    severity: str
    start_utc: dt.datetime
    end_utc: dt.datetime
    evidence: str
    event_id: str | None = None
    detail: str | None = None
    """What exactly: for a sensor fault ``out_of_range``, ``frozen``, ``dropout``, ``loose``,
    ``drift``; for a dragging brake ``no_pressure`` or ``braking``."""
    summary: str | None = None
    """A few words for a sensor fault merged into another's flag ("was frozen at 8.04 °C")."""


@dataclass(frozen=True)
class Flag:
    """A row of ``flags``."""

    flag_id: str
    wagon_id: str
    event_id: str | None
    kind: str
    severity: str
    start_utc: dt.datetime
    end_utc: dt.datetime
    evidence: str
    detail: str | None = None


@dataclass
class FlagReport:
    """What :func:`raise_flags` did."""

    wagons: list[str] = field(default_factory=list)
    """The wagons whose flags were recomputed."""
    flags: list[Flag] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    """Wagons judged only in part (no registry entry, no predictions), naming the wagon."""

    def count(self, kind: str | None = None) -> int:
        return sum(1 for f in self.flags if kind is None or f.kind == kind)


# --------------------------------------------------------------------------------------------
# One wagon's series on a 1 Hz grid


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
    """(event_id, activation, release, complete), seconds since t0."""

    @property
    def n(self) -> int:
        return int(self.present.size)

    def utc(self, k: float) -> dt.datetime:
        return self.t0 + dt.timedelta(seconds=float(k))

    @classmethod
    def spans_from_frame(
        cls,
        wagon_id: str,
        samples: pl.DataFrame,
        *,
        ambient_default_c: float,
        events: pl.DataFrame | None = None,
        bridge_max_s: int = FlagConfig.bridge_max_s,
    ) -> list[WagonSeries]:
        """One series per stretch of the samples without a gap longer than ``bridge_max_s``
        (each event in the stretch holding its activation)."""
        if samples.height == 0:
            return []
        frame = samples.sort("time_utc").unique("time_utc", keep="first", maintain_order=True)
        gap = frame["time_utc"].diff().dt.total_seconds().fill_null(0)
        parts = frame.with_columns(_span=(gap > bridge_max_s).cum_sum()).partition_by(
            "_span", maintain_order=True, include_key=False
        )
        out = []
        for part in parts:
            t0, t1 = part["time_utc"][0], part["time_utc"][-1]
            own = None
            if events is not None:
                own = events.filter((pl.col("start_utc") >= t0) & (pl.col("start_utc") <= t1))
            out.append(
                cls.from_frame(wagon_id, part, ambient_default_c=ambient_default_c, events=own)
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
    ) -> WagonSeries:
        """From ``samples`` rows (``time_utc``, ``speed_kmh``, ``brake_pressure_bar``,
        ``block_temp_c``, optional ``block_temp_fault``, ``block_temp_raw_c``,
        ``ambient_temp_c``) and optional ``events`` (``event_id``, ``start_utc``,
        ``end_utc``, optional ``complete``)."""
        if samples.height == 0:
            raise ValueError(f"wagon {wagon_id}: no samples")
        frame = samples.sort("time_utc").unique("time_utc", keep="first", maintain_order=True)
        t0 = frame["time_utc"][0]
        k = (frame["time_utc"] - t0).dt.total_seconds().to_numpy().astype(np.int64)
        n = int(k[-1]) + 1

        def column(name: str) -> FloatArray:
            out = np.full(n, np.nan)
            if name in frame.columns:
                out[k] = frame[name].cast(pl.Float64).to_numpy()
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
            speed_kmh=np.maximum(_interpolate(speed_raw, 0.0), 0.0),
            pressure_bar=np.maximum(_interpolate(column("brake_pressure_bar"), 0.0), 0.0),
            ambient_c=_interpolate(column("ambient_temp_c"), ambient_default_c),
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


def _interpolate(values: FloatArray, default: float) -> FloatArray:
    ok = np.isfinite(values)
    if not ok.any():
        return np.full(values.size, float(default))
    k = np.arange(values.size)
    return np.interp(k, k[ok], values[ok])


def _runs(mask: BoolArray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True."""
    if mask.size == 0:
        return []
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _merge(spans: Iterable[tuple[int, int]], gap: int) -> list[tuple[int, int]]:
    out: list[list[int]] = []
    for a, b in sorted(spans):
        if out and a - out[-1][1] <= gap:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def _running_median(values: FloatArray, width: int) -> FloatArray:
    if width <= 1 or values.size < width:
        return values.copy()
    half = width // 2
    padded = np.pad(values, half, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, width)
    return np.median(windows, axis=1)


def _nan_running_mean(values: FloatArray, width: int) -> FloatArray:
    """Centred running mean over ``width`` samples, ignoring NaN (NaN where none valid)."""
    ok = np.isfinite(values)
    if width <= 1:
        return np.where(ok, values, np.nan)
    kernel = np.ones(width)
    total = np.convolve(np.where(ok, values, 0.0), kernel, mode="same")
    count = np.convolve(ok.astype(np.float64), kernel, mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)


# --------------------------------------------------------------------------------------------
# Text


def _clock(t: dt.datetime) -> str:
    return t.strftime("%H:%M:%S") if t.second else t.strftime("%H:%M")


def _when(start: dt.datetime, end: dt.datetime) -> str:
    """'on 2024-03-04 between 10:12 and 10:31 UTC' (or with both dates)."""
    if start.date() == end.date():
        return f"on {start:%Y-%m-%d} between {_clock(start)} and {_clock(end)} UTC"
    return f"between {start:%Y-%m-%d} {_clock(start)} and {end:%Y-%m-%d} {_clock(end)} UTC"


def _at(t: dt.datetime) -> str:
    return f"on {t:%Y-%m-%d} at {_clock(t)} UTC"


def _duration(seconds: float) -> str:
    s = round(seconds)
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s" if s % 60 else f"{s // 60} min"
    return f"{s // 3600} h {(s % 3600) // 60} min"


def _signed(value: float, unit: str = "K", digits: int = 1) -> str:
    return f"{value:+.{digits}f} {unit}"


def _speeds(v0: float, v1: float) -> str:
    """'from 92 to 40 km/h', or 'at 92 km/h' when the speed hardly changed."""
    if abs(v0 - v1) < 2.0:
        return f"at {0.5 * (v0 + v1):.0f} km/h"
    return f"from {v0:.0f} to {v1:.0f} km/h"


def _severity_by_duration(seconds: float, config: FlagConfig) -> str:
    if seconds >= config.sensor_alarm_s:
        return "alarm"
    return "warning" if seconds >= config.sensor_warning_s else "info"


# --------------------------------------------------------------------------------------------
# 1. Sensor faults from the readings alone


def find_out_of_range(series: WagonSeries, config: FlagConfig = FlagConfig()) -> list[Finding]:
    """Runs of out-of-range readings (``block_temp_fault``), merged across short breaks."""
    lo, hi = BLOCK_TEMP_VALID_C
    out = []
    for a, b in _merge(_runs(series.fault), config.fault_merge_gap_s):
        raw = series.raw_c[a:b][series.fault[a:b]]
        raw = raw[np.isfinite(raw)]
        count = int(series.fault[a:b].sum())
        if raw.size and np.all(raw > hi):
            what = f"read {np.median(raw):.1f} °C, above the {hi:g} °C a Pt1000 can read"
            cause = "an open circuit (broken wire or connector)"
        elif raw.size and np.all(raw < lo):
            what = f"read {np.median(raw):.1f} °C, below the {lo:g} °C a Pt1000 can read"
            cause = "a short circuit in the sensor cable"
        else:
            what = f"read out of the {lo:g}…{hi:g} °C range"
            cause = "a broken sensor circuit"
        start, end = series.utc(a), series.utc(b)
        out.append(
            Finding(
                "sensor_fault",
                _severity_by_duration(b - a, config),
                start,
                end,
                f"Block temperature sensor of {series.wagon_id} {what} {_when(start, end)} "
                f"({count} readings over {_duration(b - a)}): {cause}; check the Pt1000, its "
                "cable and connector.",
                detail="out_of_range",
                summary=f"out of range for {_duration(b - a)}",
            )
        )
    return out


def find_frozen(
    series: WagonSeries,
    config: FlagConfig = FlagConfig(),
    predicted_c: FloatArray | None = None,
) -> list[Finding]:
    """Readings unchanged (to within ``frozen_resolution_k``) for ``frozen_min_s`` or more,
    while the same sensor is noisy elsewhere or ``predicted_c`` (the model's sensor
    temperature on the series' grid) changes by ``frozen_min_change_k`` meanwhile."""
    out = []
    for a, b, value in _constant_runs(series.measured_c, config):
        change, signed = None, 0.0
        if predicted_c is not None:
            seg = predicted_c[a:b]
            seg = seg[np.isfinite(seg)]
            if seg.size:
                change = float(seg.max() - seg.min())
                signed = float(seg[-1] - seg[0])
        noise = _scatter_around(series.measured_c, a, b)
        by_model = change is not None and change >= config.frozen_min_change_k
        by_noise = noise is not None and noise >= config.frozen_noise_k
        if not (by_model or by_noise):
            continue
        start, end = series.utc(a), series.utc(b)
        reasons = []
        if by_model:
            reasons.append(f"the model has the block change by {_signed(signed)} meanwhile")
        if by_noise:
            reasons.append(f"its readings scatter by ±{noise:.2f} K elsewhere")
        out.append(
            Finding(
                "sensor_fault",
                _severity_by_duration(b - a, config),
                start,
                end,
                f"Block temperature reading of {series.wagon_id} stuck at {value:.2f} °C for "
                f"{_duration(b - a)} {_when(start, end)} while {' and '.join(reasons)}: the "
                "reading is frozen; check the sensor and its logger channel.",
                detail="frozen",
                summary=f"frozen at {value:.2f} °C for {_duration(b - a)}",
            )
        )
    return out


def _constant_runs(values: FloatArray, config: FlagConfig) -> list[tuple[int, int, float]]:
    """[start, stop) of runs of valid readings within ``frozen_resolution_k`` of the run's
    first one lasting ``frozen_min_s`` or more (missing readings inside do not break a run)."""
    idx = np.flatnonzero(np.isfinite(values))
    if idx.size < 2:
        return []
    v = values[idx]
    same = np.abs(np.diff(v)) < config.frozen_resolution_k
    out = []
    for a, b in _runs(same):  # same[a:b]: readings idx[a] .. idx[b] equal their neighbours
        first, last = int(idx[a]), int(idx[b])
        if last - first + 1 >= config.frozen_min_s:
            out.append((first, last + 1, float(v[a])))
    return out


def _scatter_around(values: FloatArray, a: int, b: int) -> float | None:
    """The noise of the valid readings within an hour around [a, b), as the standard
    deviation a Gaussian noise would have given their median reading-to-reading difference
    (robust to the block's own changes); None if too few."""
    lo, hi = max(a - 3600, 0), min(b + 3600, values.size)
    window = values[lo:hi].copy()
    window[a - lo : b - lo] = np.nan
    pairs = np.isfinite(window[1:]) & np.isfinite(window[:-1])
    if pairs.sum() < 60:
        return None
    # median |x1 - x0| of two samples of N(0, s^2) is 0.6745 sqrt(2) s
    return float(np.median(np.abs(np.diff(window))[pairs])) / (0.6745 * math.sqrt(2.0))


def find_dropouts(series: WagonSeries, config: FlagConfig = FlagConfig()) -> list[Finding]:
    """Runs of rows with no reading (not out of range, just missing) for ``dropout_min_s``
    or more while the logger wrote the rest of the row."""
    missing = series.present & ~np.isfinite(series.measured_c) & ~series.fault
    out = []
    for a, b in _merge(_runs(missing), 0):
        rows = int(missing[a:b].sum())
        if b - a < config.dropout_min_s or rows < 0.8 * (b - a):
            continue
        start, end = series.utc(a), series.utc(b)
        out.append(
            Finding(
                "sensor_fault",
                _severity_by_duration(b - a, config),
                start,
                end,
                f"Block temperature readings of {series.wagon_id} missing for {_duration(b - a)} "
                f"{_when(start, end)} ({rows} rows) while speed and pressure were logged: the "
                "sensor drops out; check its connector and cable.",
                detail="dropout",
                summary=f"missing for {_duration(b - a)}",
            )
        )
    return out


# --------------------------------------------------------------------------------------------
# 2. The watch simulation and its segments


@dataclass(frozen=True)
class Segment:
    """A stretch of the watch simulation with its own anchor: a braking (activation to
    ``after_release_s`` after release) or a quiet window. Start/end values are means over
    ``edge_s`` of valid readings at each end."""

    start: int
    stop: int
    """[start, stop), seconds since the series' t0."""
    kind: str
    """``braking``, ``quiet`` or ``gap`` (no rows)."""
    enough: bool
    """Long enough, with enough valid readings."""
    calm: bool
    """The simulated block is sure (no blind gap or frozen GPS speed within ``settle_s``)."""
    event_id: str | None
    speed_kmh: float
    """Mean speed."""
    pressure_max_bar: float
    ambient_c: float
    m_start: float
    m_end: float
    p_start: float
    p_end: float
    m_rise: float
    """Measured peak (after a running mean over ``smooth_s``) minus ``m_start``."""
    p_rise: float
    slope_k_per_h: float
    """Slope of measured - predicted, least squares."""
    line_rms_k: float
    """rms of measured - predicted about that line."""
    since_release_s: float
    """Seconds from the last release before the segment to its start (inf if none)."""
    m_ambient_k: float
    """Mean |measured - air| over the segment."""

    @property
    def judged(self) -> bool:
        return self.enough and self.calm

    @property
    def excess_k(self) -> float:
        """How much more the reading rose than predicted (negative: less)."""
        return (self.m_end - self.m_start) - (self.p_end - self.p_start)

    @property
    def ratio(self) -> float:
        return self.m_rise / self.p_rise if self.p_rise > 0 else math.nan


@dataclass
class Watch:
    """The watch simulation of a series: the predicted sensor and contact temperatures on
    its grid, the segment bounds and kinds."""

    predicted_c: FloatArray
    contact_max_c: FloatArray
    bounds: list[int]
    """Segment starts, then the end of the series."""
    kinds: list[str]
    unsure: BoolArray
    """Seconds at which the simulated block is unsure (a blind gap, frozen speed while
    braking, and ``settle_s`` after them)."""


def _unsure_mask(series: WagonSeries, config: FlagConfig) -> BoolArray:
    n = series.n
    unsure = np.zeros(n, dtype=bool)
    spans: list[tuple[int, int]] = []
    present = np.flatnonzero(series.present)
    gaps = np.flatnonzero(np.diff(present) > config.max_gap_s)
    for g in gaps:
        a, b = int(present[g]), int(present[g + 1])
        edge = [a, b]
        moving = any(series.speed_kmh[k] > 5.0 for k in edge)
        braking = any(series.pressure_bar[k] > config.p_quiet_bar for k in edge)
        if moving or braking:
            spans.append((a, b))
    # frozen GPS speed over a braking
    speed = series.speed_raw_kmh
    idx = np.flatnonzero(np.isfinite(speed))
    if idx.size > 1:
        same = (np.abs(np.diff(speed[idx])) < 1e-9) & (speed[idx][1:] > 1.0)
        for a, b in _runs(same):
            first, last = int(idx[a]), int(idx[b])
            if last - first + 1 >= config.speed_frozen_s and np.any(
                series.pressure_bar[first : last + 1] > config.p_quiet_bar
            ):
                spans.append((first, last + 1))
    for a, b in spans:
        unsure[a : min(b + config.settle_s, n)] = True
    return unsure


def segment_bounds(
    series: WagonSeries,
    config: FlagConfig = FlagConfig(),
) -> tuple[list[int], list[str]]:
    """Segment starts (then the series' end) and kinds: every activation starts a
    ``braking`` segment lasting until ``after_release_s`` after the release; the quiet
    stretches between are cut into ``quiet`` windows of about ``window_s``; every data gap
    longer than ``max_gap_s`` is a ``gap`` segment of its own."""
    n = series.n
    braking = np.zeros(n, dtype=bool)
    starts = set()
    for _, a, b, _ in series.events:
        lo, hi = max(a, 0), min(b + config.after_release_s, n)
        if hi > lo:
            braking[lo:hi] = True
        if 0 <= a < n:
            starts.add(a)
    bounds = {0} | starts
    present = np.flatnonzero(series.present)
    gaps = [
        (int(present[g]) + 1, int(present[g + 1]))
        for g in np.flatnonzero(np.diff(present) > config.max_gap_s)
    ]
    for a, b in _runs(~braking):
        windows = max(1, round((b - a) / config.window_s))
        bounds |= {a + ((b - a) * j) // windows for j in range(windows)}
    for a, _ in _runs(braking):  # a braking segment starts at its activation
        bounds.add(a)
    inside = np.zeros(n + 1, dtype=bool)
    for a, b in gaps:
        inside[a + 1 : b] = True
    bounds = {k for k in bounds if not inside[k]} | {k for gap in gaps for k in gap}
    gap_starts = {a for a, _ in gaps}
    ordered = sorted(k for k in bounds if 0 <= k < n - 1)
    kinds = ["gap" if k in gap_starts else "braking" if braking[k] else "quiet" for k in ordered]
    return [*ordered, n], kinds


def watch_simulation(
    series: WagonSeries,
    wagon: WagonConfig,
    rom: Any,
    effects: EffectSet = EffectSet(),  # noqa: B008
    config: FlagConfig = FlagConfig(),
    *,
    invalid: BoolArray | None = None,
) -> Watch:
    """Simulate the series' block from a uniform start at its first valid reading, through
    its gaps, re-anchored at the start of every segment (readings where ``invalid`` is set
    are not used)."""
    from fleetbrake.model.rom import first_order_lag
    from fleetbrake.model.timeline import simulate_timeline

    n = series.n
    measured = series.measured_c.copy()
    if invalid is not None:
        measured[invalid] = np.nan
    bounds, kinds = segment_bounds(series, config)
    predicted = np.full(n, np.nan)
    contact = np.full(n, np.nan)
    speed = _running_median(series.speed_kmh, 7)
    # A sensor lag is carried across the segments here (simulate_timeline would restart it
    # at each one): the block is simulated without it and the lag applied to the seat
    # temperature less the anchoring shifts, which act at once, as a correction of the whole
    # field does.
    lag = effects.get("sensor_lag")
    tau_s = float(getattr(lag, "tau_s", 0.0))
    block_effects = EffectSet(tuple(e for e in effects if e.name != "sensor_lag"))
    t_ref: float | None = None
    t_first = 0.0
    state = None
    lagged_last: float | None = None

    def run(
        a: int, b: int, ref: float, initial: Any, coarse: bool
    ) -> tuple[Any, FloatArray, FloatArray, float | None]:
        """The segment [a, b] simulated: (result, sensor, contact max) at every second, and
        the lag's last value. A long gap (no readings, the wagon standing or unknown) is
        simulated in steps of up to ``GAP_STEP_S`` and interpolated."""
        k = np.arange(a, b + 1)
        if coarse:
            steps = math.ceil((b - a) / GAP_STEP_S)
            at = np.linspace(a, b, steps + 1)
            dt_s = (b - a) / steps
        else:
            at, dt_s = k.astype(np.float64), 1.0
        result = simulate_timeline(
            rom,
            wagon,
            dt_s=dt_s,
            p_bar=np.interp(at, k, series.pressure_bar[a : b + 1]),
            speed_kmh=np.interp(at, k, speed[a : b + 1]),
            ambient_c=np.interp(at, k, series.ambient_c[a : b + 1]),
            initial_c=ref,
            initial_state=initial,
            effects=block_effects,
        )
        sensor, last = result.sensor_c, None
        if lag is not None:
            shift = ref - t_first
            base = first_order_lag(sensor - shift, dt_s, tau_s, initial=lagged_last)
            sensor, last = base + shift, float(base[-1])
        if coarse:
            return result, np.interp(k, at, sensor), np.interp(k, at, result.contact_max_c), last
        return result, sensor, result.contact_max_c, last

    for (a, stop), kind in zip(itertools.pairwise(bounds), kinds, strict=True):
        b = min(stop, n - 1)
        if b <= a:
            continue
        coarse = kind == "gap" and b - a > 2 * GAP_STEP_S
        if t_ref is None:  # uniform at the first valid reading
            ahead = measured[a : min(a + config.window_s, n)]
            ok = np.flatnonzero(np.isfinite(ahead))
            t_ref = t_first = float(ahead[ok[0]]) if ok.size else float(series.ambient_c[a])
            state = None
        back = (
            measured[max(a - config.anchor_s, 0) : a] - predicted[max(a - config.anchor_s, 0) : a]
        )
        back = back[np.isfinite(back)]
        if back.size >= 5:
            t_ref += float(back.mean())
            result, sensor, face_max, last = run(a, b, t_ref, state, coarse)
        else:
            result, sensor, face_max, last = run(a, b, t_ref, state, coarse)
            length = min(config.anchor_s, sensor.size)
            ahead = measured[a : a + length] - sensor[:length]
            ahead = ahead[np.isfinite(ahead)]
            if ahead.size >= 5 and abs(float(ahead.mean())) > 1e-3:
                t_ref += float(ahead.mean())
                result, sensor, face_max, last = run(a, b, t_ref, state, coarse)
        state, lagged_last = result.final_state, last
        predicted[a : b + 1] = sensor
        contact[a : b + 1] = face_max
    return Watch(predicted, contact, bounds, kinds, _unsure_mask(series, config))


def segment_stats(
    series: WagonSeries,
    predicted_c: FloatArray,
    bounds: Sequence[int],
    kinds: Sequence[str],
    config: FlagConfig = FlagConfig(),
    *,
    unsure: BoolArray | None = None,
    invalid: BoolArray | None = None,
) -> list[Segment]:
    """The :class:`Segment` of each [bounds[i], bounds[i+1]) of the series and its prediction."""
    measured = series.measured_c.copy()
    if invalid is not None:
        measured[invalid] = np.nan
    releases = sorted(b for _, _, b, _ in series.events)
    event_at = {a: event_id for event_id, a, _, _ in series.events}
    smooth = _nan_running_mean(measured, config.smooth_s)
    out = []
    for i, (a, b) in enumerate(itertools.pairwise(bounds)):
        m = measured[a:b]
        p = predicted_c[a:b]
        ok = np.isfinite(m) & np.isfinite(p)
        idx = np.flatnonzero(ok)
        length = b - a
        enough = (
            length >= config.min_segment_s
            and idx.size >= 2 * config.edge_s
            and idx.size >= config.min_valid_fraction * length
        )
        calm = unsure is None or not unsure[a:b].any()
        nan = math.nan
        if idx.size >= 2:
            head, tail = idx[: config.edge_s], idx[-config.edge_s :]
            m_start, m_end = float(m[head].mean()), float(m[tail].mean())
            p_start, p_end = float(p[head].mean()), float(p[tail].mean())
            r = m[idx] - p[idx]
            k = idx.astype(np.float64)
            slope, intercept = np.polyfit(k, r, 1)
            rms = float(np.sqrt(np.mean((r - (slope * k + intercept)) ** 2)))
            sm = smooth[a:b][idx]
            m_rise = float(np.nanmax(sm) - m_start)
            p_rise = float(np.max(p[idx]) - p_start)
            m_ambient = float(np.mean(np.abs(m[idx] - series.ambient_c[a:b][idx])))
        else:
            m_start = m_end = p_start = p_end = m_rise = p_rise = nan
            slope, rms, m_ambient = nan, nan, nan
        j = np.searchsorted(releases, a, side="right") - 1
        since = a - releases[j] if j >= 0 else math.inf
        out.append(
            Segment(
                start=int(a),
                stop=int(b),
                kind=kinds[i],
                enough=bool(enough),
                calm=bool(calm),
                event_id=event_at.get(a) if kinds[i] == "braking" else None,
                speed_kmh=float(series.speed_kmh[a:b].mean()),
                pressure_max_bar=float(series.pressure_bar[a:b].max()),
                ambient_c=float(series.ambient_c[a:b].mean()),
                m_start=m_start,
                m_end=m_end,
                p_start=p_start,
                p_end=p_end,
                m_rise=m_rise,
                p_rise=p_rise,
                slope_k_per_h=float(slope) * 3600.0,
                line_rms_k=rms,
                since_release_s=float(since),
                m_ambient_k=m_ambient,
            )
        )
    return out


# --------------------------------------------------------------------------------------------
# 3. Sensor faults against the model


def _is_loose_window(s: Segment, config: FlagConfig) -> bool:
    if s.kind != "quiet" or not s.judged:
        return False
    contrast = s.m_start - s.ambient_c
    model_contrast = s.p_start - s.ambient_c
    if contrast < config.loose_min_contrast_k or model_contrast <= 0:
        return False
    towards_m = (s.m_start - s.m_end) / contrast
    towards_p = (s.p_start - s.p_end) / model_contrast
    return (
        s.m_start - s.m_end >= config.loose_min_drop_k
        and s.excess_k <= -config.loose_min_drop_k
        and towards_m - towards_p >= config.loose_min_fraction
    )


def _is_detached_braking(s: Segment, config: FlagConfig) -> bool:
    return (
        s.kind == "braking"
        and s.judged
        and s.p_rise >= max(2.0, config.weak_min_predicted_rise_k)
        and s.ratio < config.detached_ratio
        and s.m_ambient_k <= config.loose_ambient_k
    )


def find_loose(
    series: WagonSeries,
    segments: Sequence[Segment],
    config: FlagConfig = FlagConfig(),
    predicted_c: FloatArray | None = None,
) -> list[Finding]:
    """A sensor come loose: its reading falls towards the air much faster than the block can
    cool (a quiet window), or it reads the air and does not rise in a braking. The flag goes
    on over the following segments while the reading keeps reading the air or stays flat in
    brakings (segments not judged are passed over), and ends before a braking it follows
    again or a quiet window where it reads neither the air nor falls towards it. With
    ``predicted_c`` (the watch simulation) the start is moved back to where the reading left
    the model in the segment before."""
    out = []
    i = 0
    while i < len(segments):
        s = segments[i]
        if not (_is_loose_window(s, config) or _is_detached_braking(s, config)):
            i += 1
            continue
        first = last = i
        brakings: list[Segment] = []
        j = i + 1
        while j < len(segments):
            t = segments[j]
            if t.kind == "braking":
                if not t.judged or not t.p_rise >= 2.0:
                    pass
                elif t.ratio >= config.responsive_ratio:
                    break
                elif t.ratio < config.detached_ratio:
                    brakings.append(t)
                    last = j
            elif t.judged and math.isfinite(t.m_ambient_k):
                if not (_is_loose_window(t, config) or t.m_ambient_k <= config.loose_ambient_k):
                    break
                last = j
            j += 1
        head = segments[first]
        onset = head.start
        if predicted_c is not None:
            onset = _departure(series, predicted_c, head, head.start, config)
            if first > 0:
                onset = _departure(series, predicted_c, segments[first - 1], onset, config)
        start, end = series.utc(onset), series.utc(segments[last].stop)
        if head.kind == "quiet":
            seen = (
                f"fell from {head.m_start:.1f} °C to {head.m_end:.1f} °C "
                f"{_when(series.utc(head.start), series.utc(head.stop))}, towards the "
                f"{head.ambient_c:.1f} °C air, while the model has the block at "
                f"{head.p_end:.1f} °C"
            )
        else:
            seen = (
                f"stayed at {head.m_start:.1f} °C, the air's {head.ambient_c:.1f} °C, in the "
                f"braking {_at(series.utc(head.start))} where a rise of {head.p_rise:.1f} K "
                "was predicted"
            )
        if brakings:
            rises = [f"{b.m_rise:.1f} K instead of {b.p_rise:.1f} K" for b in brakings[:3]]
            more = f" (and in {len(brakings) - 3} more)" if len(brakings) > 3 else ""
            seen += f"; in the brakings after that it rose {', '.join(rises)}{more}"
        out.append(
            Finding(
                "sensor_fault",
                _severity_by_duration((end - start).total_seconds(), config),
                start,
                end,
                f"Block temperature reading of {series.wagon_id} {seen}: the sensor is no longer "
                "in contact with the block (loose); reseat and fix it.",
                detail="loose",
                summary=f"read the air ({_when(start, end)})",
            )
        )
        i = j
    return out


def _departure(
    series: WagonSeries,
    predicted_c: FloatArray,
    before: Segment,
    default: int,
    config: FlagConfig,
) -> int:
    """Where, in the segment ``before``, measured - predicted fell below -loose_min_drop_k
    for good (the reading left the model), or ``default``."""
    r = series.measured_c[before.start : before.stop] - predicted_c[before.start : before.stop]
    r = _nan_running_mean(r, config.edge_s)
    below = np.isfinite(r) & (r < -config.loose_min_drop_k)
    if r.size == 0 or not below[-config.edge_s :].any():
        return default
    above = np.flatnonzero(np.isfinite(r) & ~below)
    return before.start + (int(above[-1]) + 1 if above.size else 0)


def _is_drifting(s: Segment, config: FlagConfig) -> bool:
    """A judged segment whose measured - predicted changes steadily at a drift's rate."""
    rate = abs(s.slope_k_per_h)
    return (
        s.judged
        and config.drift_min_rate_k_per_h <= rate <= config.drift_max_rate_k_per_h
        and s.line_rms_k <= config.drift_max_rms_k
        and s.excess_k < config.drag_min_excess_k
    )


def heat_flow_corrected(
    segments: Sequence[Segment], config: FlagConfig = FlagConfig()
) -> list[Segment]:
    """The quiet windows with what the model's heat flow has wrong for this wagon taken out.

    The rate at which measured - predicted changes in the quiet windows long after a braking
    (``settle_after_braking_s``) is fitted, robustly, as e (k0 + k1 v / 100 km/h), e the
    block's excess over the air, v the speed: a cooling the model has too slow or too fast
    (a convection coefficient, one growing with speed) is in every window of the wagon and is
    fitted; a drifting sensor is in a minority of them and is trimmed away. The fit is taken
    out of the quiet windows' rates (and end values), within the range of e and v it was made
    on, when it matters: when it explains most of the windows' rates and its rates reach half
    ``drift_min_rate_k_per_h`` (rms). With fewer than ``heat_flow_min_windows`` such windows
    nothing is changed."""
    rows = [
        s
        for s in segments
        if s.kind == "quiet"
        and s.judged
        and s.since_release_s >= config.settle_after_braking_s
        and math.isfinite(s.slope_k_per_h)
        and math.isfinite(s.p_start)
    ]
    if len(rows) < config.heat_flow_min_windows:
        return list(segments)

    def columns(items: Sequence[Segment]) -> tuple[FloatArray, FloatArray]:
        excess = np.array([0.5 * (s.p_start + s.p_end) - s.ambient_c for s in items])
        return excess, np.array([s.speed_kmh for s in items]) / 100.0

    excess, speed = columns(rows)
    x = np.column_stack([excess, excess * speed])
    y = np.array([s.slope_k_per_h for s in rows])
    keep = np.ones(y.size, dtype=bool)
    for _ in range(3):  # least squares, trimming the windows far from the fit
        coef = np.linalg.lstsq(x[keep], y[keep], rcond=None)[0]
        residual = y - x @ coef
        spread = 1.4826 * float(np.median(np.abs(residual[keep])))
        keep = np.abs(residual) <= max(3.0 * spread, config.drift_min_rate_k_per_h / 2)
        if keep.sum() < config.heat_flow_min_windows:
            return list(segments)
    fitted = x[keep] @ coef
    explained = 1.0 - float(np.sum((y[keep] - fitted) ** 2)) / max(
        float(np.sum(y[keep] ** 2)), 1e-12
    )
    if explained < 0.5 or float(np.sqrt(np.mean(fitted**2))) < config.drift_min_rate_k_per_h / 2:
        return list(segments)
    (e_lo, e_hi), (v_lo, v_hi) = (excess.min(), excess.max()), (speed.min(), speed.max())
    out = []
    for s in segments:
        if s.kind != "quiet" or not math.isfinite(s.p_start):
            out.append(s)
            continue
        (e,), (v,) = columns([s])
        e, v = float(np.clip(e, e_lo, e_hi)), float(np.clip(v, v_lo, v_hi))
        rate = float(coef[0] * e + coef[1] * e * v)
        hours = (s.stop - s.start) / 3600.0
        out.append(
            dataclasses.replace(
                s, slope_k_per_h=s.slope_k_per_h - rate, p_end=s.p_end + rate * hours
            )
        )
    return out


def _explained_by_heat_flow(run: Sequence[Segment], config: FlagConfig) -> bool:
    """Whether the quiet windows' rates follow the block's excess over the air (rate = k x
    excess) much better than they are constant (``drift_heat_flow_ratio``), over a wide
    enough range of excess (``drift_heat_flow_min_spread``): a heat flow the model has wrong
    (convection, holder), not a sensor drifting."""
    rates = np.array([s.slope_k_per_h for s in run])
    excess = np.array([0.5 * (s.p_start + s.p_end) - s.ambient_c for s in run])
    if not np.all(np.isfinite(excess)) or excess.min() <= 0:
        return False
    if excess.max() < config.drift_heat_flow_min_spread * excess.min():
        return False  # too narrow a range of block temperatures to tell
    k = float(rates @ excess) / float(excess @ excess)
    proportional = float(np.sum((rates - k * excess) ** 2))
    constant = float(np.sum((rates - rates.mean()) ** 2))
    return proportional < config.drift_heat_flow_ratio * constant


def find_drift(
    series: WagonSeries, segments: Sequence[Segment], config: FlagConfig = FlagConfig()
) -> list[Finding]:
    """A drifting reading: measured - predicted changes steadily, at one sign, segment after
    segment, whatever the block does: in quiet windows and brakings alike.

    A run collects the drifting segments of one sign; brakings, segments not judged and
    windows right after a braking (``settle_after_braking_s``) that do not drift are passed
    over; any other quiet window that does not drift ends it. A run of at least
    ``drift_min_windows`` segments, one of them a quiet window, is a drift when no braking's
    aftermath explains it (one of its windows starts long after a braking, or every braking in
    it drifts along: a weak brake's do not, they fall far behind the model) and no heat flow
    does (:func:`_explained_by_heat_flow`)."""
    out = []
    run: list[Segment] = []

    def close() -> None:
        quiet = [s for s in run if s.kind == "quiet"]
        if len(run) < config.drift_min_windows or not quiet:
            return
        span = run[-1].stop - run[0].start
        total = sum(s.excess_k for s in run)
        if span < config.drift_min_duration_s or abs(total) < config.drift_min_change_k:
            return
        rate = float(np.median([s.slope_k_per_h for s in run]))
        settled = any(s.since_release_s >= config.settle_after_braking_s for s in quiet)
        members = {id(s) for s in run}
        brakings = [
            s
            for s in segments
            if s.kind == "braking" and s.judged and run[0].start <= s.start < run[-1].stop
        ]
        along = bool(brakings) and all(id(s) in members for s in brakings)
        if not (settled or along) or _explained_by_heat_flow(quiet, config):
            return
        start, end = series.utc(run[0].start), series.utc(run[-1].stop)
        where = (
            "long after brakings as much as right after them"
            if settled
            else f"in the {len(brakings)} braking{'s' if len(brakings) > 1 else ''} as much "
            "as between them"
        )
        out.append(
            Finding(
                "sensor_fault",
                _severity_by_duration(span, config),
                start,
                end,
                f"Block temperature reading of {series.wagon_id} drifted away from the model at "
                f"{_signed(rate, 'K/h')} ({_signed(total)} over {_duration(span)}) "
                f"{_when(start, end)}, {where}, which no heat flow of the block explains: the "
                "sensor is drifting; check its seating and calibration.",
                detail="drift",
                summary=f"drifted at {_signed(rate, 'K/h')}",
            )
        )

    for s in segments:
        if not s.judged:
            continue  # neither counts nor ends a run
        if _is_drifting(s, config) and (
            not run or np.sign(s.slope_k_per_h) == np.sign(run[-1].slope_k_per_h)
        ):
            run.append(s)
            continue
        if s.kind == "braking" or s.since_release_s < config.settle_after_braking_s:
            continue  # a braking, or right after one: its own heat may hide a drift
        close()
        run = [s] if _is_drifting(s, config) else []
    close()
    return out


# --------------------------------------------------------------------------------------------
# 4. Brakes


@dataclass(frozen=True)
class EventStat:
    """One braking as the revision's predictions show it."""

    event_id: str
    start_utc: dt.datetime
    end_utc: dt.datetime
    window_end_utc: dt.datetime
    judged: bool
    m_rise: float
    p_rise: float
    contact_max_c: float
    contact_max_utc: dt.datetime
    v_start_kmh: float
    v_end_kmh: float
    p_max_bar: float

    @property
    def ratio(self) -> float:
        return self.m_rise / self.p_rise if self.p_rise > 0 else math.nan


def event_stats(
    predictions: pl.DataFrame,
    events: pl.DataFrame,
    config: FlagConfig = FlagConfig(),
    *,
    excluded: Sequence[tuple[dt.datetime, dt.datetime]] = (),
    unsure: Sequence[tuple[dt.datetime, dt.datetime]] = (),
) -> list[EventStat]:
    """Per braking (``events``: ``event_id``, ``start_utc``, ``end_utc``, optional
    ``complete``) the measured and predicted rise from activation to the peak of its window in
    ``predictions`` (rows of one wagon and revision). A braking is not judged when incomplete,
    when its window overlaps ``excluded`` (sensor faults), when [activation - settle_s,
    release] overlaps ``unsure``, or with too few valid readings."""
    out = []
    by_event = {key[0]: group for key, group in predictions.group_by(["event_id"])}
    for row in events.sort("start_utc").iter_rows(named=True):
        group = by_event.get(row["event_id"])
        if group is None or group.height < 2:
            continue
        group = group.sort("time_utc")
        times = group["time_utc"]
        m = group["measured_sensor_c"].cast(pl.Float64).fill_null(np.nan).to_numpy()
        p = group["predicted_sensor_c"].to_numpy().astype(np.float64)
        cmax = group["predicted_contact_max_c"].to_numpy().astype(np.float64)
        w0, w1 = times[0], times[-1]
        valid = np.isfinite(m)
        start_vals = m[:5][valid[:5]]
        judged = bool(row.get("complete", True)) and valid.mean() >= config.min_valid_fraction
        judged = judged and start_vals.size > 0
        judged = judged and not any(a < w1 and w0 < b for a, b in excluded)
        lead = dt.timedelta(seconds=config.settle_s)
        judged = judged and not any(
            a < row["end_utc"] and row["start_utc"] - lead < b for a, b in unsure
        )
        m0 = float(start_vals.mean()) if start_vals.size else math.nan
        smooth = _nan_running_mean(m, config.smooth_s)
        m_rise = float(np.nanmax(smooth) - m0) if np.isfinite(smooth).any() else math.nan
        p_rise = float(p.max() - p[0])
        k = int(np.argmax(cmax))
        pressure = group["brake_pressure_bar"].cast(pl.Float64).fill_null(0.0).to_numpy()
        speed = group["speed_kmh"].cast(pl.Float64).fill_null(0.0).to_numpy()
        heating = (group["phase"] == "heating").to_numpy()
        v_h = speed[heating] if heating.any() else speed
        out.append(
            EventStat(
                event_id=row["event_id"],
                start_utc=row["start_utc"],
                end_utc=row["end_utc"],
                window_end_utc=w1,
                judged=judged and math.isfinite(m_rise),
                m_rise=m_rise,
                p_rise=p_rise,
                contact_max_c=float(cmax[k]),
                contact_max_utc=times[k],
                v_start_kmh=float(v_h[0]),
                v_end_kmh=float(v_h[-1]),
                p_max_bar=float(pressure.max()),
            )
        )
    return out


def find_weak(
    wagon_id: str, stats: Sequence[EventStat], config: FlagConfig = FlagConfig()
) -> list[Finding]:
    """Runs of weak brakings (measured rise below ``weak_ratio`` x the predicted one) with no
    normal braking between them; brakings not judged or with a small predicted rise neither
    count nor break a run."""
    out = []
    run: list[EventStat] = []

    def close() -> None:
        if len(run) < config.weak_min_events:
            return
        ratios = np.array([e.ratio for e in run])
        median = float(np.median(ratios))
        worst = min(run, key=lambda e: e.ratio)
        start, end = run[0].start_utc, run[-1].end_utc
        if len(run) == 1:
            what = f"the braking {_at(start)}"
        else:
            what = f"{len(run)} brakings {_when(start, end)}"
        out.append(
            Finding(
                "weak_brake",
                "alarm" if median < config.weak_alarm_ratio else "warning",
                start,
                end,
                f"Block of {wagon_id} heated only {100 * median:.0f} % of the predicted rise in "
                f"{what} (e.g. {worst.m_rise:.1f} K instead of {worst.p_rise:.1f} K "
                f"{_at(worst.start_utc)}, {_speeds(worst.v_start_kmh, worst.v_end_kmh)} "
                f"with up to {worst.p_max_bar:.2f} bar): the block presses with too little force; "
                "check the brake cylinder, rigging, slack adjuster and the blocks.",
                event_id=run[0].event_id if len(run) == 1 else None,
            )
        )

    for e in stats:
        if not e.judged or e.p_rise < config.weak_min_predicted_rise_k:
            continue
        if e.ratio < config.weak_ratio:
            run.append(e)
        else:
            close()
            run = []
    close()
    return out


def find_dragging(
    series: WagonSeries,
    segments: Sequence[Segment],
    stats: Sequence[EventStat] = (),
    config: FlagConfig = FlagConfig(),
    *,
    excluded: Sequence[tuple[int, int]] = (),
) -> list[Finding]:
    """Quiet windows (no cylinder pressure, moving) in which the block heats by
    ``drag_min_rise_k`` and by ``drag_min_excess_k`` more than the model predicts, and
    brakings heating ``drag_event_ratio`` x and ``drag_event_excess_k`` more than predicted;
    those closer than ``drag_merge_gap_s`` are one flag. Segments overlapping ``excluded``
    ([start, stop) seconds: sensor faults) are not used."""
    items: list[tuple[int, int, str, Any]] = []
    for s in segments:
        if s.kind != "quiet" or not s.enough:
            continue
        if any(a < s.stop and s.start < b for a, b in excluded):
            continue
        if not s.calm and not s.excess_k >= config.drag_unsure_excess_k:
            continue
        if (
            s.speed_kmh >= config.drag_min_speed_kmh
            and s.m_end - s.m_start >= config.drag_min_rise_k
            and s.excess_k >= config.drag_min_excess_k
        ):
            items.append((s.start, s.stop, "window", s))
    for e in stats:
        if not e.judged or e.p_rise <= 0:
            continue
        if e.m_rise - e.p_rise >= config.drag_event_excess_k and e.ratio >= config.drag_event_ratio:
            a = int((e.start_utc - series.t0).total_seconds())
            b = int((e.window_end_utc - series.t0).total_seconds())
            items.append((a, b, "braking", e))
    items.sort(key=lambda x: x[0])
    groups: list[list[tuple[int, int, str, Any]]] = []
    for item in items:
        if groups and item[0] - max(x[1] for x in groups[-1]) <= config.drag_merge_gap_s:
            groups[-1].append(item)
        else:
            groups.append([item])
    out = []
    for group in groups:
        a = min(x[0] for x in group)
        b = max(x[1] for x in group)
        start, end = series.utc(a), series.utc(b)
        windows = [x[3] for x in group if x[2] == "window"]
        brakings = [x[3] for x in group if x[2] == "braking"]
        parts = []
        excess = 0.0
        if windows:
            dm = sum(w.m_end - w.m_start for w in windows)
            dp = sum(w.p_end - w.p_start for w in windows)
            excess += dm - dp
            seconds = sum(w.stop - w.start for w in windows)
            speed = sum(w.speed_kmh * (w.stop - w.start) for w in windows) / seconds
            pressure = max(w.pressure_max_bar for w in windows)
            w0, w1 = series.utc(windows[0].start), series.utc(windows[-1].stop)
            model = f"cooling by {-dp:.1f} K" if dp < 0 else f"a rise of only {dp:.1f} K"
            parts.append(
                f"heated {dm:.1f} K {_when(w0, w1)} ({_duration(seconds)} at {speed:.0f} km/h "
                f"on average) with at most {pressure:.2f} bar in the brake cylinder; the model "
                f"predicts {model}"
            )
        if brakings:
            extra = [e.m_rise - e.p_rise for e in brakings]
            excess += sum(extra)
            worst = max(brakings, key=lambda e: e.m_rise - e.p_rise)
            what = (
                f"{worst.m_rise:.1f} K in the braking {_at(worst.start_utc)} "
                f"({_speeds(worst.v_start_kmh, worst.v_end_kmh)} with up to "
                f"{worst.p_max_bar:.2f} bar) where {worst.p_rise:.1f} K were predicted"
            )
            if len(brakings) > 1:
                what = (
                    f"{sum(extra):.1f} K more than predicted in {len(brakings)} brakings, "
                    f"the most {what}"
                )
            parts.append(f"{'and it heated' if windows else 'heated'} {what}")
        severity = "alarm" if excess >= config.drag_alarm_excess_k else "warning"
        event_id = brakings[0].event_id if (len(brakings) == 1 and not windows) else None
        out.append(
            Finding(
                "dragging_brake",
                severity,
                start,
                end,
                f"Block of {series.wagon_id} {'; '.join(parts)}: check for a dragging brake "
                "(handbrake left on, stuck distributor or release valve, binding rigging).",
                event_id=event_id,
                detail="no_pressure" if windows else "braking",
            )
        )
    return out


def find_overheating(
    wagon_id: str, stats: Sequence[EventStat], config: FlagConfig = FlagConfig()
) -> list[Finding]:
    """Brakings whose predicted contact maximum exceeds ``contact_limit_c``; severity by the
    margin."""
    out = []
    for e in stats:
        over = e.contact_max_c - config.contact_limit_c
        if over <= 0:
            continue
        if over >= config.overheat_alarm_margin_k:
            severity = "alarm"
        elif over >= config.overheat_warning_margin_k:
            severity = "warning"
        else:
            severity = "info"
        out.append(
            Finding(
                "overheating",
                severity,
                e.start_utc,
                e.window_end_utc,
                f"Predicted wheel–block contact temperature of {wagon_id} reached "
                f"{e.contact_max_c:.0f} °C {_at(e.contact_max_utc)}, {over:.0f} K over the "
                f"{config.contact_limit_c:.0f} °C limit, in the braking "
                f"{_speeds(e.v_start_kmh, e.v_end_kmh)} with up to {e.p_max_bar:.2f} bar: "
                "inspect the wheel treads and blocks for hot spots, cracks and metal pick-up.",
                event_id=e.event_id,
            )
        )
    return out


def merge_sensor_faults(
    findings: Sequence[Finding], config: FlagConfig = FlagConfig()
) -> list[Finding]:
    """Sensor faults that overlap or follow each other within ``fault_merge_gap_s`` are one
    flag: the first one's evidence, the others summed up after it (a loose sensor that ends
    up reading a constant air temperature is one fault, not a loose one and six frozen)."""
    faults = sorted(
        (f for f in findings if f.kind == "sensor_fault"), key=lambda f: (f.start_utc, f.end_utc)
    )
    others = [f for f in findings if f.kind != "sensor_fault"]
    gap = dt.timedelta(seconds=config.fault_merge_gap_s)
    groups: list[list[Finding]] = []
    for f in faults:
        if groups and f.start_utc <= max(g.end_utc for g in groups[-1]) + gap:
            groups[-1].append(f)
        else:
            groups.append([f])
    merged = []
    for group in groups:
        head = group[0]
        if len(group) == 1:
            merged.append(head)
            continue
        end = max(f.end_utc for f in group)
        by_detail: dict[str, list[Finding]] = {}
        for f in group[1:]:
            by_detail.setdefault(f.detail or "faulty", []).append(f)
        parts = []
        for detail, items in by_detail.items():
            if len(items) == 1:
                parts.append(items[0].summary or detail)
            else:
                seconds = sum((f.end_utc - f.start_utc).total_seconds() for f in items)
                parts.append(
                    f"{detail.replace('_', ' ')} {len(items)} times ({_duration(seconds)})"
                )
        seconds = (end - head.start_utc).total_seconds()
        rank = {name: k for k, name in enumerate(SEVERITIES)}
        severity = max(
            [_severity_by_duration(seconds, config), *(f.severity for f in group)],
            key=rank.__getitem__,
        )
        merged.append(
            dataclasses.replace(
                head,
                end_utc=end,
                severity=severity,
                evidence=f"{head.evidence} Until {end:%Y-%m-%d %H:%M:%S} UTC its reading was "
                f"also {'; '.join(parts)}.",
            )
        )
    return merged + others


# --------------------------------------------------------------------------------------------
# One wagon, the warehouse


def _spans_utc(series: WagonSeries, mask: BoolArray) -> list[tuple[dt.datetime, dt.datetime]]:
    return [(series.utc(a), series.utc(b)) for a, b in _runs(mask)]


def _mask_of(series: WagonSeries, findings: Iterable[Finding]) -> BoolArray:
    mask = np.zeros(series.n, dtype=bool)
    for f in findings:
        a = max(int((f.start_utc - series.t0).total_seconds()), 0)
        b = min(int((f.end_utc - series.t0).total_seconds()), series.n)
        mask[a:b] = True
    return mask


@dataclass
class _SpanVerdict:
    series: WagonSeries
    findings: list[Finding]
    segments: list[Segment]
    """Segments with every sensor fault left out (for the brakes)."""
    faults: list[tuple[int, int]]
    unsure: BoolArray


def _judge_span(
    series: WagonSeries,
    wagon: WagonConfig,
    rom: Any,
    effects: EffectSet,
    config: FlagConfig,
) -> _SpanVerdict:
    """Steps 1-3 of the module docstring on one span: the sensor faults, and the segments of
    the watch simulation for the brakes."""
    findings = find_out_of_range(series, config) + find_dropouts(series, config)
    # out of range or missing: no readings; unchanged runs: left out of the anchoring
    # whatever their verdict
    broken = _mask_of(series, findings)
    frozen_runs = np.zeros(series.n, dtype=bool)
    for a, b, _ in _constant_runs(series.measured_c, config):
        frozen_runs[a:b] = True
    watch = watch_simulation(series, wagon, rom, effects, config, invalid=broken | frozen_runs)
    findings += find_frozen(series, config, watch.predicted_c)
    # loose and drifting against the model, frozen readings included (a loose sensor may end
    # up reading a constant air temperature: that is still reading the air)
    segments = segment_stats(
        series,
        watch.predicted_c,
        watch.bounds,
        watch.kinds,
        config,
        unsure=watch.unsure,
        invalid=broken,
    )
    loose = find_loose(series, segments, config, watch.predicted_c)
    loose_mask = _mask_of(series, loose)
    rest = [s for s in segments if not loose_mask[s.start : s.stop].any()]
    drift = find_drift(series, heat_flow_corrected(rest, config), config)
    findings = merge_sensor_faults([*findings, *loose, *drift], config)
    fault_mask = _mask_of(series, findings)
    segments = segment_stats(
        series,
        watch.predicted_c,
        watch.bounds,
        watch.kinds,
        config,
        unsure=watch.unsure,
        invalid=fault_mask | frozen_runs,
    )
    return _SpanVerdict(series, findings, segments, _runs(fault_mask), watch.unsure)


def judge_wagon(
    spans: WagonSeries | Sequence[WagonSeries],
    *,
    wagon: WagonConfig | None,
    rom: Any = None,
    effects: EffectSet = EffectSet(),  # noqa: B008
    predictions: pl.DataFrame | None = None,
    events: pl.DataFrame | None = None,
    config: FlagConfig = FlagConfig(),
) -> list[Finding]:
    """Every finding of one wagon (the steps of the module docstring), from its series (one
    per span of data, see :meth:`WagonSeries.spans_from_frame`), the revision's
    ``predictions`` of its brakings and its ``events``. Without ``wagon`` (no registry entry)
    or ``rom`` only the readings are judged (out of range, dropouts, frozen by their
    scatter)."""
    spans = [spans] if isinstance(spans, WagonSeries) else list(spans)
    if wagon is None or rom is None:
        out: list[Finding] = []
        for series in spans:
            found = find_out_of_range(series, config) + find_dropouts(series, config)
            out += merge_sensor_faults(found + find_frozen(series, config), config)
        return out
    verdicts = [_judge_span(series, wagon, rom, effects, config) for series in spans]
    findings = [f for v in verdicts for f in v.findings]
    stats: list[EventStat] = []
    if predictions is not None and events is not None and predictions.height:
        excluded = [(v.series.utc(a), v.series.utc(b)) for v in verdicts for a, b in v.faults]
        unsure = [span for v in verdicts for span in _spans_utc(v.series, v.unsure)]
        stats = event_stats(predictions, events, config, excluded=excluded, unsure=unsure)
    findings += find_weak(spans[0].wagon_id, stats, config)
    for v in verdicts:
        t0, t1 = v.series.t0, v.series.utc(v.series.n)
        own = [e for e in stats if t0 <= e.start_utc < t1]
        findings += find_dragging(v.series, v.segments, own, config, excluded=v.faults)
    findings += find_overheating(spans[0].wagon_id, stats, config)
    return findings


def _utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(tzinfo=None)


def _flag_ids(wagon_id: str, findings: Sequence[Finding]) -> list[Flag]:
    taken: set[str] = set()
    flags = []
    for f in sorted(findings, key=lambda f: (f.start_utc, f.kind, f.end_utc, f.evidence)):
        base = f"{f.kind}-{wagon_id}-{f.start_utc:%Y%m%dT%H%M%S}"
        flag_id, k = base, 1
        while flag_id in taken:
            k += 1
            flag_id = f"{base}-{k}"
        taken.add(flag_id)
        flags.append(
            Flag(
                flag_id=flag_id,
                wagon_id=wagon_id,
                event_id=f.event_id,
                kind=f.kind,
                severity=f.severity,
                start_utc=f.start_utc,
                end_utc=f.end_utc,
                evidence=f.evidence,
                detail=f.detail,
            )
        )
    return flags


def _load_series(
    wh: Warehouse, wagon_id: str, ambient_default_c: float, config: FlagConfig
) -> list[WagonSeries]:
    samples = wh.con.sql(
        "SELECT time_utc, speed_kmh, brake_pressure_bar, block_temp_c, block_temp_fault, "
        "block_temp_raw_c, ambient_temp_c FROM samples WHERE wagon_id = $wagon "
        "ORDER BY time_utc, file_id",
        params={"wagon": wagon_id},
    ).pl()
    if samples.height == 0:
        return []
    events = wh.con.sql(
        "SELECT event_id, start_utc, end_utc, complete FROM events WHERE wagon_id = $wagon "
        "ORDER BY start_utc",
        params={"wagon": wagon_id},
    ).pl()
    return WagonSeries.spans_from_frame(
        wagon_id,
        samples,
        ambient_default_c=ambient_default_c,
        events=events,
        bridge_max_s=config.bridge_max_s,
    )


def raise_flags(
    wh: Warehouse,
    registry: Registry | Mapping[str, WagonConfig],
    revision_name: str,
    config: FlagConfig = FlagConfig(),
    *,
    wagons: Iterable[str] | None = None,
    refinement: float | None = None,
    rom_for: Callable[[WagonConfig], Any] | None = None,
) -> FlagReport:
    """Recompute the flags of ``wagons`` (default: every wagon with samples) from their
    samples, events and the predictions of ``revision_name``, and replace their rows of
    ``flags`` in one transaction. A wagon without a registry entry is judged on its readings
    only.

    The watch simulation uses ``rom_for(wagon)`` if given, else the wagon's reduced model at
    ``refinement`` (None: ``$FLEETBRAKE_REFINEMENT`` or 1.0, as the pipeline's); it should be
    the model the revision's predictions were made with."""
    from fleetbrake.model.rom import ReducedModel
    from fleetbrake.simulation.predictions import revision

    effects = revision(wh, revision_name).effects
    if isinstance(registry, Registry):
        wagons_by_id: Mapping[str, WagonConfig] = registry.wagons
        default_ambient_c = float(registry.defaults["ambient_temp_c"])
    else:  # the entries a run stored (pipeline.stored_wagons)
        wagons_by_id = registry
        default_ambient_c = WagonConfig(wagon_id="-").ambient_temp_c
    if wagons is None:
        wanted = [
            r[0]
            for r in wh.con.execute(
                "SELECT DISTINCT wagon_id FROM samples ORDER BY wagon_id"
            ).fetchall()
        ]
    else:
        wanted = sorted(set(wagons))
    report = FlagReport(wagons=wanted)
    roms: dict[tuple[Any, ...], Any] = {}
    new: list[Flag] = []
    for wagon_id in wanted:
        wagon = wagons_by_id.get(wagon_id)
        ambient = float(wagon.ambient_temp_c if wagon else default_ambient_c)
        series = _load_series(wh, wagon_id, ambient, config)
        if not series:
            continue
        rom = None
        predictions = events = None
        if wagon is None:
            report.notes.append(
                f"wagon {wagon_id}: no valid registry entry; only its readings were judged"
            )
        else:
            key = (wagon.geometry, wagon.block, wagon.sensor_point_m)
            if key not in roms:
                roms[key] = (
                    rom_for(wagon)
                    if rom_for is not None
                    else ReducedModel.for_wagon(wagon, refinement=refinement)
                )
            rom = roms[key]
            predictions = wh.con.sql(
                "SELECT event_id, time_utc, phase, measured_sensor_c, predicted_sensor_c, "
                "predicted_contact_max_c, speed_kmh, brake_pressure_bar FROM predictions "
                "WHERE wagon_id = $wagon AND model_revision = $rev ORDER BY event_id, time_utc",
                params={"wagon": wagon_id, "rev": revision_name},
            ).pl()
            events = wh.con.sql(
                "SELECT event_id, start_utc, end_utc, complete FROM events "
                "WHERE wagon_id = $wagon ORDER BY start_utc",
                params={"wagon": wagon_id},
            ).pl()
            if predictions.height == 0 and events.height:
                report.notes.append(
                    f"wagon {wagon_id}: no predictions of revision {revision_name}; brakings "
                    "not judged for weak brakes, dragging in brakings or overheating"
                )
        findings = judge_wagon(
            series,
            wagon=wagon,
            rom=rom,
            effects=effects,
            predictions=predictions,
            events=events,
            config=config,
        )
        new += _flag_ids(wagon_id, findings)
    _store(wh, report.wagons, new)
    report.flags = new
    return report


def _store(wh: Warehouse, wagons: Sequence[str], flags: Sequence[Flag]) -> None:
    """Replace the flags of ``wagons`` in one transaction; a flag identical to a stored one
    keeps its ``detected_utc``."""
    con = wh.con
    wagon_list = pl.DataFrame({"wagon_id": pl.Series(list(wagons), dtype=pl.String)})
    now = _utc_now()
    con.execute("BEGIN TRANSACTION")
    try:
        con.register("fb_wagons", wagon_list)
        old = con.sql(
            "SELECT flag_id, event_id, kind, severity, start_utc, end_utc, evidence, "
            "detected_utc FROM flags WHERE wagon_id IN (SELECT wagon_id FROM fb_wagons)"
        ).fetchall()
        kept = {(r[0], r[1], r[2], r[3], r[4], r[5], r[6]): r[7] for r in old}
        con.execute("DELETE FROM flags WHERE wagon_id IN (SELECT wagon_id FROM fb_wagons)")
        con.unregister("fb_wagons")
        if flags:
            rows = pl.DataFrame(
                {
                    "flag_id": [f.flag_id for f in flags],
                    "wagon_id": [f.wagon_id for f in flags],
                    "event_id": pl.Series([f.event_id for f in flags], dtype=pl.String),
                    "kind": [f.kind for f in flags],
                    "severity": [f.severity for f in flags],
                    "start_utc": pl.Series([f.start_utc for f in flags], dtype=pl.Datetime("us")),
                    "end_utc": pl.Series([f.end_utc for f in flags], dtype=pl.Datetime("us")),
                    "evidence": [f.evidence for f in flags],
                    "detected_utc": pl.Series(
                        [
                            kept.get(
                                (
                                    f.flag_id,
                                    f.event_id,
                                    f.kind,
                                    f.severity,
                                    f.start_utc,
                                    f.end_utc,
                                    f.evidence,
                                ),
                                now,
                            )
                            for f in flags
                        ],
                        dtype=pl.Datetime("us"),
                    ),
                }
            )
            con.register("fb_flags", rows)
            con.execute(
                "INSERT INTO flags (flag_id, wagon_id, event_id, kind, severity, start_utc, "
                "end_utc, evidence, detected_utc) SELECT flag_id, wagon_id, event_id, kind, "
                "severity, start_utc, end_utc, evidence, detected_utc FROM fb_flags"
            )
            con.unregister("fb_flags")
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise
