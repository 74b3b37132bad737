"""The study the paper's conclusion asks for: how the sensor's time to peak and rise depend on
its depth, the convection and the brake cylinder's bore, with two what-ifs (eq. 6 as the paper
prints it, A and B with each other's T0), and the check that moving the probe is as good as
re-meshing towards the depth (``fleetbrake paper --study``).

::

    from fleetbrake.paper.reproduction import reproduce_paper
    from fleetbrake.paper.study import run_study

    study = run_study(reproduce_paper())
    study.select("convection_w_m2k", "A")      # one StudyRow per value
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fleetbrake.model.physics import event_heat_input
from fleetbrake.model.thermal import BlockModel
from fleetbrake.paper.peaks import find_peak
from fleetbrake.paper.reproduction import (
    free_decay_response,
    run_jobs,
    simulate_manoeuvre,
    superposed_curves,
)
from fleetbrake.paper.results import (
    ManoeuvreResult,
    PaperReproduction,
    RemeshCheck,
    Study,
    StudyRow,
)
from fleetbrake.paper.settings import STUDY_BORES_M, STUDY_CONVECTION_W_M2K, STUDY_DEPTHS_M

__all__ = ["remesh_check", "run_study"]

FloatArray = NDArray[np.float64]


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

    return run_jobs([job(d) for d in depths_m], rep.settings.workers)


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
    outputs = run_jobs(jobs, settings.workers)
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
