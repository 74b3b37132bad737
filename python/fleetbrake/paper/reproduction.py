"""The paper's manoeuvres A and B in the declared model, the study its conclusion asks for,
and a calibration of the sensor depth (issue 3; ``fleetbrake paper``).

Usage::

    from fleetbrake.paper.reproduction import reproduce_paper, run_study

    rep = reproduce_paper()                     # registry defaults, hex20 mesh, 1200 s of 1 s
    rep.runs["A"].time_to_peak_s                # s from activation to the sensor's maximum
    rep.runs["A"].sensor_rise_k                 # peak - T0
    rep.calibration.sensor_depth_m              # one depth fitted to both paper times to peak
    study = run_study(rep)                      # depth, convection, bore (+ two what-ifs)

What is simulated (``shared/spec/block-model.md``): the block of the wagon (default: the
registry's defaults), uniform at the manoeuvre's T0, the ambient of the registry (10 C),
h = 10 W/m^2 K on every surface but the friction face, the paper's constant flux Phi_b for
the manoeuvre's duration then nothing; Crank-Nicolson, dt = 1 s, one damped start step,
1200 steps; t = 0 is brake activation.

Probes. Besides the registry's sensor seat, every run carries probes along the seat's radial
line (every 0.5 mm from the friction face to the back of the block): a sensor at another
depth is the same simulation read elsewhere. The mesh stays graded towards the registry's
seat (0.055 m); :func:`remesh_check` measures what re-meshing towards another depth would
change (a few tenths of a second in the time to peak: see ``docs/paper-reproduction.md``).

Linearity. The declared model is linear (constant properties, h and ambient constant), so
with u = T - T_amb the response is linear in (initial excess, flux). One extra run, the free
decay g of a unit initial excess (no flux, ambient 0), gives the sensor curve of any flux
scale and any T0 exactly: T = T_amb + (T0 - T_amb) g + s (T_ref - T_amb - (T0_ref - T_amb) g).
The study uses that for the cylinder bore (the bore only scales the flux), for eq. 6 as the
paper prints it (flux x 1/mu) and for swapping T0 between A and B; convection needs runs.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from fleetbrake.fleet.block import DEFAULT_CONVECTION_W_M2K, BlockGeometry, sensor_point_m
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.physics import (
    PAPER_MANOEUVRES,
    EventHeatInput,
    Manoeuvre,
    event_heat_input,
    pulse_flux_series_w_m2,
)
from fleetbrake.model.thermal import AIR_FACES, BlockModel, Element, SimulationResult

__all__ = [
    "MANOEUVRE_NAMES",
    "Calibration",
    "ManoeuvreResult",
    "PaperReproduction",
    "Peak",
    "RemeshCheck",
    "RunSettings",
    "Study",
    "StudyRow",
    "calibrate_depth",
    "find_peak",
    "free_decay_response",
    "paper_wagon",
    "peak_times",
    "print_report",
    "print_study",
    "remesh_check",
    "reproduce_paper",
    "run_study",
    "simulate_manoeuvre",
    "superposed_curves",
    "write_outputs",
]

FloatArray = NDArray[np.float64]
T = TypeVar("T")

MANOEUVRE_NAMES = ("A", "B")
"""The paper's manoeuvres, in its order."""

STUDY_DEPTHS_M = (0.045, 0.050, 0.055, 0.060, 0.065, 0.070)
STUDY_CONVECTION_W_M2K = (5.0, 10.0, 20.0, 50.0)
STUDY_BORES_M = (0.203, 0.254, 0.305, 0.356)
"""8, 10, 12 and 14 inch brake cylinders (the registry default is 10 inch, 0.254 m)."""

CALIBRATION_RANGE_M = (0.030, 0.070)
"""Depths the calibration may choose from: the lower half of the body to the lug's back."""


# --------------------------------------------------------------------------------------------
# Settings and small helpers


@dataclass(frozen=True)
class RunSettings:
    """How the manoeuvres are simulated. The defaults are the reproduction's."""

    element: Element = "hex20"
    refinement: float = 1.0
    dt_s: float = 1.0
    horizon_s: float = 1200.0
    probe_spacing_m: float = 0.0005
    field_every: int = 10
    """Whole fields kept every k steps (fields between are recomputed from the nearest one)."""
    workers: int = 2
    """Simulations run side by side in threads (the core releases the GIL)."""

    def __post_init__(self) -> None:
        if not self.dt_s > 0 or not self.horizon_s >= self.dt_s:
            raise ValueError("RunSettings: dt_s must be > 0 and horizon_s >= dt_s")
        if not self.probe_spacing_m > 0 or self.field_every < 1 or self.workers < 1:
            raise ValueError("RunSettings: probe_spacing_m > 0, field_every >= 1, workers >= 1")

    @property
    def n_steps(self) -> int:
        return round(self.horizon_s / self.dt_s)


def paper_wagon() -> WagonConfig:
    """The wagon of the reproduction: every value the registry's default (fleet-data.md)."""
    return WagonConfig(wagon_id="paper-default")


def _depth_limit_m(geometry: BlockGeometry, theta_deg: float, z_m: float) -> float:
    """Deepest point of the block on the radial line at (theta, z): lug back or body back."""
    in_lug = abs(theta_deg) <= geometry.lug_angle_deg / 2 and abs(z_m) <= geometry.lug_width_m / 2
    return geometry.body_thickness_m + (geometry.lug_height_m if in_lug else 0.0)


