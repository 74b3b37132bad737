"""The paper's manoeuvres A and B in the declared model and a calibration of the sensor depth
(``fleetbrake paper``); the study its conclusion asks for is in
:mod:`fleetbrake.paper.study`, the results' types in :mod:`fleetbrake.paper.results`.

Usage::

    from fleetbrake.paper.reproduction import reproduce_paper
    from fleetbrake.paper.study import run_study

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
seat (0.055 m); :func:`fleetbrake.paper.study.remesh_check` measures what re-meshing towards another depth would
change (a few tenths of a second in the time to peak: see ``docs/paper-reproduction.md``).

Linearity. The declared model is linear (constant properties, h and ambient constant), so
with u = T - T_amb the response is linear in (initial excess, flux). One extra run, the free
decay g of a unit initial excess (no flux, ambient 0), gives the sensor curve of any flux
scale and any T0 exactly: T = T_amb + (T0 - T_amb) g + s (T_ref - T_amb - (T0_ref - T_amb) g).
The study uses that for the cylinder bore (the bore only scales the flux), for eq. 6 as the
paper prints it (flux x 1/mu) and for swapping T0 between A and B; convection needs runs.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from fleetbrake.fleet.block import DEFAULT_CONVECTION_W_M2K, BlockGeometry, sensor_point_m
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.physics import (
    PAPER_MANOEUVRES,
    Manoeuvre,
    event_heat_input,
    pulse_flux_series_w_m2,
)
from fleetbrake.model.thermal import AIR_FACES, BlockModel, SimulationResult
from fleetbrake.paper.peaks import find_peak
from fleetbrake.paper.results import Calibration, ManoeuvreResult, PaperReproduction
from fleetbrake.paper.settings import (
    CALIBRATION_RANGE_M,
    DEFAULT_SETTINGS,
    RunSettings,
    paper_wagon,
)

__all__ = [
    "calibrate_depth",
    "free_decay_response",
    "reproduce_paper",
    "run_jobs",
    "simulate_manoeuvre",
    "superposed_curves",
]

FloatArray = NDArray[np.float64]
T = TypeVar("T")


# --------------------------------------------------------------------------------------------
# Small helpers


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


def run_jobs(jobs: Sequence[Callable[[], T]], workers: int) -> list[T]:
    """Run the jobs side by side in up to ``workers`` threads (the core releases the GIL);
    their results in the jobs' order."""
    if workers <= 1 or len(jobs) <= 1:
        return [job() for job in jobs]
    with ThreadPoolExecutor(max_workers=min(workers, len(jobs))) as pool:
        futures = [pool.submit(job) for job in jobs]
        return [f.result() for f in futures]


def _h(convection_w_m2k: float) -> dict[str, float]:
    return dict.fromkeys(AIR_FACES, float(convection_w_m2k))


# --------------------------------------------------------------------------------------------
# One manoeuvre


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
    settings: RunSettings = DEFAULT_SETTINGS,
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
    sensor_x, sensor_y, sensor_z = wagon.sensor_point_m
    peak = find_peak(res.time_s, sensor_c)
    peak_step = min(n, round(peak.time_s / dt))
    field_end = field_peak = None
    if keep_fields:

        def field_at(step: int) -> FloatArray:
            return _field_at_step(
                model,
                res,
                step,
                dt_s=dt,
                flux=flux,
                ambient_c=ambient,
                h=h,
                probe=sensor,
                damped_steps=damped,
            )

        field_end = field_at(min(n, round(manoeuvre.duration_s / dt)))
        field_peak = field_at(peak_step)
    return ManoeuvreResult(
        name=name,
        manoeuvre=manoeuvre,
        heat=heat,
        convection_w_m2k=h_value,
        ambient_c=ambient,
        flux_scale=flux_scale,
        sensor_m=(float(sensor_x), float(sensor_y), float(sensor_z)),
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


def calibrate_depth(
    runs: Mapping[str, ManoeuvreResult],
    depth_range_m: tuple[float, float] = CALIBRATION_RANGE_M,
    resolution_m: float = 1.0e-5,
) -> Calibration:
    """The depth on the sensor's line minimising sum((t_peak(d) / t_paper - 1)^2) over ``runs``.

    The times to peak come from the probes every 0.5 mm of the runs (no new simulation),
    linear between probes; the search is on a grid of ``resolution_m`` over ``depth_range_m``.
    """
    papers = {
        name: float(paper_s) for name, run in runs.items() if (paper_s := run.paper_time_to_peak_s)
    }
    names = list(papers)
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
        cost += (np.interp(grid, d, curves[name][keep]) / papers[name] - 1.0) ** 2
    best = float(grid[int(np.argmin(cost))])
    t_best = {n: float(np.interp(best, d, curves[n][keep])) for n in names}
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


def reproduce_paper(
    wagon: WagonConfig | None = None,
    settings: RunSettings = DEFAULT_SETTINGS,
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

    results = run_jobs([job(n) for n in names], settings.workers)
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
    settings: RunSettings = DEFAULT_SETTINGS,
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
