"""Pictures of the reproduction, rendered headlessly (matplotlib's Agg backend) to PNG.

One function per picture:

* :func:`plot_block_field`: the block's temperature field -- its boundary surface seen from
  the wheel and from the holder, and the cut through the sensor seat (the paper's figures
  4, 5, 7 and 8);
* :func:`plot_sensor_curve`: the sensor temperature over time, with the friction face's mean
  and maximum (the paper's figures 6 and 9, simulated curves only: the paper publishes no
  measured ones);
* :func:`plot_calibration`: time to peak against sensor depth, with the paper's values;
* :func:`plot_study`: time to peak and rise against depth, convection and cylinder bore.

Each takes the data and a path, writes the PNG and returns the path.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib import tri
from matplotlib.axes import Axes
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter, ScalarFormatter
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # type: ignore[import-untyped]  # no py.typed
from mpl_toolkits.mplot3d.axes3d import Axes3D  # type: ignore[import-untyped]  # no py.typed
from numpy.typing import ArrayLike, NDArray

from fleetbrake.fleet.block import BlockGeometry
from fleetbrake.model.thermal import Mesh

if TYPE_CHECKING:
    from fleetbrake.paper.results import Calibration, ManoeuvreResult, Study

__all__ = [
    "plot_block_field",
    "plot_calibration",
    "plot_sensor_curve",
    "plot_study",
]

CMAP = "inferno"
_QUAD8_OUTLINE = (0, 4, 1, 5, 2, 6, 3, 7)
"""Corners and mid-edge nodes of a VTK quadratic quad, in order around its outline."""


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _block_frame(nodes: NDArray[np.float64], wheel_radius_m: float) -> NDArray[np.float64]:
    """Plot coordinates in mm: along the arc (x), across the block (wheel axis z), height
    above the friction face's middle (y - R_w), so that the friction face is at the bottom."""
    return np.column_stack(
        [nodes[:, 0] * 1e3, nodes[:, 2] * 1e3, (nodes[:, 1] - wheel_radius_m) * 1e3]
    )


def _boundary_polygons(mesh: Mesh) -> NDArray[np.int64]:
    """Node indices of every boundary face, each in order around its outline."""
    faces = np.vstack([np.asarray(f) for f in mesh.face_sets.values()])
    if faces.shape[1] == 8:
        return faces[:, list(_QUAD8_OUTLINE)]
    return faces


def _surface_view(
    ax: Axes3D,
    xyz: NDArray[np.float64],
    polygons: NDArray[np.int64],
    field_c: NDArray[np.float64],
    norm: Normalize,
    elev: float,
    azim: float,
    title: str,
) -> None:
    cmap = plt.get_cmap(CMAP)
    colours = cmap(norm(field_c[polygons].mean(axis=1)))
    collection = Poly3DCollection(
        xyz[polygons], facecolors=colours, edgecolors=(0, 0, 0, 0.15), linewidths=0.2
    )
    ax.add_collection3d(collection)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-9)), zoom=1.35)
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()
    ax.set_title(title, fontsize=9, y=0.92)


def plot_block_field(
    mesh: Mesh,
    field_c: ArrayLike,
    geometry: BlockGeometry,
    path: str | Path,
    *,
    title: str,
    sensor_m: Sequence[float] | None = None,
    vmin: float | None = None,
    vmax: float | None = None,
) -> Path:
    """The block's temperature field ``field_c`` (one value per node of ``mesh``): its surface
    seen from the wheel and from the holder, and the cut through the sensor seat (the plane
    z = sensor z) with the sensor marked; one colour scale for all three views."""
    field = np.asarray(field_c, dtype=np.float64).reshape(-1)
    if field.size != mesh.n_nodes:
        raise ValueError(f"field has {field.size} values, the mesh {mesh.n_nodes} nodes")
    range_c = (
        float(field.min()) if vmin is None else vmin,
        float(field.max()) if vmax is None else vmax,
    )
    norm = Normalize(vmin=range_c[0], vmax=range_c[1])
    rw = geometry.wheel_radius_m
    xyz = _block_frame(mesh.nodes, rw)
    polygons = _boundary_polygons(mesh)

    fig = plt.figure(figsize=(11.0, 7.5))
    grid = fig.add_gridspec(
        2, 3, width_ratios=(1.0, 1.0, 0.035), height_ratios=(1.1, 1.0), hspace=0.05, wspace=0.0
    )
    ax_wheel = fig.add_subplot(grid[0, 0], projection="3d")
    ax_back = fig.add_subplot(grid[0, 1], projection="3d")
    _surface_view(
        ax_wheel, xyz, polygons, field, norm, -32.0, -60.0, "seen from the wheel: friction face"
    )
    _surface_view(
        ax_back, xyz, polygons, field, norm, 32.0, -60.0, "seen from the holder: back and lug"
    )

    ax_cut = fig.add_subplot(grid[1, :2])
    _section(ax_cut, mesh, field, geometry, norm, range_c, sensor_m)
    mappable = plt.cm.ScalarMappable(norm=norm, cmap=CMAP)
    bar = fig.colorbar(mappable, cax=fig.add_subplot(grid[:, 2]))
    bar.set_label("temperature, °C")
    fig.suptitle(title, fontsize=11)
    fig.subplots_adjust(left=0.06, right=0.93, top=0.93, bottom=0.07)
    return _save(fig, path)