def _probe_depths_m(wagon: WagonConfig, spacing_m: float) -> FloatArray:
    limit = _depth_limit_m(wagon.geometry, wagon.sensor_theta_deg, wagon.sensor_z_m)
    n = math.floor(limit / spacing_m + 1e-9)
    return np.round(np.arange(n + 1) * spacing_m, 9)


def _probe_points_m(wagon: WagonConfig, depths_m: FloatArray) -> FloatArray:
    return np.array(
        [
            sensor_point_m(wagon.geometry, float(d), wagon.sensor_theta_deg, wagon.sensor_z_m)
            for d in depths_m
        ]
    )


def _parallel(jobs: Sequence[Callable[[], T]], workers: int) -> list[T]:
    if workers <= 1 or len(jobs) <= 1:
        return [job() for job in jobs]
    with ThreadPoolExecutor(max_workers=min(workers, len(jobs))) as pool:
        futures = [pool.submit(job) for job in jobs]
        return [f.result() for f in futures]


def _h(convection_w_m2k: float) -> dict[str, float]:
    return dict.fromkeys(AIR_FACES, float(convection_w_m2k))


# --------------------------------------------------------------------------------------------
# Peaks


@dataclass(frozen=True)
class Peak:
    """The maximum of a sampled curve, refined by a parabola through the 3 samples around it."""

    time_s: float
    value_c: float
    index: int
    """The sample holding the largest value."""
    interior: bool
    """False when the largest sample is the first or the last (no maximum inside the horizon)."""


