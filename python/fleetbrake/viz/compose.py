"""The one composition of a wagon's recording: every concern logged by its ``log_<thing>()`` on
the one timeline, with the recording's name, start and layout, whatever the sink.

Both sinks use it: the ``.rrd`` files of ``fleetbrake record``
(:func:`fleetbrake.viz.record.record`) and the live viewer of ``fleetbrake watch --rerun``
(:mod:`fleetbrake.viz.live`), so that the entity paths (:mod:`fleetbrake.viz.entities`) and
the blueprint (:mod:`fleetbrake.viz.blueprint`) are written in one place.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun as rr

from fleetbrake.viz.block import BlockField, log_block_field
from fleetbrake.viz.blueprint import blueprint
from fleetbrake.viz.data import RecordData, frame_times, instant
from fleetbrake.viz.entities import BLOCK_MESH, PRESSURE, RESIDUAL, SPEED
from fleetbrake.viz.timeline import (
    log_contact_estimate,
    log_events,
    log_faulty_readings,
    log_flags,
    log_notes,
    log_pressure,
    log_residual,
    log_speed,
    log_temperatures,
    log_unexplained_power,
)

__all__ = ["first_instant", "log_recording"]


def first_instant(data: RecordData) -> np.datetime64:
    """The recording's first instant: its window's start, else its first sample, else its
    first event's activation (the epoch when it has none)."""
    starts = [
        t
        for t in (
            data.window[0] if data.window is not None else None,
            frame_times(data.samples)[0] if data.samples.height else None,
            instant(data.events["start_utc"][0]) if data.events.height else None,
        )
        if t is not None
    ]
    return instant(starts[0]) if starts else np.datetime64(0, "ns")


def log_recording(
    rec: rr.RecordingStream,
    name: str,
    data: RecordData,
    *,
    block: BlockField | None = None,
    notes: Sequence[str] = (),
    about: Sequence[str] = (),
    start: bool = True,
) -> dict[str, int]:
    """Everything ``data`` holds on the one timeline, each concern by its ``log_<thing>()``,
    with the recording's name (``name`` and the revision), start and layout; ``notes`` (what
    the recording lacks, WARN) and ``about`` (how it was made, INFO) as text logs at its first
    instant. ``start``: send the recording's start time (its first instant; not for a live
    recording, which grows). Returns the counts per entity path or concern."""
    rec.set_log_time_enabled(False)
    rec.set_log_tick_enabled(False)
    rec.send_recording_name(f"{name} (revision {data.revision or 'none'})")
    first = first_instant(data)
    if start:
        rec.send_recording_start_time_nanos(int(first.astype(np.int64)))
    rec.send_blueprint(blueprint(block_range_c=block.range_c if block else None))

    counts: dict[str, int] = {}
    counts[SPEED] = log_speed(rec, data.samples)
    counts[PRESSURE] = log_pressure(rec, data.samples)
    counts |= log_temperatures(rec, data.samples, data.predictions)
    counts |= log_contact_estimate(rec, data.estimates)
    counts |= log_unexplained_power(rec, data.estimates)
    counts[RESIDUAL] = log_residual(rec, data.predictions)
    counts["faulty_readings"] = log_faulty_readings(rec, data.samples)
    counts["events"] = log_events(rec, data.events)
    counts["flags"] = log_flags(rec, data.flags)
    if block is not None:
        counts[BLOCK_MESH] = log_block_field(rec, block)
    counts["notes"] = log_notes(rec, first, notes) + log_notes(rec, first, about, level="INFO")
    return counts
