"""The block's temperature field through one event (``fleetbrake record --event``): simulated
with the full model from the event's stored heat input, and logged to rerun as the block's
boundary coloured by its temperature (``block/mesh``) with the sensor seat (``block/sensor``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl
import rerun as rr
from numpy.typing import NDArray

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.viz.data import frame_times, frame_values
from fleetbrake.viz.entities import (
    BLOCK,
    BLOCK_MESH,
    BLOCK_SENSOR,
    COLORMAP,
    Floats,
    Times,
    time_index,
)

__all__ = [
    "DEFAULT_BLOCK_REFINEMENT",
    "FIELD_EVERY_S",
    "BlockField",
    "log_block_field",
    "simulate_block_field",
]

FIELD_EVERY_S = 5.0
"""Interval between two temperature fields of the block (``--event``)."""

DEFAULT_BLOCK_REFINEMENT = 0.5
"""Mesh of the block pictures: coarse hex8 (about 1,000 nodes), enough for a picture."""


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
    times = frame_times(predictions)
    seconds = (times - times[0]) / np.timedelta64(1, "s")
    grid = np.arange(0.0, float(seconds[-1]) + 0.5, 1.0)
    if grid.size < 2:
        return None
    flux = np.interp(grid, seconds, frame_values(predictions, "flux_w_m2"))
    ambient = np.interp(grid, seconds, frame_values(predictions, "ambient_c"))
    initial = float(frame_values(predictions, "predicted_sensor_c")[0])
    model = BlockModel(
        wagon.geometry,
        wagon.block_material,
        element="hex8",
        refinement=refinement,
        sensor_m=wagon.sensor_point_m,
    )
    every = max(1, round(field_every_s))
    n_steps = grid.size - 1
    # Step n holds on [t_n, t_n+1]: the mean of its two bounding samples (as fleetbrake.model.timeline).
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
        indexes=time_index(block.times),
        columns=rr.Mesh3D.columns(vertex_colors=colors).partition(np.full(k, n)),
        strict=True,
    )
    return k