def peak_times(time_s: FloatArray, values: FloatArray) -> tuple[FloatArray, FloatArray, NDArray]:
    """Refined maxima of each column of ``values`` (n, P) sampled at equally spaced ``time_s``.

    Returns (times, values, interior) of shape (P,). Where the largest sample is the first or
    the last, that sample is returned as it is and ``interior`` is False.
    """
    y = np.asarray(values, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    n = y.shape[0]
    if n < 3:
        raise ValueError("peak_times needs at least 3 samples")
    dt = float(time_s[1] - time_s[0])
    i = np.argmax(y, axis=0)
    cols = np.arange(y.shape[1])
    interior = (i > 0) & (i < n - 1)
    j = np.clip(i, 1, n - 2)
    y0, y1, y2 = y[j - 1, cols], y[j, cols], y[j + 1, cols]
    curvature = y0 - 2.0 * y1 + y2
    with np.errstate(divide="ignore", invalid="ignore"):
        offset = np.where(curvature < 0, 0.5 * (y0 - y2) / curvature, 0.0)
    offset = np.where(interior, np.clip(offset, -0.5, 0.5), 0.0)
    t = np.asarray(time_s, dtype=np.float64)[i] + offset * dt
    v = np.where(interior, y1 - 0.25 * (y0 - y2) * offset, y[i, cols])
    return t, v, interior


def find_peak(time_s: FloatArray, values: FloatArray) -> Peak:
    """The refined maximum of one curve (see :func:`peak_times`)."""
    t, v, interior = peak_times(time_s, np.asarray(values, dtype=np.float64).reshape(-1, 1))
    index = int(np.argmax(values))
    return Peak(time_s=float(t[0]), value_c=float(v[0]), index=index, interior=bool(interior[0]))


# --------------------------------------------------------------------------------------------
# One manoeuvre


@dataclass(frozen=True)
class ManoeuvreResult:
    """One manoeuvre simulated in the declared model, with what the paper reports and more."""

    name: str
    manoeuvre: Manoeuvre
    heat: EventHeatInput
    convection_w_m2k: float
    ambient_c: float
    flux_scale: float
    """Multiplies Phi_b of the heat input (1 for the declared model)."""
    sensor_m: tuple[float, float, float]
    sensor_depth_m: float
    time_s: FloatArray
    flux_w_m2: FloatArray
    """Per step (n_steps): the flux into the friction face on [t_n, t_n+1]."""
    sensor_c: FloatArray
    depths_m: FloatArray
    depth_c: FloatArray
    """(n_steps + 1, len(depths_m)): probes on the sensor's radial line."""
    contact_mean_c: FloatArray
    contact_max_c: FloatArray
    peak: Peak
    field_end_c: FloatArray | None
    """The whole field at the end of braking (t = duration), or None."""
    field_peak_c: FloatArray | None
    """The whole field at the step nearest the sensor's maximum, or None."""
    field_peak_time_s: float
    seconds: float
    energy_in_j: float

    @property
    def time_to_peak_s(self) -> float:
        return self.peak.time_s

    @property
    def sensor_peak_c(self) -> float:
        return self.peak.value_c

    @property
    def sensor_rise_k(self) -> float:
        return self.peak.value_c - self.manoeuvre.t0_c

    @property
    def paper_time_to_peak_s(self) -> float | None:
        return self.manoeuvre.time_to_peak_s

    @property
    def time_to_peak_rel_error(self) -> float | None:
        paper = self.manoeuvre.time_to_peak_s
        return None if paper is None else self.time_to_peak_s / paper - 1.0

    @property
    def block_flux_w_m2(self) -> float:
        return self.heat.block_flux_w_m2 * self.flux_scale

    def _at(self, series: FloatArray, t_s: float) -> float:
        return float(np.interp(t_s, self.time_s, series))

    @property
    def contact_max_end_c(self) -> float:
        return self._at(self.contact_max_c, self.manoeuvre.duration_s)

    @property
    def contact_mean_end_c(self) -> float:
        return self._at(self.contact_mean_c, self.manoeuvre.duration_s)

    @property
    def contact_max_at_peak_c(self) -> float:
        return self._at(self.contact_max_c, self.time_to_peak_s)

    @property
    def contact_mean_at_peak_c(self) -> float:
        return self._at(self.contact_mean_c, self.time_to_peak_s)

    def curve_at_depth(self, depth_m: float) -> FloatArray:
        """The temperature at ``depth_m`` on the sensor's line, linear between the probes."""
        d = self.depths_m
        if not d[0] <= depth_m <= d[-1]:
            raise ValueError(f"depth {depth_m} m outside the probes' {d[0]}..{d[-1]} m")
        k = int(np.clip(np.searchsorted(d, depth_m) - 1, 0, d.size - 2))
        w = (depth_m - d[k]) / (d[k + 1] - d[k])
        return (1.0 - w) * self.depth_c[:, k] + w * self.depth_c[:, k + 1]

    def depth_peaks(self) -> tuple[FloatArray, FloatArray, NDArray]:
        """(time to peak, rise, interior) at every probe depth."""
        t, v, interior = peak_times(self.time_s, self.depth_c)
        return t, v - self.manoeuvre.t0_c, interior

    def to_dict(self, *, curve_every_s: float = 10.0) -> dict[str, Any]:
        forces = {k: float(v) for k, v in dataclasses.asdict(self.heat.forces).items()}
        every = max(1, round(curve_every_s / float(self.time_s[1] - self.time_s[0])))
        paper = self.paper_time_to_peak_s
        rel = self.time_to_peak_rel_error
        return {
            "time_to_peak_s": round(self.time_to_peak_s, 2),
            "paper_time_to_peak_s": paper,
            "time_to_peak_rel_error": None if rel is None else round(rel, 4),
            "peak_within_horizon": self.peak.interior,
            "sensor_rise_k": round(self.sensor_rise_k, 3),
            "sensor_peak_c": round(self.sensor_peak_c, 3),
            "sensor_depth_m": self.sensor_depth_m,
            "t0_c": self.manoeuvre.t0_c,
            "ambient_c": self.ambient_c,
            "convection_w_m2k": self.convection_w_m2k,
            "duration_s": self.manoeuvre.duration_s,
            "p_mean_bar": self.manoeuvre.p_mean_bar,
            "mean_speed_m_s": round(self.manoeuvre.mean_speed_m_s, 4),
            "contact_max_end_c": round(self.contact_max_end_c, 3),
            "contact_mean_end_c": round(self.contact_mean_end_c, 3),
            "contact_max_at_peak_c": round(self.contact_max_at_peak_c, 3),
            "contact_mean_at_peak_c": round(self.contact_mean_at_peak_c, 3),
            "power_w": round(self.heat.power_w * self.flux_scale, 3),
            "frictional_flux_w_m2": round(self.heat.frictional_flux_w_m2 * self.flux_scale, 3),
            "alpha": round(self.heat.alpha, 6),
            "flux_w_m2": round(self.block_flux_w_m2, 3),
            "block_energy_j": round(self.energy_in_j, 1),
            "force_chain": forces,
            "sensor_curve": {
                "time_s": [float(t) for t in self.time_s[::every]],
                "sensor_c": [round(float(v), 3) for v in self.sensor_c[::every]],
            },
        }


def _field_at_step(
    model: BlockModel,
    res: SimulationResult,
    step: int,
    *,
    dt_s: float,
    flux: FloatArray,
    ambient_c: float,
    h: Mapping[str, float],
    probe: FloatArray,
    damped_steps: int,
) -> FloatArray:
    """The whole field after ``step`` steps: the nearest stored one before it, continued.

    A continuation of a run with the same inputs and plain Crank-Nicolson steps (the damped
    start only applies to the run's first steps) gives the run's own field, bit for bit.
    """
    stored = res.field_steps
    k = int(np.searchsorted(stored, step, side="right") - 1)
    start = int(stored[k])
    if start == step:
        return np.array(res.fields_c[k])
    cont = model.simulate(
        dt_s=dt_s,
        flux_w_m2=flux[start:step],
        initial_c=res.fields_c[k],
        ambient_c=ambient_c,
        h_w_m2k=h,
        probes_m=probe,
        damped_steps=max(0, damped_steps - start),
    )
    return np.array(cont.final_c)


def simulate_manoeuvre(
    model: BlockModel,
    wagon: WagonConfig,
    name: str,
    manoeuvre: Manoeuvre,
    *,
    settings: RunSettings = RunSettings(),
    convection_w_m2k: float | None = None,
    flux_scale: float = 1.0,
    keep_fields: bool = True,
) -> ManoeuvreResult:
    """One manoeuvre in the declared model on ``model`` (a mesh of ``wagon``'s block).

    ``convection_w_m2k``: on every surface but the friction face (default: the declared 10).
    ``keep_fields``: also return the whole field at the end of braking and at the sensor's
    maximum (two short continuations from the stored fields).
    """
    started = time.perf_counter()
    h_value = DEFAULT_CONVECTION_W_M2K if convection_w_m2k is None else float(convection_w_m2k)
    h = _h(h_value)
    heat = event_heat_input(wagon, manoeuvre)
    n = settings.n_steps
    dt = settings.dt_s
    flux = flux_scale * pulse_flux_series_w_m2(heat.block_flux_w_m2, manoeuvre.duration_s, n, dt)
    depths = _probe_depths_m(wagon, settings.probe_spacing_m)
    sensor = np.array([wagon.sensor_point_m])
    probes = np.vstack([sensor, _probe_points_m(wagon, depths)])
    ambient = wagon.ambient_temp_c
    damped = 1
    res = model.simulate(
        dt_s=dt,
        flux_w_m2=flux,
        initial_c=manoeuvre.t0_c,
        ambient_c=ambient,
        h_w_m2k=h,
        probes_m=probes,
        damped_steps=damped,
        field_every=settings.field_every if keep_fields else 0,
    )
    sensor_c = np.array(res.probe_c[:, 0])
    peak = find_peak(res.time_s, sensor_c)
    peak_step = min(n, round(peak.time_s / dt))
    field_end = field_peak = None
    if keep_fields:
        common = {
            "dt_s": dt,
            "flux": flux,
            "ambient_c": ambient,
            "h": h,
            "probe": sensor,
            "damped_steps": damped,
        }
        end_step = min(n, round(manoeuvre.duration_s / dt))
        field_end = _field_at_step(model, res, end_step, **common)
        field_peak = _field_at_step(model, res, peak_step, **common)
    return ManoeuvreResult(
        name=name,
        manoeuvre=manoeuvre,
        heat=heat,
        convection_w_m2k=h_value,
        ambient_c=ambient,
        flux_scale=flux_scale,
        sensor_m=tuple(float(v) for v in wagon.sensor_point_m),  # type: ignore[arg-type]
        sensor_depth_m=wagon.sensor_depth_m,
        time_s=np.array(res.time_s),
        flux_w_m2=flux,
        sensor_c=sensor_c,
        depths_m=depths,
        depth_c=np.array(res.probe_c[:, 1:]),
        contact_mean_c=np.array(res.face_mean_c),
        contact_max_c=np.array(res.face_max_c),
        peak=peak,
        field_end_c=field_end,
        field_peak_c=field_peak,
        field_peak_time_s=peak_step * dt,
        seconds=time.perf_counter() - started,
        energy_in_j=float(res.energy_flux_in_j),
    )


# --------------------------------------------------------------------------------------------
# Calibration


@dataclass(frozen=True)
class Calibration:
    """One sensor depth fitted to both paper times to peak (least squares of relative errors)."""

    sensor_depth_m: float
    time_to_peak_s: Mapping[str, float]
    paper_time_to_peak_s: Mapping[str, float]
    rel_error: Mapping[str, float]
    sensor_rise_k: Mapping[str, float]
    rms_rel_error: float
    depth_range_m: tuple[float, float]
    depths_m: FloatArray
    """The probe depths of the curves below."""
    time_to_peak_curves_s: Mapping[str, FloatArray]
    """Time to peak at every probe depth, per manoeuvre."""

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "sensor_depth_m": round(self.sensor_depth_m, 6),
            "rms_rel_error": round(self.rms_rel_error, 5),
            "depth_range_m": list(self.depth_range_m),
        }
        for name in self.time_to_peak_s:
            out[name] = {
                "time_to_peak_s": round(self.time_to_peak_s[name], 2),
                "paper_time_to_peak_s": self.paper_time_to_peak_s[name],
                "rel_error": round(self.rel_error[name], 5),
                "sensor_rise_k": round(self.sensor_rise_k[name], 3),
            }
        return out


