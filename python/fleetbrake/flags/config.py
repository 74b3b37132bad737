"""The flags' configuration: every threshold a detector uses, named, with its unit, and the
TOML file a fleet engineer sets them in (``fleetbrake run --flag-config FILE``).

::

    from fleetbrake.flags.config import FlagConfig, load_flag_config

    config = load_flag_config("flags.toml")     # the defaults, with the keys the file sets
    config = FlagConfig(contact_limit_c=380.0)  # or in code

``docs/flags.md`` explains each key, ``docs/configuration.md`` lists them. How the timeline
the detectors judge is cut and anchored is not a flag threshold but the simulation's
(``fleetbrake.simulation.chains.ChainParams``): a file setting one of those keys is refused
with a message naming the field that holds it (:data:`MOVED_KEYS`).
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleetbrake.errors import ConfigError

__all__ = [
    "CONFIG_KEYS",
    "DEFAULT_FLAG_CONFIG",
    "FLAG_KINDS",
    "MOVED_KEYS",
    "SEVERITIES",
    "FlagConfig",
    "FlagConfigError",
    "load_flag_config",
]

FLAG_KINDS: tuple[str, ...] = ("dragging_brake", "weak_brake", "sensor_fault", "overheating")
SEVERITIES: tuple[str, ...] = ("info", "warning", "alarm")


class FlagConfigError(ConfigError):
    """A flag configuration file that cannot be used; the message names the file and key."""


@dataclass(frozen=True)
class FlagConfig:
    """Every threshold of the flags, its unit in its name. ``docs/flags.md`` explains each.

    A TOML file for :func:`load_flag_config` sets any of these by name, at the top level::

        contact_limit_c = 380.0
        weak_ratio = 0.7

    Read by: ``fleetbrake run``, ``fleetbrake watch``, ``fleetbrake demo``.
    """

    # ---- data handling (all kinds)
    p_quiet_bar: float = 0.05
    """Cylinder pressure at or below which the brake counts as released (the events'
    baseline)."""
    min_segment_s: int = 120
    """A segment shorter than this is simulated but not judged."""
    edge_s: int = 30
    """The readings averaged at each end of a segment for its start and end values."""
    settle_s: int = 900
    """After a data gap in which the wagon may have braked, or a braking with frozen GPS
    speed, segments and brakings starting within this are not judged (the simulated block is
    unsure)."""
    gap_moving_speed_kmh: float = 5.0
    """A data gap longer than the simulation's ``max_gap_s`` whose rows on either side
    show the wagon faster than this (or braking) may hide brakings: the block is unsure for
    ``settle_s`` after it (below it the wagon stood, and nothing heated the block)."""
    speed_frozen_s: int = 10
    """GPS speed repeating one value at least this long while moving is frozen (a braking
    over it has an unknown heat input) ..."""
    speed_frozen_min_kmh: float = 1.0
    """... moving meaning faster than this (a standing wagon's speed repeats anyway)."""
    smooth_s: int = 15
    """The measured peak of a braking is taken after a running mean over this many seconds."""

    # ---- sensor_fault
    fault_merge_gap_s: int = 600
    """Sensor faults of one wagon closer than this are one flag (out-of-range runs closer
    than this are one run)."""
    frozen_min_s: int = 120
    """A reading unchanged at least this long may be frozen."""
    frozen_resolution_k: float = 0.01
    """Readings differing by less than this count as unchanged (the logging resolution)."""
    frozen_min_change_k: float = 0.5
    """... it is frozen if the model predicts a change of at least this meanwhile, ..."""
    frozen_noise_k: float = 0.03
    """... or if the same sensor's noise around the run (estimated from the median
    reading-to-reading difference) is at least this: a live reading would have moved ..."""
    frozen_noise_window_s: int = 3600
    """... that noise taken from the readings within this on either side of the run ..."""
    frozen_noise_min_pairs: int = 60
    """... and only from at least this many pairs of consecutive valid readings there."""
    dropout_min_s: int = 60
    """Readings missing at least this long, in rows that have their other values, are a
    dropout."""
    loose_min_contrast_k: float = 3.0
    """A quiet window is judged for a loose sensor if the reading starts at least this far
    above the air."""
    loose_min_drop_k: float = 2.0
    """... and falls by at least this, and by this much more than the model says the block
    cools, ..."""
    loose_min_fraction: float = 0.3
    """... covering this much more of the way to the air than the block does (0-1)."""
    loose_min_predicted_rise_k: float = 2.0
    """A braking tells a loose sensor (one not rising in it) from a sound one only when the
    model predicts a rise of at least this (and ``weak_min_predicted_rise_k``) in it: smaller
    rises are lost in the noise and the sensor's own lag."""
    loose_ambient_k: float = 3.0
    """A reading within this of the air reads the air (a loose sensor's, after a while)."""
    detached_ratio: float = 0.25
    """A braking whose measured rise is below this share of the predicted one while the
    reading is at the air temperature shows a sensor not touching the block."""
    responsive_ratio: float = 0.5
    """A braking whose measured rise is at least this share of the predicted one shows a
    sensor in contact (a loose-sensor flag ends before it)."""
    drift_min_rate_k_per_h: float = 2.0
    """A quiet window whose measured - predicted changes at least this fast, steadily,
    may be drifting ..."""
    drift_max_rate_k_per_h: float = 30.0
    """... up to this (faster is not a calibration drift)."""
    drift_max_rms_k: float = 0.3
    """... when measured - predicted stays within this (rms) of a straight line."""
    drift_min_windows: int = 3
    """Consecutive drifting segments (of one sign, at least one a quiet window) needed for a
    flag ..."""
    drift_min_duration_s: int = 1500
    """... spanning at least this, ..."""
    drift_min_change_k: float = 1.5
    """... adding up to at least this, with at least one window starting ``settle_after_
    braking_s`` after the last release (the block has settled: no braking explains it)."""
    drift_heat_flow_ratio: float = 0.35
    """A run whose rates a rate proportional to the block's excess over the air fits with
    less than this share of the squared error of a constant rate is a heat flow the model has
    wrong (convection, conduction), not a drift (0-1)."""
    drift_heat_flow_min_spread: float = 2.0
    """... a test made only when the block's excess over the air within the run varies by at
    least this factor (over a narrower range a constant rate and a proportional one cannot be
    told apart)."""
    heat_flow_min_explained: float = 0.5
    """The heat-flow fit is taken out of the quiet windows' rates only when it explains at
    least this share of their squared rates (0-1) ..."""
    heat_flow_min_windows: int = 12
    """Quiet windows long after a braking needed to fit (and take out) the model's heat-flow
    error of a wagon before drifts are judged (fewer: nothing taken out)."""
    settle_after_braking_s: int = 600
    """A quiet window starting this long after a release has a settled block."""
    sensor_warning_s: int = 60
    """A sensor fault shorter than this is ``info`` (a glitch), longer ``warning`` ..."""
    sensor_alarm_s: int = 3600
    """... and ``alarm`` from this long (the block has gone unwatched that long)."""

    # ---- weak_brake
    weak_ratio: float = 0.75
    """A braking is weak when measured rise / predicted rise is below this ..."""
    weak_min_predicted_rise_k: float = 1.0
    """... and the predicted rise is at least this (smaller ones are not judged)."""
    weak_min_deficit_k: float = 0.3
    """... and falls short of the predicted rise by at least this (raised to
    ``residual_factor`` x the revision's residual spread: a model error no larger than the
    residual is not a weak brake)."""
    weak_alarm_ratio: float = 0.5
    """A weak-brake flag whose brakings' median ratio is below this is ``alarm``, else
    ``warning``."""
    weak_min_events: int = 2
    """Consecutive weak brakings needed for a flag (no normal braking between them)."""
    min_valid_fraction: float = 0.8
    """A braking or window is judged only if at least this share of its readings is valid."""
    rise_start_s: int = 5
    """A braking's measured rise is counted from the mean of the valid readings in its
    first this many seconds (one reading would add its noise to the rise); none valid there:
    the braking is not judged."""

    # ---- dragging_brake
    drag_min_speed_kmh: float = 10.0
    """A quiet window is judged for dragging only at this mean speed or more (a block
    cannot be heated by friction at a standstill)."""
    drag_min_rise_k: float = 1.0
    """The block must heat by at least this over the window, ..."""
    drag_min_excess_k: float = 3.0
    """... and by at least this more than the model, with no cylinder pressure, predicts."""
    drag_unsure_excess_k: float = 10.0
    """Within ``settle_s`` after a data gap in which the wagon may have braked, a window
    needs this much heating beyond the model (an unsure simulation is off by a few kelvin at
    most)."""
    drag_event_ratio: float = 1.5
    """A braking heating more than this times the predicted rise ..."""
    drag_event_excess_k: float = 5.0
    """... and by at least this much more is dragging too."""
    drag_merge_gap_s: int = 1800
    """Dragging windows and brakings closer than this are one flag."""
    drag_alarm_excess_k: float = 15.0
    """A dragging flag whose heating beyond the model adds up to this is ``alarm``, else
    ``warning``."""

    # ---- the estimator's opinion (the virtual sensor, fleetbrake.model.estimator)
    estimator: bool = True
    """Judge the brakes and the sensor on the virtual sensor's estimate too (the unexplained
    heat power and the innovations); false: the timeline's detectors alone."""
    est_drag_min_power_w: float = 60.0
    """A dragging brake is unexplained heat power into the block whose lower 95 % bound
    stays above this ..."""
    est_drag_min_s: int = 300
    """... for at least this long (seconds with the cylinder released, moving faster than
    ``drag_min_speed_kmh``; short interruptions up to ``est_drag_join_s`` are bridged) ..."""
    est_drag_join_s: int = 120
    """... such runs closer than this are one."""
    est_weak_fraction: float = 0.25
    """A braking is weak for the estimator when the unexplained energy over its window is
    below minus this share of the declared braking energy, ..."""
    est_weak_bound_fraction: float = 0.1
    """... and its upper bound (the power's upper 95 % bounds summed over the window) below
    minus this share of it."""
    est_weak_min_kj: float = 50.0
    """Brakings declaring less heat into the block than this are not judged by the
    estimator (their missing heat is lost in the noise)."""
    est_tail_s: int = 300
    """A braking's window for the estimator runs from activation to this long after the
    release (or the next activation): the time the filter takes to see the heat."""
    est_nis_window_s: int = 60
    """The normalised innovations (nu^2 / S) are averaged over windows of this many valid
    readings ..."""
    est_nis_max: float = 25.0
    """... and a window whose mean is above this (after scaling by the revision's residual
    spread) while the unexplained power cannot follow it is a sensor that stopped reading
    the block."""
    est_settle_s: int = 1800
    """The estimator's first seconds of each span (the filter converging from its prior)
    are not judged."""

    # ---- residual scaling
    residual_factor: float = 4.0
    """Thresholds in kelvin of the brake and drift detectors are at least this many times the
    wagon's residual spread for the revision (the median over its brakings of the rms of
    measured - predicted, :func:`fleetbrake.flags.wagon.wagon_residual_spread`): with a model
    no better than that, smaller differences are model error."""

    # ---- overheating
    contact_limit_c: float = 400.0
    """Predicted wheel-block contact maximum above which a braking is overheating
    (see docs/flags.md for where 400 degC comes from)."""
    overheat_warning_margin_k: float = 20.0
    """Over the limit by less than this is ``info``, ..."""
    overheat_alarm_margin_k: float = 100.0
    """... by this or more ``alarm``, in between ``warning``."""

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
            raise FlagConfigError("FlagConfig: " + "; ".join(problems))
        for f in dataclasses.fields(self):
            if f.type == "float":
                object.__setattr__(self, f.name, float(getattr(self, f.name)))

    def key(self) -> str:
        """A stable hash (sha256, hex) of every threshold's name and value: equal for equal
        configurations (a number given as an integer or a real alike), whatever the file or
        call they came from. ``flagged_wagons.config_key`` records it with each wagon's
        flags, so a run with other thresholds judges every wagon again
        (:func:`fleetbrake.flags.storage.stale_wagons`)."""
        content = json.dumps(dataclasses.asdict(self), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(content.encode("utf-8")).hexdigest()

    def scaled(self, residual_spread_k: float | None) -> FlagConfig:
        """These thresholds with those in kelvin that a model error could reach raised to
        ``residual_factor`` x ``residual_spread_k`` (the revision's residual spread; None or
        not finite: unchanged). Drift rates are raised to ``residual_factor`` x the spread
        per hour. A threshold above that stays as it is."""
        if residual_spread_k is None or not math.isfinite(residual_spread_k):
            return self
        floor = self.residual_factor * max(float(residual_spread_k), 0.0)
        raised = {
            name: max(getattr(self, name), floor)
            for name in _RESIDUAL_SCALED
            if getattr(self, name) < floor
        }
        if self.drift_min_rate_k_per_h < floor:
            raised["drift_min_rate_k_per_h"] = min(floor, 0.5 * self.drift_max_rate_k_per_h)
        return dataclasses.replace(self, **raised) if raised else self


_FRACTIONS = {
    "heat_flow_min_explained",
    "loose_min_fraction",
    "drift_heat_flow_ratio",
    "detached_ratio",
    "responsive_ratio",
    "weak_alarm_ratio",
    "min_valid_fraction",
    "est_weak_fraction",
    "est_weak_bound_fraction",
}


_RESIDUAL_SCALED = (
    "weak_min_deficit_k",
    "drag_min_excess_k",
    "drag_event_excess_k",
    "drift_min_change_k",
    "loose_min_drop_k",
    "frozen_min_change_k",
)
"""The thresholds in kelvin :meth:`FlagConfig.scaled` raises with the residual spread."""

_MAY_BE_ZERO = {"p_quiet_bar", "settle_s", "fault_merge_gap_s"}

MOVED_KEYS: dict[str, str] = {
    "max_gap_s": "max_gap_s",
    "bridge_max_s": "bridge_max_s",
    "anchor_s": "anchor_s",
    "window_s": "window_s",
    "after_release_s": "quiet_after_release_s",
}
"""Keys a flag configuration file may not set because they cut and anchor the simulation's
timeline (``fleetbrake.simulation.chains.ChainParams``): key -> its field there."""


def _check_field(name: str, kind: object, value: object) -> str | None:
    """Why ``value`` cannot be field ``name`` (declared type ``kind``), or None."""
    if kind == "bool":
        return None if isinstance(value, bool) else f"must be true or false, got {_shown(value)}"
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


DEFAULT_FLAG_CONFIG = FlagConfig()
"""The defaults (a frozen value, shared)."""

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
        if key in MOVED_KEYS:
            problems.append(
                f"{path}: key {key}: no longer a flag threshold: how the timeline is cut and "
                f"anchored is the simulation's (ChainParams.{MOVED_KEYS[key]}, see "
                "docs/pipeline.md); remove it"
            )
            continue
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
    except FlagConfigError as error:
        message = str(error).removeprefix("FlagConfig: ")
        raise FlagConfigError(f"{path}: {message}") from None
