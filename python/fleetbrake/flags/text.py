"""The words of the flags' evidence: times, durations and signed values as a maintainer reads
them, and the severity of a sensor fault by how long it lasted."""

from __future__ import annotations

import datetime as dt

from fleetbrake.flags.config import FlagConfig

__all__ = [
    "SAME_SPEED_KMH",
    "at_text",
    "clock_text",
    "duration_text",
    "severity_by_duration",
    "signed_text",
    "speeds_text",
    "when_text",
]

SAME_SPEED_KMH = 2.0
"""km/h: a braking whose speed changed by less than this is described at one speed (words
only: no detector uses it)."""


def clock_text(t: dt.datetime) -> str:
    return t.strftime("%H:%M:%S") if t.second else t.strftime("%H:%M")


def when_text(start: dt.datetime, end: dt.datetime) -> str:
    """'on 2024-03-04 between 10:12 and 10:31 UTC' (or with both dates)."""
    if start.date() == end.date():
        return f"on {start:%Y-%m-%d} between {clock_text(start)} and {clock_text(end)} UTC"
    return f"between {start:%Y-%m-%d} {clock_text(start)} and {end:%Y-%m-%d} {clock_text(end)} UTC"


def at_text(t: dt.datetime) -> str:
    return f"on {t:%Y-%m-%d} at {clock_text(t)} UTC"


def duration_text(seconds: float) -> str:
    s = round(seconds)
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s" if s % 60 else f"{s // 60} min"
    return f"{s // 3600} h {(s % 3600) // 60} min"


def signed_text(value: float, unit: str = "K", digits: int = 1) -> str:
    return f"{value:+.{digits}f} {unit}"


def speeds_text(v0: float, v1: float) -> str:
    """'from 92 to 40 km/h', or 'at 92 km/h' when the speed hardly changed."""
    if abs(v0 - v1) < SAME_SPEED_KMH:
        return f"at {0.5 * (v0 + v1):.0f} km/h"
    return f"from {v0:.0f} to {v1:.0f} km/h"


def severity_by_duration(seconds: float, config: FlagConfig) -> str:
    if seconds >= config.sensor_alarm_s:
        return "alarm"
    return "warning" if seconds >= config.sensor_warning_s else "info"