def calibrate_depth(
    runs: Mapping[str, ManoeuvreResult],
    depth_range_m: tuple[float, float] = CALIBRATION_RANGE_M,
    resolution_m: float = 1.0e-5,
) -> Calibration:
    """The depth on the sensor's line minimising sum((t_peak(d) / t_paper - 1)^2) over ``runs``.

    The times to peak come from the probes every 0.5 mm of the runs (no new simulation),
    linear between probes; the search is on a grid of ``resolution_m`` over ``depth_range_m``.
    """
    names = [n for n in runs if runs[n].paper_time_to_peak_s]
    if not names:
        raise ValueError("calibrate_depth: no run has a paper time to peak")
    depths = runs[names[0]].depths_m
    lo, hi = depth_range_m
    keep = (depths >= lo - 1e-12) & (depths <= hi + 1e-12)
    if keep.sum() < 2:
        raise ValueError(f"calibrate_depth: fewer than 2 probes within {depth_range_m}")
    d = depths[keep]
    curves: dict[str, FloatArray] = {}
    rises: dict[str, FloatArray] = {}
    for name in names:
        t, rise, interior = runs[name].depth_peaks()
        if not interior[keep].all():
            raise ValueError(f"calibrate_depth: manoeuvre {name} peaks at the horizon somewhere")
        curves[name] = t
        rises[name] = rise
    grid = np.arange(d[0], d[-1] + resolution_m / 2, resolution_m)
    cost = np.zeros_like(grid)
    for name in names:
        paper = float(runs[name].paper_time_to_peak_s)  # type: ignore[arg-type]
        cost += (np.interp(grid, d, curves[name][keep]) / paper - 1.0) ** 2
    best = float(grid[int(np.argmin(cost))])
    t_best = {n: float(np.interp(best, d, curves[n][keep])) for n in names}
    papers = {n: float(runs[n].paper_time_to_peak_s) for n in names}  # type: ignore[arg-type]
    rel = {n: t_best[n] / papers[n] - 1.0 for n in names}
    return Calibration(
        sensor_depth_m=best,
        time_to_peak_s=t_best,
        paper_time_to_peak_s=papers,
        rel_error=rel,
        sensor_rise_k={n: float(np.interp(best, d, rises[n][keep])) for n in names},
        rms_rel_error=math.sqrt(sum(e * e for e in rel.values()) / len(rel)),
        depth_range_m=(float(lo), float(hi)),
        depths_m=depths,
        time_to_peak_curves_s=curves,
    )


