"""Rerun recordings of a wagon's timeline, or of one braking event, for incident review.

::

    from fleetbrake.viz.record import record

    summary = record("warehouse/fleet.duckdb", "SGG-0001", "SGG-0001.rrd")   # the timeline
    summary = record(db, "SGG-0001", "incident.rrd", event_id="SGG-0001-20240301T101500")
    summary.notes    # what the recording lacks and why (no predictions yet, ...)

Open the file with ``rerun FILE.rrd``. The database is only read (``read_only``); every time
is on one timeline, ``time_utc``, a timestamp timeline of real UTC time. Entities:

- ``wagon/speed_kmh``, ``wagon/brake_pressure_bar``: the samples (``Scalars``);
- ``wagon/temperature/measured_sensor_c``: the samples' valid sensor readings (a faulty
  reading is a broken wire, not a temperature: it is not drawn);
- ``wagon/temperature/predicted_sensor_c``, ``.../predicted_contact_mean_c``,
  ``.../predicted_contact_max_c``: the predictions of one model revision (sensor seat,
  friction face mean and maximum);
- ``wagon/residual_k``: measured - predicted sensor temperature, kelvin;
- ``state/events``, ``state/flags/<kind>``, ``state/faulty_readings``: ranges
  (``StateChange``): each event (state: its kind), each flag kind (state: the highest
  severity active), each run of faulty readings;
- ``log/events``, ``log/flags``, ``log/faulty_readings``, ``log/notes``: ``TextLog`` at
  each start and end with the attributes (flags: level ERROR, WARN, INFO by severity), and
  notes on the recording (what it lacks, how the block field was made);
- ``block/mesh`` (``--event``): the block's boundary, coloured by its temperature field
  every ~5 s (``Mesh3D``: geometry static, vertex colours on the timeline);
- ``block/sensor`` (``--event``): the sensor seat (``Points3D``).

Series are sent with ``send_columns`` (a wagon-day is 86,400 samples); a line is broken
(``Clear``) where its samples are more than :data:`GAP_S` apart. The blueprint stacks the
temperature, speed, pressure and residual plots, the block beside them for an event, the
state lanes and the text log below.
"""

from __future__ import annotations

import json
import os
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import rerun as rr
import rerun.blueprint as rrb
from numpy.typing import NDArray

from fleetbrake.errors import DatabaseLockedError, FleetbrakeError
from fleetbrake.fleet.registry import RegistryError, WagonConfig, load_registry
from fleetbrake.warehouse.connection import (
    Warehouse,
    WarehouseError,
    WarehouseLockedError,
    open_warehouse,
)

__all__ = [
    "DEFAULT_BLOCK_REFINEMENT",
    "EVENT_LEAD_S",
    "FIELD_EVERY_S",
    "GAP_S",
    "TIMELINE",
    "BlockField",
    "RecordData",
    "RecordError",
    "RecordLockedError",
    "RecordSummary",
    "blueprint",
    "load_record_data",
    "log_block_field",
    "log_events",
    "log_faulty_readings",
    "log_flags",
    "log_notes",
    "log_pressure",
    "log_residual",
    "log_speed",
    "log_temperatures",
    "record",
    "simulate_block_field",
    "wagon_config",
]

TIMELINE = "time_utc"
"""The one timeline of every recording: real UTC time (a rerun timestamp timeline)."""

GAP_S = 10.0
"""Samples further apart than this are not joined by a line (a data gap, or between events)."""

EVENT_LEAD_S = 60.0
"""An event's recording begins this long before activation."""

EVENT_TAIL_S = 600.0
"""Without predictions, an event's recording ends this long after release."""

FIELD_EVERY_S = 5.0
"""Interval between two temperature fields of the block (``--event``)."""

DEFAULT_BLOCK_REFINEMENT = 0.5
"""Mesh of the block pictures: coarse hex8 (about 1,000 nodes), enough for a picture."""

COLORMAP = "inferno"

LEVELS = {"alarm": "ERROR", "warning": "WARN", "info": "INFO"}
"""Text log level of a flag by its severity."""
_SEVERITY_RANK = {"info": 1, "warning": 2, "alarm": 3}