def _section(
    ax: Axes,
    mesh: Mesh,
    field: NDArray[np.float64],
    geometry: BlockGeometry,
    norm: Normalize,
    range_c: tuple[float, float],
    sensor_m: Sequence[float] | None,
) -> None:
    """The cut through the node layer nearest the sensor's z, unrolled: arc length along the
    friction face against depth behind it (mm), areas outside the block masked."""
    nodes = mesh.nodes
    z_cut = 0.0 if sensor_m is None else float(sensor_m[2])
    layers = np.unique(np.round(nodes[:, 2], 12))
    z_layer = float(layers[np.argmin(np.abs(layers - z_cut))])
    on = np.abs(nodes[:, 2] - z_layer) < 1e-9
    pts = nodes[on]
    rw = geometry.wheel_radius_m
    theta = np.arctan2(pts[:, 0], pts[:, 1])
    s_mm = rw * theta * 1e3
    depth_mm = (np.hypot(pts[:, 0], pts[:, 1]) - rw) * 1e3
    triangulation = tri.Triangulation(s_mm, depth_mm)
    centre_s = s_mm[triangulation.triangles].mean(axis=1)
    centre_d = depth_mm[triangulation.triangles].mean(axis=1)
    lug_half_mm = rw * math.radians(geometry.lug_angle_deg) / 2 * 1e3
    in_lug_z = abs(z_layer) <= geometry.lug_width_m / 2 + 1e-12
    body_mm = geometry.body_thickness_m * 1e3
    outside = (centre_d > body_mm + 1e-6) & ((np.abs(centre_s) > lug_half_mm) | (not in_lug_z))
    triangulation.set_mask(outside)
    low_c, high_c = range_c
    levels = np.linspace(low_c, high_c, 41)
    if levels[-1] - levels[0] <= 0:
        levels = np.linspace(low_c - 0.5, low_c + 0.5, 41)
    ax.tricontourf(triangulation, field[on], levels=levels, cmap=CMAP, norm=norm, extend="both")
    ax.tricontour(triangulation, field[on], levels=levels[::4], colors="k", linewidths=0.3)
    if sensor_m is not None:
        sx, sy = float(sensor_m[0]), float(sensor_m[1])
        ax.plot(
            rw * math.atan2(sx, sy) * 1e3,
            (math.hypot(sx, sy) - rw) * 1e3,
            marker="o",
            color="cyan",
            markeredgecolor="k",
            label="sensor seat",
        )
        ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("arc length along the friction face, mm")
    ax.set_ylabel("depth behind the friction face, mm")
    ax.set_title(f"cut at z = {z_layer * 1e3:.0f} mm (through the sensor seat)", fontsize=9)