# --------------------------------------------------------------------------------------------
# The reproduction


@dataclass
class PaperReproduction:
    """Manoeuvres A and B on the wagon's block, and the calibrated sensor depth."""

    wagon: WagonConfig
    settings: RunSettings
    model: BlockModel
    runs: dict[str, ManoeuvreResult]
    calibration: Calibration
    seconds_mesh: float
    seconds: float

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {name: run.to_dict() for name, run in self.runs.items()}
        out["calibration"] = self.calibration.to_dict()
        out["model"] = {
            "element": self.settings.element,
            "refinement": self.settings.refinement,
            "nodes": self.model.n_nodes,
            "dt_s": self.settings.dt_s,
            "horizon_s": self.settings.horizon_s,
            "scheme": "crank-nicolson, 1 damped start step",
            "mesh_graded_towards_m": list(self.wagon.sensor_point_m),
            "probe_spacing_m": self.settings.probe_spacing_m,
        }
        out["seconds"] = {
            "mesh": round(self.seconds_mesh, 2),
            **{name: round(run.seconds, 2) for name, run in self.runs.items()},
            "total": round(self.seconds, 2),
        }
        return out


def reproduce_paper(
    wagon: WagonConfig | None = None,
    settings: RunSettings = RunSettings(),
    *,
    model: BlockModel | None = None,
    manoeuvres: Mapping[str, Manoeuvre] = PAPER_MANOEUVRES,
) -> PaperReproduction:
    """Simulate the paper's manoeuvres on ``wagon`` (default: registry defaults) and calibrate."""
    started = time.perf_counter()
    wagon = wagon or paper_wagon()
    if model is None:
        model = BlockModel(
            wagon.geometry,
            wagon.block_material,
            element=settings.element,
            refinement=settings.refinement,
            sensor_m=wagon.sensor_point_m,
        )
    seconds_mesh = time.perf_counter() - started
    names = list(manoeuvres)

    def job(name: str) -> Callable[[], ManoeuvreResult]:
        return lambda: simulate_manoeuvre(model, wagon, name, manoeuvres[name], settings=settings)

    results = _parallel([job(n) for n in names], settings.workers)
    runs = dict(zip(names, results, strict=True))
    calibration = calibrate_depth(runs)
    return PaperReproduction(
        wagon=wagon,
        settings=settings,
        model=model,
        runs=runs,
        calibration=calibration,
        seconds_mesh=seconds_mesh,
        seconds=time.perf_counter() - started,
    )


# --------------------------------------------------------------------------------------------
# Linear superposition


def free_decay_response(
    model: BlockModel,
    wagon: WagonConfig,
    *,
    settings: RunSettings = RunSettings(),
    convection_w_m2k: float = DEFAULT_CONVECTION_W_M2K,
) -> FloatArray:
    """g: the probes' response (sensor first, then the depth line) to a unit initial excess
    over ambient, no flux, ambient 0; shape (n_steps + 1, 1 + depths)."""
    depths = _probe_depths_m(wagon, settings.probe_spacing_m)
    probes = np.vstack([np.array([wagon.sensor_point_m]), _probe_points_m(wagon, depths)])
    res = model.simulate(
        dt_s=settings.dt_s,
        flux_w_m2=np.zeros(settings.n_steps),
        initial_c=1.0,
        ambient_c=0.0,
        h_w_m2k=_h(convection_w_m2k),
        probes_m=probes,
        damped_steps=1,
    )
    return np.array(res.probe_c)


def superposed_curves(
    run: ManoeuvreResult,
    decay: FloatArray,
    *,
    flux_scale: float = 1.0,
    t0_c: float | None = None,
) -> FloatArray:
    """The probes' curves (sensor first, then the depth line) of ``run`` with its flux times
    ``flux_scale`` and/or another initial temperature, by superposition (exact: the declared
    model is linear). ``decay`` from :func:`free_decay_response` with the run's h and mesh."""
    ta = run.ambient_c
    t0_ref = run.manoeuvre.t0_c
    t0 = t0_ref if t0_c is None else t0_c
    ref = np.column_stack([run.sensor_c, run.depth_c])
    free_ref = ta + (t0_ref - ta) * decay
    return ta + (t0 - ta) * decay + flux_scale * (ref - free_ref)


# --------------------------------------------------------------------------------------------
# The study


@dataclass(frozen=True)
class StudyRow:
    """Time to peak and rise of the sensor for one manoeuvre and one parameter value (the
    other parameters at their reproduction values)."""

    manoeuvre: str
    parameter: str
    """sensor_depth_m, convection_w_m2k, cylinder_diameter_m, flux_scale or t0_c."""
    value: float
    time_to_peak_s: float
    sensor_rise_k: float
    peaked: bool
    """False: the sensor still rose at the end of the horizon (time to peak = horizon)."""
    method: str
    """probe (a probe of the reproduction's run), run (its own simulation) or superposition."""


@dataclass(frozen=True)
class RemeshCheck:
    """A sensor at ``depth_m`` read on the mesh graded towards the registry's seat (probe)
    against a mesh graded towards ``depth_m`` itself (remesh)."""

    manoeuvre: str
    depth_m: float
    probe_time_to_peak_s: float
    remesh_time_to_peak_s: float
    probe_rise_k: float
    remesh_rise_k: float
    remesh_nodes: int