# Entity paths.
SPEED = "wagon/speed_kmh"
PRESSURE = "wagon/brake_pressure_bar"
MEASURED = "wagon/temperature/measured_sensor_c"
PREDICTED = "wagon/temperature/predicted_sensor_c"
CONTACT_MEAN = "wagon/temperature/predicted_contact_mean_c"
CONTACT_MAX = "wagon/temperature/predicted_contact_max_c"
RESIDUAL = "wagon/residual_k"
STATE_EVENTS = "state/events"
STATE_FLAGS = "state/flags"
STATE_FAULTY_READINGS = "state/faulty_readings"
LOG_EVENTS = "log/events"
LOG_FLAGS = "log/flags"
LOG_FAULTY_READINGS = "log/faulty_readings"
LOG_NOTES = "log/notes"
BLOCK = "block"
BLOCK_MESH = "block/mesh"
BLOCK_SENSOR = "block/sensor"

_EVENT_KIND_COLORS = {"stop": (230, 80, 60), "slowdown": (240, 170, 40), "drag": (170, 60, 200)}
_SEVERITY_COLORS = {"info": (90, 150, 230), "warning": (240, 170, 40), "alarm": (220, 40, 40)}

Times = NDArray[np.datetime64]
Floats = NDArray[np.float64]


class RecordError(FleetbrakeError):
    """The recording cannot be made; the message names the database, wagon, event or revision."""


class RecordLockedError(RecordError, DatabaseLockedError):
    """Another process is writing to the database: DuckDB lets no other process open it."""


# --------------------------------------------------------------------------------------------
# What is recorded, from the database.


@dataclass(frozen=True)
class RecordData:
    """Everything a recording shows, read from the warehouse (rows sorted by time)."""

    wagon_id: str
    event: dict[str, Any] | None
    """The event's row of ``events`` when one event is recorded."""
    revision: str | None
    """Model revision of the predictions; ``None`` when the wagon has none."""
    window: tuple[np.datetime64, np.datetime64] | None
    """Time range recorded for one event; ``None`` for the whole timeline."""
    samples: pl.DataFrame
    predictions: pl.DataFrame
    events: pl.DataFrame
    flags: pl.DataFrame
    notes: list[str] = field(default_factory=list)
    stored_wagon: WagonConfig | None = None
    """The wagon's registry entry as the last ``run`` stored it (``wagon_registry``)."""
    stored_wagon_source: str | None = None
    """The ``fleet.toml`` that entry came from."""


# DuckDB 2: ``execute()`` returns the connection (no ``.pl()``) and leaves its result open
# until fetched to the end, so every query here goes through a relation, fully fetched.


def _rows(con: Any, query: str, params: dict[str, Any] | None = None) -> list[tuple[Any, ...]]:
    return con.sql(query, params=params or {}).fetchall()


def _frame(con: Any, query: str, params: dict[str, Any]) -> pl.DataFrame:
    return con.sql(query, params=params).pl()


def _tables(con: Any) -> set[str]:
    return {row[0] for row in _rows(con, "SELECT table_name FROM duckdb_tables()")}


def _listing(names: Sequence[str], limit: int = 12) -> str:
    shown = ", ".join(names[:limit])
    more = len(names) - limit
    return shown + (f", ... ({more} more)" if more > 0 else "") if names else "none"


def _check_wagon(con: Any, tables: set[str], wagon_id: str, db: str) -> None:
    for table in ("samples", "events"):
        query = f"SELECT count(*) FROM {table} WHERE wagon_id = $w"
        if _rows(con, query, {"w": wagon_id})[0][0]:
            return
    if "files" in tables:
        reasons = [
            r[0]
            for r in _rows(
                con,
                "SELECT coalesce(reason, path) FROM files WHERE wagon_id = $w "
                "AND status = 'quarantined' ORDER BY path",
                {"w": wagon_id},
            )
        ]
        if reasons:
            raise RecordError(
                f"{db}: wagon {wagon_id} has no samples: all its files were quarantined "
                f"({len(reasons)}; first: {reasons[0]})"
            )
    known = [
        r[0]
        for r in _rows(
            con,
            "SELECT DISTINCT wagon_id FROM samples UNION SELECT DISTINCT wagon_id FROM events "
            "ORDER BY 1",
        )
    ]
    raise RecordError(
        f"{db}: unknown wagon {wagon_id}: it has no samples and no events there "
        f"(wagons: {_listing(known)})"
    )


