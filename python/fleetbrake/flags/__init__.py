"""Predictions -> flags: detectors of sensor faults, weak, dragging and overheating brakes,
their configuration, and the flags stored in the warehouse.

The flags read what the simulation stored (the revision's timeline and predictions) and never
simulate. One module per concern: :mod:`~fleetbrake.flags.config` (thresholds, the TOML file),
:mod:`~fleetbrake.flags.series` (what is read of a wagon), :mod:`~fleetbrake.flags.stats`
(what the detectors measure), the detector families :mod:`~fleetbrake.flags.sensor`,
:mod:`~fleetbrake.flags.brakes` and :mod:`~fleetbrake.flags.overheating`, the virtual
sensor's opinion :mod:`~fleetbrake.flags.estimated` (brakes from the unexplained heat power,
sensor faults dated by the innovations), and
:mod:`~fleetbrake.flags.judge` (the stage: :func:`raise_flags`), with
:mod:`~fleetbrake.flags.wagon` (a span judged from its arrays: :func:`judge_wagon`),
:mod:`~fleetbrake.flags.partition` (each span of a wagon's data a partition the parent
reads, :func:`judge_task` a pure function an engine runs) and :mod:`~fleetbrake.flags.storage`
(its flags stored).
"""

from fleetbrake.flags.brakes import find_dragging, find_weak
from fleetbrake.flags.config import (
    CONFIG_KEYS,
    FLAG_KINDS,
    SEVERITIES,
    FlagConfig,
    FlagConfigError,
    load_flag_config,
)
from fleetbrake.flags.estimated import (
    EstimateOnGrid,
    combine_opinions,
    date_sensor_faults,
    declared_heat_w,
    estimate_on_grid,
    find_dragging_estimated,
    find_innovation_faults,
    find_weak_estimated,
)
from fleetbrake.flags.judge import raise_flags
from fleetbrake.flags.overheating import find_overheating
from fleetbrake.flags.partition import FlagOutcome, FlagTask, flag_task, judge_task
from fleetbrake.flags.records import Finding, Flag, FlagReport
from fleetbrake.flags.sensor import (
    find_drift,
    find_dropouts,
    find_frozen,
    find_loose,
    find_out_of_range,
    heat_flow_corrected,
    merge_sensor_faults,
)
from fleetbrake.flags.series import SpanTimeline, load_spans
from fleetbrake.flags.stats import (
    EventStat,
    Segment,
    event_stats,
    same_readings,
    segment_stats,
    unsure_mask,
)
from fleetbrake.flags.storage import flag_ids
from fleetbrake.flags.wagon import judge_wagon, wagon_residual_spread

__all__ = [
    "CONFIG_KEYS",
    "FLAG_KINDS",
    "SEVERITIES",
    "EstimateOnGrid",
    "EventStat",
    "Finding",
    "Flag",
    "FlagConfig",
    "FlagConfigError",
    "FlagOutcome",
    "FlagReport",
    "FlagTask",
    "Segment",
    "SpanTimeline",
    "combine_opinions",
    "date_sensor_faults",
    "declared_heat_w",
    "estimate_on_grid",
    "event_stats",
    "find_dragging",
    "find_dragging_estimated",
    "find_drift",
    "find_dropouts",
    "find_frozen",
    "find_innovation_faults",
    "find_loose",
    "find_out_of_range",
    "find_overheating",
    "find_weak",
    "find_weak_estimated",
    "flag_ids",
    "flag_task",
    "heat_flow_corrected",
    "judge_task",
    "judge_wagon",
    "load_flag_config",
    "load_spans",
    "merge_sensor_faults",
    "raise_flags",
    "same_readings",
    "segment_stats",
    "unsure_mask",
    "wagon_residual_spread",
]