@dataclass
class Study:
    rows: list[StudyRow]
    remesh: list[RemeshCheck] = field(default_factory=list)
    seconds: float = 0.0

    def select(self, parameter: str, manoeuvre: str | None = None) -> list[StudyRow]:
        return [
            r
            for r in self.rows
            if r.parameter == parameter and (manoeuvre is None or r.manoeuvre == manoeuvre)
        ]

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for row in self.rows:
            out.setdefault(row.parameter, []).append(
                {
                    "manoeuvre": row.manoeuvre,
                    "value": row.value,
                    "time_to_peak_s": round(row.time_to_peak_s, 2),
                    "sensor_rise_k": round(row.sensor_rise_k, 3),
                    "peaked": row.peaked,
                    "method": row.method,
                }
            )
        out["remesh_check"] = [
            {k: (round(v, 4) if isinstance(v, float) else v) for k, v in vars(c).items()}
            for c in self.remesh
        ]
        out["seconds"] = round(self.seconds, 2)
        return out


def remesh_check(
    rep: PaperReproduction,
    depths_m: Sequence[float] = (0.045, 0.065),
    manoeuvre: str = "A",
    horizon_s: float = 600.0,
) -> list[RemeshCheck]:
    """Re-mesh towards each depth and compare the sensor there with the reproduction's probe.

    The re-meshed runs stop at ``horizon_s`` (the peak is long past; a maximum before the end
    does not depend on what comes after it).
    """
    run = rep.runs[manoeuvre]
    t_probe, rise_probe, _ = run.depth_peaks()
    settings = dataclasses.replace(rep.settings, horizon_s=horizon_s)

    def job(depth: float) -> Callable[[], RemeshCheck]:
        def go() -> RemeshCheck:
            wagon = dataclasses.replace(rep.wagon, sensor_depth_m=float(depth))
            model = BlockModel(
                wagon.geometry,
                wagon.block_material,
                element=settings.element,
                refinement=settings.refinement,
                sensor_m=wagon.sensor_point_m,
            )
            res = simulate_manoeuvre(
                model, wagon, manoeuvre, run.manoeuvre, settings=settings, keep_fields=False
            )
            k = int(np.argmin(np.abs(run.depths_m - depth)))
            return RemeshCheck(
                manoeuvre=manoeuvre,
                depth_m=float(depth),
                probe_time_to_peak_s=float(t_probe[k]),
                remesh_time_to_peak_s=res.time_to_peak_s,
                probe_rise_k=float(rise_probe[k]),
                remesh_rise_k=res.sensor_rise_k,
                remesh_nodes=model.n_nodes,
            )

        return go

    return _parallel([job(d) for d in depths_m], rep.settings.workers)


def _row(
    name: str, parameter: str, value: float, t: float, rise: float, interior: bool, method: str
) -> StudyRow:
    return StudyRow(name, parameter, float(value), float(t), float(rise), bool(interior), method)


def run_study(
    rep: PaperReproduction,
    *,
    depths_m: Sequence[float] = STUDY_DEPTHS_M,
    convections_w_m2k: Sequence[float] = STUDY_CONVECTION_W_M2K,
    bores_m: Sequence[float] = STUDY_BORES_M,
    remesh_depths_m: Sequence[float] = (0.045, 0.065),
) -> Study:
    """How the time to peak and the sensor's rise depend on sensor depth, convection and
    cylinder bore (the paper's conclusion), plus two what-ifs: eq. 6 as the paper prints it
    (flux x 1/mu) and A and B with each other's T0. Every row varies one parameter.

    Depth: the reproduction's probes. Convection: one run per value and manoeuvre (a new
    factorisation per h, on the same mesh). Bore, eq. 6 and T0: superposition on the
    reproduction's runs with one free-decay run. ``remesh_depths_m``: see :func:`remesh_check`.
    """
    started = time.perf_counter()
    wagon, settings, model = rep.wagon, rep.settings, rep.model
    rows: list[StudyRow] = []
    for name, run in rep.runs.items():
        t, rise, interior = run.depth_peaks()
        for depth in depths_m:
            k = int(np.argmin(np.abs(run.depths_m - depth)))
            if abs(run.depths_m[k] - depth) > 1e-9:
                raise ValueError(f"run_study: no probe at depth {depth} m")
            rows.append(_row(name, "sensor_depth_m", depth, t[k], rise[k], interior[k], "probe"))

    jobs: list[Callable[[], Any]] = [lambda: free_decay_response(model, wagon, settings=settings)]
    h_jobs: list[tuple[str, float]] = []
    for h in convections_w_m2k:
        for name, run in rep.runs.items():
            if math.isclose(h, run.convection_w_m2k):
                continue
            h_jobs.append((name, float(h)))

    def h_job(name: str, h: float) -> Callable[[], ManoeuvreResult]:
        return lambda: simulate_manoeuvre(
            model,
            wagon,
            name,
            rep.runs[name].manoeuvre,
            settings=settings,
            convection_w_m2k=h,
            keep_fields=False,
        )

    jobs += [h_job(n, h) for n, h in h_jobs]
    outputs = _parallel(jobs, settings.workers)
    decay: FloatArray = outputs[0]
    h_runs = {key: out for key, out in zip(h_jobs, outputs[1:], strict=True)}
    for h in convections_w_m2k:
        for name, run in rep.runs.items():
            other = run if math.isclose(h, run.convection_w_m2k) else h_runs[(name, float(h))]
            method = "probe" if other is run else "run"
            rows.append(
                _row(
                    name,
                    "convection_w_m2k",
                    h,
                    other.time_to_peak_s,
                    other.sensor_rise_k,
                    other.peak.interior,
                    method,
                )
            )

    def superposed(
        run: ManoeuvreResult, scale: float, t0: float | None
    ) -> tuple[float, float, bool]:
        curves = superposed_curves(run, decay, flux_scale=scale, t0_c=t0)
        peak = find_peak(run.time_s, curves[:, 0])
        base = run.manoeuvre.t0_c if t0 is None else t0
        return peak.time_s, peak.value_c - base, peak.interior

    for name, run in rep.runs.items():
        flux_ref = run.heat.block_flux_w_m2
        for bore in bores_m:
            other = dataclasses.replace(wagon, cylinder_diameter_m=float(bore))
            scale = event_heat_input(other, run.manoeuvre).block_flux_w_m2 / flux_ref
            rows.append(
                _row(
                    name,
                    "cylinder_diameter_m",
                    bore,
                    *superposed(run, scale, None),
                    "superposition",
                )
            )
        scale = 1.0 / wagon.friction_coefficient
        rows.append(_row(name, "flux_scale", scale, *superposed(run, scale, None), "superposition"))
        for other_name, other_run in rep.runs.items():
            if other_name != name:
                t0 = other_run.manoeuvre.t0_c
                rows.append(_row(name, "t0_c", t0, *superposed(run, 1.0, t0), "superposition"))

    remesh = remesh_check(rep, remesh_depths_m) if remesh_depths_m else []
    return Study(rows=rows, remesh=remesh, seconds=time.perf_counter() - started)