def _resolve_revision(
    con: Any, tables: set[str], wagon_id: str, requested: str | None, db: str
) -> tuple[str | None, list[str]]:
    notes: list[str] = []
    revisions: list[str] = []
    current: str | None = None
    if "model_revisions" in tables:
        rows = _rows(
            con, "SELECT model_revision, is_current FROM model_revisions ORDER BY created_utc"
        )
        revisions = [r[0] for r in rows]
        currents = [r[0] for r in rows if r[1]]
        current = currents[-1] if currents else None
    predicted: list[str] = []
    if "predictions" in tables:
        predicted = [
            r[0]
            for r in _rows(
                con,
                "SELECT DISTINCT model_revision FROM predictions WHERE wagon_id = $w ORDER BY 1",
                {"w": wagon_id},
            )
        ]
    if requested is not None:
        if requested not in revisions and requested not in predicted:
            known = sorted(set(revisions) | set(predicted))
            raise RecordError(
                f"{db}: unknown model revision {requested!r} (revisions: {_listing(known)})"
            )
        return requested, notes
    if current is not None:
        return current, notes
    if "declared" in predicted or "declared" in revisions:
        return "declared", notes
    if predicted:
        notes.append(
            f"no current model revision recorded; predictions shown are of {predicted[0]!r}"
        )
        return predicted[0], notes
    return None, notes


def load_record_data(
    wh: Warehouse,
    wagon_id: str,
    *,
    event_id: str | None = None,
    revision: str | None = None,
) -> RecordData:
    """Read what a recording of ``wagon_id`` (or of one of its events) shows.

    ``revision``: the model revision of the predictions; default the current one
    (``model_revisions.is_current``), else ``declared``. Raises :class:`RecordError` naming
    the database and the unknown wagon, event or revision.
    """
    con = wh.con
    db = str(wh.path)
    tables = _tables(con)
    for needed in ("samples", "events"):
        if needed not in tables:
            raise RecordError(f"{db}: not a fleetbrake warehouse (no table {needed})")
    _check_wagon(con, tables, wagon_id, db)
    chosen, notes = _resolve_revision(con, tables, wagon_id, revision, db)

    event: dict[str, Any] | None = None
    window: tuple[np.datetime64, np.datetime64] | None = None
    if event_id is not None:
        found = _frame(con, "SELECT * FROM events WHERE event_id = $e", {"e": event_id})
        if found.height == 0:
            known = [
                r[0]
                for r in _rows(
                    con,
                    "SELECT event_id FROM events WHERE wagon_id = $w ORDER BY start_utc",
                    {"w": wagon_id},
                )
            ]
            raise RecordError(
                f"{db}: unknown event {event_id} (events of wagon {wagon_id}: {_listing(known)})"
            )
        event = found.row(0, named=True)
        if event["wagon_id"] != wagon_id:
            raise RecordError(
                f"{db}: event {event_id} is of wagon {event['wagon_id']}, not of wagon {wagon_id}"
            )
        start = np.datetime64(event["start_utc"], "us")
        end = np.datetime64(event["end_utc"], "us") + np.timedelta64(int(EVENT_TAIL_S), "s")
        if chosen is not None and "predictions" in tables:
            (last,) = _rows(
                con,
                "SELECT max(time_utc) FROM predictions WHERE event_id = $e AND model_revision = $r",
                {"e": event_id, "r": chosen},
            )[0]
            if last is not None:
                end = max(np.datetime64(last, "us"), np.datetime64(event["end_utc"], "us"))
        window = (start - np.timedelta64(int(EVENT_LEAD_S), "s"), end)

    params: dict[str, Any] = {"w": wagon_id}
    in_window = ""  # rows at an instant inside the window
    overlaps = ""  # ranges overlapping the window
    if window is not None:
        params |= {"a": window[0].item(), "b": window[1].item()}
        in_window = " AND time_utc BETWEEN $a AND $b"
        overlaps = " AND end_utc >= $a AND start_utc <= $b"

    samples = _frame(
        con,
        "SELECT time_utc, speed_kmh, brake_pressure_bar, block_temp_c, block_temp_raw_c, "
        "block_temp_fault FROM samples WHERE wagon_id = $w" + in_window + " ORDER BY time_utc",
        params,
    )
    events = _frame(
        con, "SELECT * FROM events WHERE wagon_id = $w" + overlaps + " ORDER BY start_utc", params
    )
    if "flags" in tables:
        flag_params, flag_filter = params, overlaps
        if event_id is not None:  # the event's flags, and the wagon's others in the window
            flag_params = params | {"e": event_id}
            flag_filter = " AND (event_id = $e OR (end_utc >= $a AND start_utc <= $b))"
        flags = _frame(
            con,
            "SELECT flag_id, event_id, kind, severity, start_utc, end_utc, evidence FROM flags "
            "WHERE wagon_id = $w" + flag_filter + " ORDER BY start_utc, flag_id",
            flag_params,
        )
    else:
        flags = pl.DataFrame()
        notes.append("the database has no flags table yet (no `run` has raised flags)")

    predictions = pl.DataFrame()
    if chosen is None or "predictions" not in tables:
        notes.append(
            f"wagon {wagon_id} has no predictions yet (its events were not simulated): "
            "measurements only"
        )
    else:
        predictions = _frame(
            con,
            "SELECT time_utc, event_id, measured_sensor_c, predicted_sensor_c, "
            "predicted_contact_mean_c, predicted_contact_max_c, ambient_c, flux_w_m2 "
            "FROM predictions WHERE wagon_id = $w AND model_revision = $r"
            + in_window
            + " ORDER BY time_utc, event_id",
            params | {"r": chosen},
        )
        if predictions.height == 0:
            what = f"event {event_id}" if event_id is not None else f"wagon {wagon_id}"
            notes.append(
                f"{what} has no predictions of model revision {chosen!r} yet: measurements only"
            )
    if samples.height == 0:
        notes.append(f"wagon {wagon_id} has no samples in the recorded time range")
    stored, source = _stored_wagon(con, tables, wagon_id, notes)
    return RecordData(
        wagon_id=wagon_id,
        event=event,
        revision=chosen,
        window=window,
        samples=samples,
        predictions=predictions,
        events=events,
        flags=flags,
        notes=notes,
        stored_wagon=stored,
        stored_wagon_source=source,
    )