def plot_sensor_curve(
    run: ManoeuvreResult,
    path: str | Path,
    *,
    extra_depths_m: Mapping[str, float] | None = None,
) -> Path:
    """The sensor temperature over the run (and at ``extra_depths_m``, label -> depth, on the
    sensor's line), the simulated and the paper's time to peak; below, the friction face's
    mean and maximum."""
    t = run.time_s
    fig, (ax, ax_face) = plt.subplots(
        2, 1, figsize=(8.0, 6.5), sharex=True, height_ratios=(1.6, 1.0)
    )
    ax.plot(t, run.sensor_c, color="C0", label=f"sensor at {run.sensor_depth_m * 1e3:.1f} mm")
    for k, (label, depth) in enumerate((extra_depths_m or {}).items()):
        ax.plot(t, run.curve_at_depth(depth), color=f"C{k + 2}", ls="--", label=label)
    ax.axvline(run.time_to_peak_s, color="C0", lw=0.8, ls=":")
    ax.plot(run.time_to_peak_s, run.sensor_peak_c, "o", color="C0")
    ax.annotate(
        f"max at {run.time_to_peak_s:.0f} s, +{run.sensor_rise_k:.1f} K",
        (run.time_to_peak_s, run.sensor_peak_c),
        xytext=(12, 6),
        textcoords="offset points",
        fontsize=8,
    )
    paper = run.paper_time_to_peak_s
    if paper is not None:
        ax.axvline(paper, color="C3", lw=1.0, label=f"paper: max at {paper:g} s")
    ax.axvspan(0, run.manoeuvre.duration_s, color="0.9", label="braking")
    ax.set_ylabel("temperature, °C")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    ax.set_title(
        f"Manoeuvre {run.name}: simulated sensor temperature "
        f"(T0 {run.manoeuvre.t0_c:g} °C, Φ_b {run.block_flux_w_m2:,.0f} W/m² "
        f"for {run.manoeuvre.duration_s:g} s)",
        fontsize=10,
    )
    ax_face.plot(t, run.contact_max_c, color="C1", label="friction face, max")
    ax_face.plot(t, run.contact_mean_c, color="C1", ls="--", label="friction face, mean")
    ax_face.plot(t, run.sensor_c, color="C0", lw=0.8, label="sensor")
    ax_face.axvspan(0, run.manoeuvre.duration_s, color="0.9")
    ax_face.set_xlabel("time from brake activation, s")
    ax_face.set_ylabel("temperature, °C")
    ax_face.legend(fontsize=8)
    ax_face.grid(alpha=0.3)
    ax_face.set_xlim(t[0], t[-1])
    fig.tight_layout()
    return _save(fig, path)


def plot_calibration(
    calibration: Calibration, path: str | Path, *, registry_depth_m: float | None = None
) -> Path:
    """Time to peak against sensor depth for each manoeuvre, the paper's times, the
    calibrated depth (and the registry's)."""
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    d_mm = calibration.depths_m * 1e3
    lo, hi = (v * 1e3 for v in calibration.depth_range_m)
    keep = (d_mm >= lo - 1e-9) & (d_mm <= hi + 1e-9)
    for k, (name, curve) in enumerate(calibration.time_to_peak_curves_s.items()):
        ax.plot(d_mm[keep], curve[keep], color=f"C{k}", label=f"{name}: simulated")
        paper = calibration.paper_time_to_peak_s[name]
        ax.axhline(paper, color=f"C{k}", ls=":", label=f"{name}: paper {paper:g} s")
        ax.axhspan(0.9 * paper, 1.1 * paper, color=f"C{k}", alpha=0.07)
    ax.axvline(
        calibration.sensor_depth_m * 1e3,
        color="k",
        lw=1.0,
        label=f"calibrated {calibration.sensor_depth_m * 1e3:.1f} mm",
    )
    if registry_depth_m is not None:
        ax.axvline(
            registry_depth_m * 1e3,
            color="0.5",
            ls="--",
            label=f"registry {registry_depth_m * 1e3:g} mm",
        )
    ax.set_xlabel("sensor depth behind the friction face, mm")
    ax.set_ylabel("time from activation to the sensor's maximum, s")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Calibration of the sensor depth (bands: ±10 % of the paper's times)", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


_STUDY_PANELS = (
    ("sensor_depth_m", "sensor depth, mm", 1e3),
    ("convection_w_m2k", "convection h, W/m² K", 1.0),
    ("cylinder_diameter_m", "cylinder bore, mm", 1e3),
)


def plot_study(study: Study, path: str | Path) -> Path:
    """Time to peak (top) and sensor rise (bottom) against each studied parameter."""
    fig, axes = plt.subplots(2, 3, figsize=(11.0, 6.0))
    for col, (parameter, label, scale) in enumerate(_STUDY_PANELS):
        rows = study.select(parameter)
        for k, name in enumerate(sorted({r.manoeuvre for r in rows})):
            mine = sorted((r for r in rows if r.manoeuvre == name), key=lambda r: r.value)
            x = [r.value * scale for r in mine]
            axes[0, col].plot(x, [r.time_to_peak_s for r in mine], "o-", color=f"C{k}", label=name)
            axes[1, col].plot(x, [r.sensor_rise_k for r in mine], "o-", color=f"C{k}", label=name)
        axes[1, col].set_xlabel(label)
        if parameter == "convection_w_m2k":
            ticks = sorted({r.value for r in rows})
            for ax in axes[:, col]:
                ax.set_xscale("log")
                ax.set_xticks(ticks)
                ax.xaxis.set_major_formatter(ScalarFormatter())
                ax.xaxis.set_minor_formatter(NullFormatter())
        for ax in axes[:, col]:
            ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("time to peak, s")
    axes[1, 0].set_ylabel("sensor rise, K")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("How the sensor's maximum depends on depth, convection and cylinder bore")
    fig.tight_layout()
    return _save(fig, path)