# --------------------------------------------------------------------------------------------
# Human output


def print_report(rep: PaperReproduction, console: Any = None) -> None:
    """Rich tables: heat input, results against the paper, calibration."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    names = list(rep.runs)
    heat = Table(title="Heat input (paper eqs. 1-12, eq. 6 with F_t; registry defaults)")
    heat.add_column("quantity")
    for name in names:
        heat.add_column(name, justify="right")
    rows: list[tuple[str, Callable[[ManoeuvreResult], str]]] = [
        ("T0 / ambient, C", lambda r: f"{r.manoeuvre.t0_c:g} / {r.ambient_c:g}"),
        ("duration, s", lambda r: f"{r.manoeuvre.duration_s:g}"),
        ("d_f / Delta t, m/s", lambda r: f"{r.manoeuvre.mean_speed_m_s:.2f}"),
        ("p_mean, bar", lambda r: f"{r.manoeuvre.p_mean_bar:g}"),
        ("F_cyl, N", lambda r: f"{r.heat.forces.cylinder_force_n:,.0f}"),
        ("F_bogie, N", lambda r: f"{r.heat.forces.bogie_force_n:,.0f}"),
        ("F_block, N", lambda r: f"{r.heat.forces.block_force_n:,.1f}"),
        ("F_t = mu F_block, N", lambda r: f"{r.heat.forces.friction_force_n:,.1f}"),
        ("P = F_t d_f / Delta t, W", lambda r: f"{r.heat.power_w:,.0f}"),
        ("Phi_th, W/m^2", lambda r: f"{r.heat.frictional_flux_w_m2:,.0f}"),
        ("alpha (wheel share)", lambda r: f"{r.heat.alpha:.4f}"),
        ("Phi_b, W/m^2", lambda r: f"{r.block_flux_w_m2:,.0f}"),
        ("energy into block, kJ", lambda r: f"{r.energy_in_j / 1e3:.1f}"),
    ]
    for label, fmt in rows:
        heat.add_row(label, *(fmt(rep.runs[n]) for n in names))
    console.print(heat)

    res = Table(title=f"Sensor at {rep.wagon.sensor_depth_m:g} m and friction face")
    res.add_column("quantity")
    for name in names:
        res.add_column(name, justify="right")
    rows = [
        ("time to peak, s", lambda r: f"{r.time_to_peak_s:.1f}"),
        ("paper, s", lambda r: f"{r.paper_time_to_peak_s:g}"),
        ("difference", lambda r: f"{100 * (r.time_to_peak_rel_error or 0):+.1f} %"),
        ("sensor peak, C", lambda r: f"{r.sensor_peak_c:.2f}"),
        ("sensor rise, K", lambda r: f"{r.sensor_rise_k:.2f}"),
        (
            "contact max / mean at end of braking, C",
            lambda r: f"{r.contact_max_end_c:.1f} / {r.contact_mean_end_c:.1f}",
        ),
        (
            "contact max / mean at sensor peak, C",
            lambda r: f"{r.contact_max_at_peak_c:.1f} / {r.contact_mean_at_peak_c:.1f}",
        ),
        ("run, s", lambda r: f"{r.seconds:.1f}"),
    ]
    for label, fmt in rows:
        res.add_row(label, *(fmt(rep.runs[n]) for n in names))
    console.print(res)

    cal = rep.calibration
    table = Table(title=f"Calibrated sensor depth: {1000 * cal.sensor_depth_m:.2f} mm")
    for col in ("manoeuvre", "time to peak, s", "paper, s", "difference", "rise, K"):
        table.add_column(col, justify="right")
    for name in cal.time_to_peak_s:
        table.add_row(
            name,
            f"{cal.time_to_peak_s[name]:.1f}",
            f"{cal.paper_time_to_peak_s[name]:g}",
            f"{100 * cal.rel_error[name]:+.1f} %",
            f"{cal.sensor_rise_k[name]:.2f}",
        )
    console.print(table)
    console.print(
        f"{rep.model.n_nodes:,} nodes ({rep.settings.element}), "
        f"{rep.settings.n_steps} steps of {rep.settings.dt_s:g} s; "
        f"mesh {rep.seconds_mesh:.1f} s, total {rep.seconds:.1f} s"
    )


_PARAMETER_LABELS = {
    "sensor_depth_m": ("sensor depth", "depth, m", "{:.3f}"),
    "convection_w_m2k": ("convection on every surface but the friction face", "h, W/m2K", "{:g}"),
    "cylinder_diameter_m": ("brake cylinder bore", "bore, m", "{:.3f}"),
    "flux_scale": (
        "eq. 6 as the paper prints it (F_block for F_t: flux x 1/mu)",
        "flux x",
        "{:.2f}",
    ),
    "t0_c": ("A and B with each other's T0", "T0, C", "{:g}"),
}


def print_study(study: Study, console: Any = None) -> None:
    """Rich tables of the study: one per parameter, A and B side by side."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    for parameter, (title, label, fmt) in _PARAMETER_LABELS.items():
        rows = study.select(parameter)
        if not rows:
            continue
        table = Table(title=f"Study: {title}")
        table.add_column(label, justify="right", no_wrap=True)
        names = sorted({r.manoeuvre for r in rows})
        for name in names:
            table.add_column(f"{name} t_peak, s", justify="right")
            table.add_column(f"{name} rise, K", justify="right")
        table.add_column("method", no_wrap=True)
        if parameter == "t0_c":  # each manoeuvre with the other's T0: one row
            groups = [[r for r in rows if r.manoeuvre == name][:1] for name in names]
            keys: list[tuple[str, list[list[StudyRow]]]] = [("swapped", groups)]
        else:
            keys = [
                (
                    fmt.format(v),
                    [[r for r in rows if r.manoeuvre == n and r.value == v] for n in names],
                )
                for v in sorted({r.value for r in rows})
            ]
        for key, per_name in keys:
            cells = [key]
            method = ""
            for match in per_name:
                if not match:
                    cells += ["", ""]
                    continue
                r = match[0]
                mark = "" if r.peaked else " (rising)"
                cells += [f"{r.time_to_peak_s:.1f}{mark}", f"{r.sensor_rise_k:.2f}"]
                method = r.method
            table.add_row(*cells, method)
        console.print(table)
    if study.remesh:
        table = Table(title="Moving the probe vs re-meshing towards the depth (manoeuvre A)")
        for col in (
            "depth, m",
            "t_peak probe, s",
            "t_peak remesh, s",
            "rise probe, K",
            "rise remesh, K",
            "nodes",
        ):
            table.add_column(col, justify="right")
        for c in study.remesh:
            table.add_row(
                f"{c.depth_m:.3f}",
                f"{c.probe_time_to_peak_s:.2f}",
                f"{c.remesh_time_to_peak_s:.2f}",
                f"{c.probe_rise_k:.3f}",
                f"{c.remesh_rise_k:.3f}",
                f"{c.remesh_nodes:,}",
            )
        console.print(table)
    console.print(f"study: {study.seconds:.1f} s")