def _stored_wagon(
    con: Any, tables: set[str], wagon_id: str, notes: list[str]
) -> tuple[WagonConfig | None, str | None]:
    """The wagon's entry in ``wagon_registry`` (what the last ``run`` simulated it with)."""
    if "wagon_registry" not in tables:
        return None, None
    rows = _rows(
        con,
        "SELECT config_json, source FROM wagon_registry WHERE wagon_id = $w",
        {"w": wagon_id},
    )
    if not rows:
        return None, None
    try:
        return WagonConfig(**json.loads(rows[0][0])), rows[0][1]
    except (ValueError, TypeError) as error:
        notes.append(f"wagon {wagon_id}: stored registry entry unusable ({error})")
        return None, None


# --------------------------------------------------------------------------------------------
# Logging helpers.


def _times(frame: pl.DataFrame, column: str = "time_utc") -> Times:
    return frame[column].to_numpy().astype("datetime64[ns]")


def _values(frame: pl.DataFrame, column: str) -> Floats:
    return frame[column].cast(pl.Float64).fill_null(float("nan")).to_numpy()


def _index(times: Times) -> list[rr.TimeColumn]:
    return [rr.TimeColumn(TIMELINE, timestamp=times)]


def _style(rec: rr.RecordingStream, path: str, name: str, color: Sequence[int]) -> None:
    rec.log(path, rr.SeriesLines(names=name, colors=[color], widths=1.5), static=True)


def _send_series(rec: rr.RecordingStream, path: str, times: Times, values: Floats) -> int:
    """Send the finite values as one column, and a ``Clear`` after every gap > GAP_S (which
    rerun's plots draw as a hole in the line). Returns the number of values sent."""
    keep = np.isfinite(values)
    times, values = times[keep], values[keep]
    if times.size == 0:
        return 0
    rec.send_columns(
        path, indexes=_index(times), columns=rr.Scalars.columns(scalars=values), strict=True
    )
    gap = np.timedelta64(int(GAP_S * 1e9), "ns")
    after = np.flatnonzero(np.diff(times) > gap)
    if after.size:
        holes = times[after] + np.timedelta64(1, "s")
        rec.send_columns(
            path,
            indexes=_index(holes),
            columns=rr.Clear.columns(is_recursive=np.zeros(after.size, dtype=bool)),
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
        indexes=_index(times),
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
        indexes=_index(times),
        columns=rr.StateChange.columns(state=[c[2] for c in changes]),
        strict=True,
    )


