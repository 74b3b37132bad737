"""The wagon's timeline logged to rerun: one ``log_<thing>()`` per concern (speed, pressure,
temperatures, contact estimate, unexplained power, residual, events, flags, faulty readings,
notes), each taking the recording
stream and the frames of :mod:`fleetbrake.viz.data` and returning how much it logged.

Series are sent with ``send_columns`` (a wagon-day is 86,400 samples); a line is broken
(``Clear``) where its samples are more than :data:`GAP_S` apart. Entity paths:
:mod:`fleetbrake.viz.entities`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import polars as pl
import rerun as rr

from fleetbrake.viz.data import frame_times, frame_values, instant
from fleetbrake.viz.entities import (
    CONTACT_MAX,
    CONTACT_MEAN,
    ESTIMATE_HI,
    ESTIMATE_LO,
    ESTIMATE_MEAN,
    LOG_EVENTS,
    LOG_FAULTY_READINGS,
    LOG_FLAGS,
    LOG_NOTES,
    MEASURED,
    POWER,
    POWER_HI,
    POWER_LO,
    PREDICTED,
    PRESSURE,
    RESIDUAL,
    SPEED,
    STATE_EVENTS,
    STATE_FAULTY_READINGS,
    STATE_FLAGS,
    Floats,
    Times,
    time_index,
)

__all__ = [
    "GAP_S",
    "LEVELS",
    "log_contact_estimate",
    "log_events",
    "log_faulty_readings",
    "log_flags",
    "log_notes",
    "log_pressure",
    "log_residual",
    "log_speed",
    "log_temperatures",
    "log_unexplained_power",
]

GAP_S = 10.0
"""Samples further apart than this are not joined by a line (a data gap, or between events)."""

LEVELS = {"alarm": "ERROR", "warning": "WARN", "info": "INFO"}
"""Text log level of a flag by its severity."""
_SEVERITY_RANK = {"info": 1, "warning": 2, "alarm": 3}

_EVENT_KIND_COLORS = {"stop": (230, 80, 60), "slowdown": (240, 170, 40), "drag": (170, 60, 200)}
_SEVERITY_COLORS = {"info": (90, 150, 230), "warning": (240, 170, 40), "alarm": (220, 40, 40)}


# --------------------------------------------------------------------------------------------
# Sending columns.


def _style(
    rec: rr.RecordingStream, path: str, name: str, color: Sequence[int], width: float = 1.5
) -> None:
    rec.log(path, rr.SeriesLines(names=name, colors=[color], widths=width), static=True)


def _send_series(rec: rr.RecordingStream, path: str, times: Times, values: Floats) -> int:
    """Send the finite values as one column, and a ``Clear`` after every gap > GAP_S (which
    rerun's plots draw as a hole in the line). Returns the number of values sent."""
    keep = np.isfinite(values)
    times, values = times[keep], values[keep]
    if times.size == 0:
        return 0
    rec.send_columns(
        path, indexes=time_index(times), columns=rr.Scalars.columns(scalars=values), strict=True
    )
    gap = np.timedelta64(int(GAP_S * 1e9), "ns")
    after = np.flatnonzero(np.diff(times) > gap)
    if after.size:
        holes = times[after] + np.timedelta64(1, "s")
        rec.send_columns(
            path,
            indexes=time_index(holes),
            columns=rr.Clear.columns(is_recursive=[False] * int(after.size)),
            strict=True,
        )
    return int(times.size)


def _send_text(
    rec: rr.RecordingStream, path: str, rows: list[tuple[np.datetime64, str, str]]
) -> int:
    """Send (time, level, text) rows as one ``TextLog`` column, in time order."""
    if not rows:
        return 0
    rows = sorted(rows, key=lambda r: r[0])
    times = np.array([r[0] for r in rows], dtype="datetime64[ns]")
    rec.send_columns(
        path,
        indexes=time_index(times),
        columns=rr.TextLog.columns(text=[r[2] for r in rows], level=[r[1] for r in rows]),
        strict=True,
    )
    return len(rows)


def _send_states(
    rec: rr.RecordingStream, path: str, changes: list[tuple[np.datetime64, int, str]]
) -> None:
    """Send (time, order, state) changes as one ``StateChange`` column; "" ends a state."""
    if not changes:
        return
    changes = sorted(changes, key=lambda c: (c[0], c[1]))
    times = np.array([c[0] for c in changes], dtype="datetime64[ns]")
    rec.send_columns(
        path,
        indexes=time_index(times),
        columns=rr.StateChange.columns(state=[c[2] for c in changes]),
        strict=True,
    )


def _fmt(value: Any, unit: str, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f} {unit}"


def _hms(value: Any) -> str:
    return str(np.datetime64(value, "s")).replace("T", " ") + "Z"


# --------------------------------------------------------------------------------------------
# One function per concern.


def log_speed(rec: rr.RecordingStream, samples: pl.DataFrame) -> int:
    """The samples' speed, km/h. Returns the number of values logged."""
    _style(rec, SPEED, "speed (km/h)", (80, 160, 240))
    if samples.height == 0:
        return 0
    return _send_series(rec, SPEED, frame_times(samples), frame_values(samples, "speed_kmh"))


def log_pressure(rec: rr.RecordingStream, samples: pl.DataFrame) -> int:
    """The samples' brake cylinder pressure, bar. Returns the number of values logged."""
    _style(rec, PRESSURE, "brake pressure (bar)", (90, 200, 120))
    if samples.height == 0:
        return 0
    return _send_series(
        rec, PRESSURE, frame_times(samples), frame_values(samples, "brake_pressure_bar")
    )


def log_temperatures(
    rec: rr.RecordingStream, samples: pl.DataFrame, predictions: pl.DataFrame
) -> dict[str, int]:
    """Measured sensor temperature (valid readings only: a faulty reading is a broken wire,
    not a temperature) and the predicted sensor, contact mean and contact max temperatures.
    Returns the number of values logged per entity path."""
    _style(rec, MEASURED, "measured sensor (°C)", (235, 235, 235))
    _style(rec, PREDICTED, "predicted sensor (°C)", (255, 150, 40))
    _style(rec, CONTACT_MEAN, "predicted contact mean (°C)", (240, 80, 80))
    _style(rec, CONTACT_MAX, "predicted contact max (°C)", (170, 30, 60))
    counts = {MEASURED: 0, PREDICTED: 0, CONTACT_MEAN: 0, CONTACT_MAX: 0}
    if samples.height:
        valid = samples.filter(~pl.col("block_temp_fault"))
        counts[MEASURED] = _send_series(
            rec, MEASURED, frame_times(valid), frame_values(valid, "block_temp_c")
        )
    if predictions.height:
        times = frame_times(predictions)
        for path, column in (
            (PREDICTED, "predicted_sensor_c"),
            (CONTACT_MEAN, "predicted_contact_mean_c"),
            (CONTACT_MAX, "predicted_contact_max_c"),
        ):
            counts[path] = _send_series(rec, path, times, frame_values(predictions, column))
    return counts


_ESTIMATE_COLOR = (60, 200, 220)
_POWER_COLOR = (250, 210, 60)
_BAND_WIDTH = 0.6
"""The 95 % bounds are drawn as thin lines of their estimate's colour (rerun's plots have no
filled band)."""


def _send_band(
    rec: rr.RecordingStream,
    estimates: pl.DataFrame,
    lines: Sequence[tuple[str, str, str, Sequence[int], float]],
) -> dict[str, int]:
    """Each (path, column, name, colour, width) of ``estimates`` as a styled series."""
    counts = dict.fromkeys((path for path, *_ in lines), 0)
    for path, _, name, color, width in lines:
        _style(rec, path, name, color, width)
    if estimates.height == 0:
        return counts
    times = frame_times(estimates)
    for path, column, *_ in lines:
        counts[path] = _send_series(rec, path, times, frame_values(estimates, column))
    return counts


def log_contact_estimate(rec: rr.RecordingStream, estimates: pl.DataFrame) -> dict[str, int]:
    """The virtual sensor's filtered estimate of the friction-face mean temperature
    (``v_contact_estimates.contact_mean_c``: the model and the reading together) and its
    95 % bounds, beside the open-loop prediction of :func:`log_temperatures`. Returns the
    number of values logged per entity path."""
    return _send_band(
        rec,
        estimates,
        [
            (ESTIMATE_MEAN, "contact_mean_c", "estimated contact mean (°C)", _ESTIMATE_COLOR, 1.5),
            (
                ESTIMATE_LO,
                "contact_mean_lo_c",
                "estimate, 95 % low (°C)",
                _ESTIMATE_COLOR,
                _BAND_WIDTH,
            ),
            (
                ESTIMATE_HI,
                "contact_mean_hi_c",
                "estimate, 95 % high (°C)",
                _ESTIMATE_COLOR,
                _BAND_WIDTH,
            ),
        ],
    )


def log_unexplained_power(rec: rr.RecordingStream, estimates: pl.DataFrame) -> dict[str, int]:
    """The heat power on the friction face that the declared inputs do not explain
    (``unexplained_power_w``: a dragging brake heats with the cylinder released, a weak brake
    heats less than declared) and its 95 % bounds, W, on their own plot. Returns the number of
    values logged per entity path."""
    return _send_band(
        rec,
        estimates,
        [
            (POWER, "unexplained_power_w", "unexplained power (W)", _POWER_COLOR, 1.5),
            (POWER_LO, "unexplained_power_lo_w", "95 % low (W)", _POWER_COLOR, _BAND_WIDTH),
            (POWER_HI, "unexplained_power_hi_w", "95 % high (W)", _POWER_COLOR, _BAND_WIDTH),
        ],
    )


def log_residual(rec: rr.RecordingStream, predictions: pl.DataFrame) -> int:
    """Measured minus predicted sensor temperature (K), where the reading is valid."""
    _style(rec, RESIDUAL, "measured - predicted sensor (K)", (200, 120, 230))
    if predictions.height == 0:
        return 0
    residual = frame_values(predictions, "measured_sensor_c") - frame_values(
        predictions, "predicted_sensor_c"
    )
    return _send_series(rec, RESIDUAL, frame_times(predictions), residual)


def log_events(rec: rr.RecordingStream, events: pl.DataFrame) -> int:
    """Each event as a range (``state/events``, state: its kind) and a text log at its start
    (with its attributes) and at its end. Returns the number of events."""
    rec.log(
        STATE_EVENTS,
        rr.StateConfiguration(
            values=list(_EVENT_KIND_COLORS), colors=list(_EVENT_KIND_COLORS.values())
        ),
        static=True,
    )
    rows: list[tuple[np.datetime64, str, str]] = []
    changes: list[tuple[np.datetime64, int, str]] = []
    for e in events.iter_rows(named=True):
        start, end = instant(e["start_utc"]), instant(e["end_utc"])
        incomplete = "" if e["complete"] else ", incomplete (at a data gap or session edge)"
        rows.append(
            (
                start,
                "INFO",
                f"event {e['event_id']} begins: {e['kind']}{incomplete}; "
                f"{_fmt(e['v_start_kmh'], 'km/h')} -> {_fmt(e['v_end_kmh'], 'km/h')}, "
                f"pressure mean {_fmt(e['p_mean_bar'], 'bar', 2)} "
                f"(max {_fmt(e['p_max_bar'], 'bar', 2)}), {_fmt(e['duration_s'], 's', 0)}, "
                f"{_fmt(e['distance_m'], 'm', 0)}, block {_fmt(e['t_block_start_c'], '°C')} "
                "at activation",
            )
        )
        rows.append(
            (
                end,
                "INFO",
                f"event {e['event_id']} ends (release) after {_fmt(e['duration_s'], 's', 0)}",
            )
        )
        changes.append((end, 0, ""))  # an end at the same instant as a start goes first
        changes.append((start, 1, str(e["kind"])))
    _send_text(rec, LOG_EVENTS, rows)
    _send_states(rec, STATE_EVENTS, changes)
    return events.height


def _flag_lane(flags: list[dict[str, Any]]) -> list[tuple[np.datetime64, int, str]]:
    """State changes of one flag kind: the highest severity among the flags active (a sweep
    over the flags' starts and ends)."""
    deltas: dict[np.datetime64, dict[str, int]] = {}
    for f in flags:
        severity = str(f["severity"])
        for at, step in ((instant(f["start_utc"]), 1), (instant(f["end_utc"]), -1)):
            by_severity = deltas.setdefault(at, {})
            by_severity[severity] = by_severity.get(severity, 0) + step
    active = dict.fromkeys(_SEVERITY_RANK, 0)
    changes: list[tuple[np.datetime64, int, str]] = []
    previous = ""
    for at in sorted(deltas):
        for severity, step in deltas[at].items():
            active[severity] = active.get(severity, 0) + step
        on = [s for s, n in active.items() if n > 0]
        state = max(on, key=lambda s: _SEVERITY_RANK.get(s, 0)) if on else ""
        if state != previous:
            changes.append((at, 0, state))
            previous = state
    return changes


def log_flags(rec: rr.RecordingStream, flags: pl.DataFrame) -> int:
    """Each flag as a text log at its start (level by severity: alarm ERROR, warning WARN,
    info INFO; text: kind, severity, evidence) and at its end, and as a range on
    ``state/flags/<kind>``. Returns the number of flags."""
    if flags.height == 0:
        return 0
    rows: list[tuple[np.datetime64, str, str]] = []
    by_kind: dict[str, list[dict[str, Any]]] = {}
    for f in flags.iter_rows(named=True):
        level = str(LEVELS.get(f["severity"], "INFO"))
        tied = f" (event {f['event_id']})" if f["event_id"] else ""
        rows.append(
            (
                instant(f["start_utc"]),
                level,
                f"{f['kind']} [{f['severity']}] {f['flag_id']}{tied}: {f['evidence']}",
            )
        )
        rows.append(
            (
                instant(f["end_utc"]),
                level,
                f"{f['kind']} [{f['severity']}] {f['flag_id']} ends (began {_hms(f['start_utc'])})",
            )
        )
        by_kind.setdefault(str(f["kind"]), []).append(f)
    _send_text(rec, LOG_FLAGS, rows)
    for kind, kind_flags in by_kind.items():
        path = f"{STATE_FLAGS}/{kind}"
        rec.log(
            path,
            rr.StateConfiguration(
                values=list(_SEVERITY_COLORS), colors=list(_SEVERITY_COLORS.values())
            ),
            static=True,
        )
        _send_states(rec, path, _flag_lane(kind_flags))
    return flags.height


def log_faulty_readings(rec: rr.RecordingStream, samples: pl.DataFrame) -> int:
    """Runs of faulty sensor readings (out of range: a broken wire), which are not drawn as
    temperatures: a range on ``state/faulty_readings`` and a WARN text log per run. Returns the
    number of faulty readings."""
    if samples.height == 0:
        return 0
    fault = samples["block_temp_fault"].to_numpy().astype(bool)
    if not fault.any():
        return 0
    times = frame_times(samples)
    raw = frame_values(samples, "block_temp_raw_c")
    edges = np.diff(np.concatenate(([0], fault.astype(np.int8), [0])))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    rows: list[tuple[np.datetime64, str, str]] = []
    changes: list[tuple[np.datetime64, int, str]] = []
    for a, b in zip(starts, stops, strict=True):
        end = times[b] if b < times.size else times[b - 1] + np.timedelta64(1, "s")
        values = raw[a:b][np.isfinite(raw[a:b])]
        shown = f"raw {values.min():.0f} to {values.max():.0f} °C" if values.size else "raw n/a"
        rows.append(
            (
                times[a],
                "WARN",
                f"sensor reading out of range: {b - a} reading(s) until {_hms(times[b - 1])} "
                f"({shown}); not drawn as temperatures",
            )
        )
        changes.append((times[a], 1, "out of range"))
        changes.append((end, 0, ""))
    _send_text(rec, LOG_FAULTY_READINGS, rows)
    _send_states(rec, STATE_FAULTY_READINGS, changes)
    return int(fault.sum())


def log_notes(
    rec: rr.RecordingStream, at: np.datetime64, notes: Sequence[str], *, level: str = "WARN"
) -> int:
    """Notes on the recording (what it lacks, how the block field was made) as text logs at
    ``at``, the recording's first instant."""
    return _send_text(rec, LOG_NOTES, [(at, level, n) for n in notes])