# --------------------------------------------------------------------------------------------
# Files


def write_outputs(
    rep: PaperReproduction, out_dir: str | Path, study: Study | None = None
) -> list[Path]:
    """The pictures (PNG) and fields (VTU) of the reproduction (and of the study) in ``out_dir``.

    Per manoeuvre X: ``paper_X_end_of_braking.png`` and ``paper_X_sensor_peak.png`` (the
    block's field; the paper's figures 4/5 and 7/8), ``paper_X_sensor.png`` (figures 6 and
    9), ``paper_X_fields.vtu``; then ``paper_calibration.png`` and ``paper_study.png``.
    """
    from fleetbrake.paper import plots  # matplotlib only when pictures are wanted
    from fleetbrake.paper.export import write_paper_fields

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mesh = rep.model.mesh
    geometry = rep.wagon.geometry
    sensor = rep.wagon.sensor_point_m
    cal = rep.calibration
    files: list[Path] = []
    for name, run in rep.runs.items():
        if run.field_end_c is not None:
            files.append(
                plots.plot_block_field(
                    mesh,
                    run.field_end_c,
                    geometry,
                    out / f"paper_{name}_end_of_braking.png",
                    title=f"Manoeuvre {name}: block temperature at the end of braking "
                    f"(t = {run.manoeuvre.duration_s:g} s)",
                    sensor_m=sensor,
                )
            )
        if run.field_peak_c is not None:
            files.append(
                plots.plot_block_field(
                    mesh,
                    run.field_peak_c,
                    geometry,
                    out / f"paper_{name}_sensor_peak.png",
                    title=f"Manoeuvre {name}: block temperature at the sensor's maximum "
                    f"(t = {run.field_peak_time_s:g} s)",
                    sensor_m=sensor,
                )
            )
        files.append(
            plots.plot_sensor_curve(
                run,
                out / f"paper_{name}_sensor.png",
                extra_depths_m={
                    f"calibrated depth {cal.sensor_depth_m * 1e3:.1f} mm": cal.sensor_depth_m
                },
            )
        )
    files.append(
        plots.plot_calibration(
            cal, out / "paper_calibration.png", registry_depth_m=rep.wagon.sensor_depth_m
        )
    )
    if study is not None:
        files.append(plots.plot_study(study, out / "paper_study.png"))
    files.extend(write_paper_fields(rep, out))
    return files