def _fmt(value: Any, unit: str, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f} {unit}"


def _at(value: Any) -> np.datetime64:
    return np.datetime64(value, "ns")


def _hms(value: Any) -> str:
    return str(np.datetime64(value, "s")).replace("T", " ") + "Z"


# --------------------------------------------------------------------------------------------
# One function per concern.


def log_speed(rec: rr.RecordingStream, samples: pl.DataFrame) -> int:
    """The samples' speed, km/h. Returns the number of values logged."""
    _style(rec, SPEED, "speed (km/h)", (80, 160, 240))
    if samples.height == 0:
        return 0
    return _send_series(rec, SPEED, _times(samples), _values(samples, "speed_kmh"))


def log_pressure(rec: rr.RecordingStream, samples: pl.DataFrame) -> int:
    """The samples' brake cylinder pressure, bar. Returns the number of values logged."""
    _style(rec, PRESSURE, "brake pressure (bar)", (90, 200, 120))
    if samples.height == 0:
        return 0
    return _send_series(rec, PRESSURE, _times(samples), _values(samples, "brake_pressure_bar"))


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
            rec, MEASURED, _times(valid), _values(valid, "block_temp_c")
        )
    if predictions.height:
        times = _times(predictions)
        for path, column in (
            (PREDICTED, "predicted_sensor_c"),
            (CONTACT_MEAN, "predicted_contact_mean_c"),
            (CONTACT_MAX, "predicted_contact_max_c"),
        ):
            counts[path] = _send_series(rec, path, times, _values(predictions, column))
    return counts


def log_residual(rec: rr.RecordingStream, predictions: pl.DataFrame) -> int:
    """Measured minus predicted sensor temperature (K), where the reading is valid."""
    _style(rec, RESIDUAL, "measured - predicted sensor (K)", (200, 120, 230))
    if predictions.height == 0:
        return 0
    residual = _values(predictions, "measured_sensor_c") - _values(
        predictions, "predicted_sensor_c"
    )
    return _send_series(rec, RESIDUAL, _times(predictions), residual)


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
        start, end = _at(e["start_utc"]), _at(e["end_utc"])
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
        for at, step in ((_at(f["start_utc"]), 1), (_at(f["end_utc"]), -1)):
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
                _at(f["start_utc"]),
                level,
                f"{f['kind']} [{f['severity']}] {f['flag_id']}{tied}: {f['evidence']}",
            )
        )
        rows.append(
            (
                _at(f["end_utc"]),
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
    times = _times(samples)
    raw = _values(samples, "block_temp_raw_c")
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


# --------------------------------------------------------------------------------------------
# The block's temperature field (one event).


@dataclass(frozen=True)
class BlockField:
    """The block's temperature field through one event, ready to log."""

    nodes_m: Floats
    """(N, 3) node positions, metres (block.py coordinates: wheel axis z, block on +y)."""
    triangles: NDArray[np.int64]
    """(T, 3) boundary triangles, counter-clockwise seen from outside."""
    times: Times
    """(K,) UTC instants of the fields."""
    fields_c: Floats
    """(K, N) nodal temperatures."""
    sensor_m: tuple[float, float, float]
    sensor_c: Floats
    """The full model at the sensor seat, at every second (for the note comparing it with
    the prediction)."""
    range_c: tuple[float, float]
    """The colormap's fixed range: minimum and maximum of the fields over the event."""


def _boundary_triangles(face_sets: dict[str, NDArray[np.int64]]) -> NDArray[np.int64]:
    """Every quad of the face sets (which together cover the boundary), split in two."""
    quads = np.concatenate([faces[:, :4] for faces in face_sets.values()])
    quads = np.unique(quads, axis=0)
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]).astype(np.int64)


