"""Rerun recordings of a wagon's timeline, or of one braking event, for incident review
(``fleetbrake record``).

::

    from fleetbrake.viz.record import record

    summary = record("warehouse/fleet.duckdb", "SGG-0001", "SGG-0001.rrd")   # the timeline
    summary = record(db, "SGG-0001", "incident.rrd", event_id="SGG-0001-20240301T101500")
    summary.notes    # what the recording lacks and why (no predictions yet, ...)

Open the file with ``rerun FILE.rrd``. :func:`record` orchestrates: it reads what the recording
shows (:mod:`fleetbrake.viz.data`; the database is only read), simulates the block's field for
an event (:mod:`fleetbrake.viz.block`), and logs each concern (:mod:`fleetbrake.viz.timeline`)
on the one timeline with the layout of :mod:`fleetbrake.viz.blueprint`, through
:func:`fleetbrake.viz.compose.log_recording` (which the live viewer of ``watch --rerun`` uses
too). The entities are listed
in :mod:`fleetbrake.viz.entities`.
"""

from __future__ import annotations

import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl
import rerun as rr

from fleetbrake.fleet.registry import RegistryError, WagonConfig, load_registry
from fleetbrake.viz.block import (
    DEFAULT_BLOCK_REFINEMENT,
    FIELD_EVERY_S,
    BlockField,
    simulate_block_field,
)
from fleetbrake.viz.compose import log_recording
from fleetbrake.viz.data import (
    RecordData,
    RecordError,
    frame_times,
    frame_values,
    load_record_data,
    open_read_only,
)
from fleetbrake.viz.entities import COLORMAP

__all__ = ["RecordSummary", "record", "wagon_config"]


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
    :class:`~fleetbrake.viz.data.RecordError` (or ``RecordLockedError``) naming the database, wagon, event,
    revision or output that is wrong.
    """
    began = time.perf_counter()
    db_path, out_path = Path(db), Path(out)
    with open_read_only(db_path, wait_s) as wh:
        data = load_record_data(wh, wagon_id, event_id=event_id, revision=revision)
    notes = list(data.notes)  # what the recording lacks (WARN)
    about: list[str] = []  # how it was made (INFO)
    block: BlockField | None = None
    if event_id is not None:
        block, lacks, made = _event_block(
            data, event_id, wagon, refinement=refinement, field_every_s=field_every_s
        )
        notes += lacks
        about += made

    partial = _claim(out_path)
    kind = "event" if event_id is not None else "timeline"
    rec = rr.RecordingStream(f"fleetbrake_{kind}", recording_id=uuid.uuid4())
    try:
        rec.save(partial)
        name = event_id if event_id is not None else f"{wagon_id} timeline"
        counts = log_recording(rec, name, data, block=block, notes=notes, about=about)
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


def _event_block(
    data: RecordData,
    event_id: str,
    wagon: WagonConfig | None,
    *,
    refinement: float,
    field_every_s: float,
) -> tuple[BlockField | None, list[str], list[str]]:
    """The block's field through the event, what the recording lacks for it (notes, WARN) and
    how it was made (INFO)."""
    lacks: list[str] = []
    made: list[str] = []
    if wagon is not None:
        config, source = wagon, "the registry given"
    elif data.stored_wagon is not None:
        config, source = data.stored_wagon, f"{data.stored_wagon_source}, as `run` used it"
    else:
        config, source = wagon_config(data.wagon_id, None), None
    mine = (
        data.predictions.filter(pl.col("event_id") == event_id)
        if data.predictions.height
        else data.predictions
    )
    block = simulate_block_field(config, mine, refinement=refinement, field_every_s=field_every_s)
    if block is None:
        lacks.append(f"event {event_id}: no block temperature field (no predictions)")
        return None, lacks, made
    low, high = block.range_c
    made.append(
        f"block/mesh: full model (hex8, refinement {refinement:g}) driven by the heat "
        f"input and air temperature of revision {data.revision!r}, from a uniform "
        f"{block.fields_c[0].mean():.1f} °C; colours {COLORMAP} over "
        f"{low:.1f} to {high:.1f} °C"
    )
    predicted = frame_values(mine, "predicted_sensor_c")
    seconds = (frame_times(mine) - frame_times(mine)[0]) / np.timedelta64(1, "s")
    at_seconds = np.interp(seconds, np.arange(block.sensor_c.size), block.sensor_c)
    deviation = float(np.max(np.abs(at_seconds - predicted)))
    if deviation > 5.0:
        lacks.append(
            f"block/mesh: at the sensor seat the field differs from the prediction by "
            f"up to {deviation:.1f} K (the field is the coarse full model with the "
            "declared convection; the prediction is the revision's model)"
        )
    made.append(
        "block/mesh: block geometry and sensor seat "
        + (f"from {source}" if source else "of the spec's defaults (no registry known)")
    )
    return block, lacks, made


def _claim(out_path: Path) -> Path:
    """The partial file the recording is written to before it is renamed to ``out_path``,
    created now so that an output that cannot be written is reported before any work."""
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
    return partial