def simulate_block_field(
    wagon: WagonConfig,
    predictions: pl.DataFrame,
    *,
    refinement: float = DEFAULT_BLOCK_REFINEMENT,
    field_every_s: float = FIELD_EVERY_S,
) -> BlockField | None:
    """Simulate one event with the full model (hex8, ``refinement``) from the predictions'
    heat input (``flux_w_m2``) and air temperature (``ambient_c``) per second, starting from a
    uniform block at the first predicted sensor temperature. ``None`` if there are fewer than
    two predicted seconds."""
    from fleetbrake.model.thermal import BlockModel

    if predictions.height < 2:
        return None
    times = _times(predictions)
    seconds = (times - times[0]) / np.timedelta64(1, "s")
    grid = np.arange(0.0, float(seconds[-1]) + 0.5, 1.0)
    if grid.size < 2:
        return None
    flux = np.interp(grid, seconds, _values(predictions, "flux_w_m2"))
    ambient = np.interp(grid, seconds, _values(predictions, "ambient_c"))
    initial = float(_values(predictions, "predicted_sensor_c")[0])
    model = BlockModel(
        wagon.geometry,
        wagon.block_material,
        element="hex8",
        refinement=refinement,
        sensor_m=wagon.sensor_point_m,
    )
    every = max(1, round(field_every_s))
    n_steps = grid.size - 1
    # Step n holds on [t_n, t_n+1]: the mean of its two bounding samples (as simulate.py).
    result = model.simulate(
        dt_s=1.0,
        flux_w_m2=0.5 * (flux[:-1] + flux[1:]),
        ambient_c=0.5 * (ambient[:-1] + ambient[1:]),
        initial_c=initial,
        probes_m=[wagon.sensor_point_m],
        field_every=every,
    )
    fields = np.asarray(result.fields_c, dtype=np.float64)
    steps = np.asarray(result.field_steps, dtype=np.int64)
    if steps.size == 0 or steps[-1] != n_steps:
        fields = np.vstack([fields.reshape(-1, model.n_nodes), result.final_c[None, :]])
        steps = np.append(steps, n_steps)
    mesh = model.mesh
    return BlockField(
        nodes_m=np.asarray(mesh.nodes, dtype=np.float64),
        triangles=_boundary_triangles(mesh.face_sets),
        times=times[0] + (steps * 1_000_000_000).astype("timedelta64[ns]"),
        fields_c=fields,
        sensor_m=wagon.sensor_point_m,
        sensor_c=np.asarray(result.probe_c[:, 0], dtype=np.float64),
        range_c=(float(fields.min()), float(fields.max())),
    )


def _colors(fields_c: Floats, range_c: tuple[float, float]) -> NDArray[np.uint8]:
    from matplotlib import colormaps

    low, high = range_c
    if high - low < 1e-6:
        low, high = low - 0.5, high + 0.5
    scaled = np.clip((fields_c - low) / (high - low), 0.0, 1.0)
    return colormaps[COLORMAP](scaled, bytes=True)  # (K, N, 4) uint8 RGBA


def log_block_field(rec: rr.RecordingStream, block: BlockField) -> int:
    """The block mesh (static geometry), its vertex colours through the event (``COLORMAP``
    over the event's fixed range) and the sensor seat. Returns the number of fields logged."""
    rec.log(BLOCK, rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
    rec.log(
        BLOCK_MESH,
        rr.Mesh3D(vertex_positions=block.nodes_m, triangle_indices=block.triangles),
        static=True,
    )
    rec.log(
        BLOCK_SENSOR,
        rr.Points3D([block.sensor_m], radii=0.004, colors=[(40, 220, 255)], labels=["sensor"]),
        static=True,
    )
    k, n = block.fields_c.shape
    colors = _colors(block.fields_c, block.range_c).reshape(k * n, 4)
    rec.send_columns(
        BLOCK_MESH,
        indexes=_index(block.times),
        columns=rr.Mesh3D.columns(vertex_colors=colors).partition(np.full(k, n)),
        strict=True,
    )
    return k


# --------------------------------------------------------------------------------------------
# Layout.


def blueprint(*, block_range_c: tuple[float, float] | None = None) -> rrb.Blueprint:
    """The layout for an engineer reviewing an incident: the temperature (measured vs
    predicted), speed, pressure and residual plots stacked on the left; for an event, the
    block's temperature field on the right (its name says the colour range); the event, flag
    and sensor-fault ranges, and the text log of flags, events and notes below."""
    plots = rrb.Vertical(
        rrb.TimeSeriesView(
            name="Block temperature °C: measured vs predicted",
            origin="/wagon/temperature",
            plot_legend=rrb.PlotLegend(visible=True),
        ),
        rrb.TimeSeriesView(name="Speed km/h", origin="/", contents=f"/{SPEED}"),
        rrb.TimeSeriesView(name="Brake pressure bar", origin="/", contents=f"/{PRESSURE}"),
        rrb.TimeSeriesView(
            name="Residual K (measured - predicted sensor)", origin="/", contents=f"/{RESIDUAL}"
        ),
        row_shares=[3.0, 1.2, 1.2, 1.6],
    )
    top: rrb.Container | rrb.View = plots
    if block_range_c is not None:
        low, high = block_range_c
        top = rrb.Horizontal(
            plots,
            rrb.Spatial3DView(
                name=f"Block temperature field ({COLORMAP}: {low:.0f} to {high:.0f} °C)",
                origin=f"/{BLOCK}",
            ),
            column_shares=[3.0, 2.0],
        )
    return rrb.Blueprint(
        rrb.Vertical(
            top,
            rrb.StateTimelineView(name="Events, flags, faulty readings", origin="/state"),
            rrb.TextLogView(name="Flags, events, notes", origin="/log"),
            row_shares=[6.0, 1.2, 2.0],
        ),
        rrb.TimePanel(timeline=TIMELINE),
        auto_views=False,
    )


# --------------------------------------------------------------------------------------------
# The whole recording.


@dataclass(frozen=True)
class RecordSummary:
    """What was written."""

    out: Path
    wagon_id: str
    event_id: str | None
    revision: str | None
    counts: dict[str, int]
    """Values (or rows) logged per entity path or concern."""
    notes: list[str]
    seconds: float


def wagon_config(wagon_id: str, registry: str | os.PathLike[str] | None) -> WagonConfig:
    """The wagon's block and sensor seat: from ``registry`` (a ``fleet.toml`` or a fleet
    directory) if given, else the spec's defaults."""
    if registry is None:
        try:
            return WagonConfig(wagon_id=wagon_id)
        except ValueError:
            return WagonConfig(wagon_id="unnamed")
    path = Path(registry)
    if path.is_dir():
        path = path / "fleet.toml"
    try:
        return load_registry(path).wagon(wagon_id)
    except RegistryError as error:
        raise RecordError(str(error)) from None


def _open(db: Path, wait_s: float) -> Warehouse:
    deadline = time.monotonic() + max(wait_s, 0.0)
    while True:
        try:
            return open_warehouse(db, read_only=True)
        except WarehouseLockedError as error:
            if time.monotonic() >= deadline:
                raise RecordLockedError(
                    f"{db}: cannot be read now: another process is writing to it and DuckDB "
                    "lets no other process open it meanwhile. Run again when it has finished, "
                    f"or give --wait SECONDS. ({error})"
                ) from None
            time.sleep(0.5)
        except WarehouseError as error:
            raise RecordError(f"cannot open the database: {error}") from None


def record(
    db: str | os.PathLike[str],
    wagon_id: str,
    out: str | os.PathLike[str],
    *,
    event_id: str | None = None,
    revision: str | None = None,
    wagon: WagonConfig | None = None,
    refinement: float = DEFAULT_BLOCK_REFINEMENT,
    field_every_s: float = FIELD_EVERY_S,
    wait_s: float = 0.0,
) -> RecordSummary:
    """Write a rerun recording of ``wagon_id``'s timeline, or of its event ``event_id``, to
    ``out`` (written to a temporary file first, then renamed: never half a file).

    The database is opened read-only (waiting up to ``wait_s`` while another process writes
    it). ``wagon``: the wagon's configuration for the block mesh and sensor seat (default: the
    entry the last ``run`` stored in ``wagon_registry``, else the spec's defaults). Raises
    :class:`RecordError` (or :class:`RecordLockedError`) naming the database, wagon, event,
    revision or output that is wrong.
    """
    began = time.perf_counter()
    db_path, out_path = Path(db), Path(out)
    with _open(db_path, wait_s) as wh:
        data = load_record_data(wh, wagon_id, event_id=event_id, revision=revision)
    notes = list(data.notes)  # what the recording lacks (WARN)
    about: list[str] = []  # how it was made (INFO)

    block: BlockField | None = None
    if event_id is not None:
        if wagon is not None:
            config, source = wagon, "the registry given"
        elif data.stored_wagon is not None:
            config, source = data.stored_wagon, f"{data.stored_wagon_source}, as `run` used it"
        else:
            config, source = wagon_config(wagon_id, None), None
        mine = (
            data.predictions.filter(pl.col("event_id") == event_id)
            if data.predictions.height
            else data.predictions
        )
        block = simulate_block_field(
            config, mine, refinement=refinement, field_every_s=field_every_s
        )
        if block is None:
            notes.append(f"event {event_id}: no block temperature field (no predictions)")
        else:
            low, high = block.range_c
            about.append(
                f"block/mesh: full model (hex8, refinement {refinement:g}) driven by the heat "
                f"input and air temperature of revision {data.revision!r}, from a uniform "
                f"{block.fields_c[0].mean():.1f} °C; colours {COLORMAP} over "
                f"{low:.1f} to {high:.1f} °C"
            )
            predicted = _values(mine, "predicted_sensor_c")
            seconds = (_times(mine) - _times(mine)[0]) / np.timedelta64(1, "s")
            at_seconds = np.interp(seconds, np.arange(block.sensor_c.size), block.sensor_c)
            deviation = float(np.max(np.abs(at_seconds - predicted)))
            if deviation > 5.0:
                notes.append(
                    f"block/mesh: at the sensor seat the field differs from the prediction by "
                    f"up to {deviation:.1f} K (the field is the coarse full model with the "
                    "declared convection; the prediction is the revision's model)"
                )
            about.append(
                "block/mesh: block geometry and sensor seat "
                + (f"from {source}" if source else "of the spec's defaults (no registry known)")
            )

    counts: dict[str, int] = {}
    partial = out_path.with_name(f".{out_path.name}.{os.getpid()}.partial")
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        partial.touch()
        if out_path.is_dir():
            raise IsADirectoryError(21, "is a directory")
    except OSError as error:
        partial.unlink(missing_ok=True)
        raise RecordError(
            f"{out_path}: cannot write the recording: {error.strerror or error}"
        ) from None
    kind = "event" if event_id is not None else "timeline"
    rec = rr.RecordingStream(f"fleetbrake_{kind}", recording_id=uuid.uuid4())
    try:
        rec.save(partial)
        rec.set_log_time_enabled(False)
        rec.set_log_tick_enabled(False)
        name = event_id if event_id is not None else f"{wagon_id} timeline"
        rec.send_recording_name(f"{name} (revision {data.revision or 'none'})")
        starts = [
            t
            for t in (
                data.window[0] if data.window is not None else None,
                _times(data.samples)[0] if data.samples.height else None,
                _at(data.events["start_utc"][0]) if data.events.height else None,
            )
            if t is not None
        ]
        first = np.datetime64(starts[0], "ns") if starts else np.datetime64(0, "ns")
        rec.send_recording_start_time_nanos(int(first.astype(np.int64)))
        rec.send_blueprint(blueprint(block_range_c=block.range_c if block else None))

        counts[SPEED] = log_speed(rec, data.samples)
        counts[PRESSURE] = log_pressure(rec, data.samples)
        counts |= log_temperatures(rec, data.samples, data.predictions)
        counts[RESIDUAL] = log_residual(rec, data.predictions)
        counts["faulty_readings"] = log_faulty_readings(rec, data.samples)
        counts["events"] = log_events(rec, data.events)
        counts["flags"] = log_flags(rec, data.flags)
        if block is not None:
            counts[BLOCK_MESH] = log_block_field(rec, block)
        counts["notes"] = log_notes(rec, first, notes) + log_notes(rec, first, about, level="INFO")
        rec.flush()
        rec.disconnect()
        os.replace(partial, out_path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return RecordSummary(
        out=out_path,
        wagon_id=wagon_id,
        event_id=event_id,
        revision=data.revision,
        counts=counts,
        notes=notes + about,
        seconds=time.perf_counter() - began,
    )
