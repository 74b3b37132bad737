"""``fleetbrake bench rom``: the reduced model against the full model, in one run.

Events are 700-second windows (a braking of random strength and length from a random block
temperature, then cooling). The reduced model simulates all of them at once (Rust kernel,
both cores); the full finite-element model simulates a few of them on the same mesh, and
its per-event time gives ``speedup_vs_full``. ``max_error_*`` compare the two on those
events integrated with the same scheme (Crank-Nicolson at 1 s steps): what is left is the
reduction's error. ``time_integration_face_mean_k`` is how far the full model's
Crank-Nicolson is from the reduced model's exact integration (the full model's own time
error after the steps of flux, not the reduction's).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass

import numpy as np

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.rom import ReducedModel
from fleetbrake.model.thermal import BlockModel

WINDOW_S = 700


@dataclass(frozen=True)
class RomBenchmark:
    events: int
    seconds: float
    events_per_s: float
    full_events: int
    full_seconds_per_event: float
    rom_seconds_per_event: float
    speedup_vs_full: float
    max_error_sensor_k: float
    max_error_face_mean_k: float
    max_error_face_max_k: float
    time_integration_sensor_k: float
    time_integration_face_mean_k: float
    order: int
    nodes: int
    refinement: float
    rom_build_or_load_s: float


def random_events(n_events: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Fluxes (E, 700) of a braking of 15-120 s at 5-60 kW/m^2, and start temperatures."""
    rng = np.random.default_rng(seed)
    duration = rng.integers(15, 120, n_events)
    level = rng.uniform(5e3, 6e4, n_events)
    flux = np.where(np.arange(WINDOW_S)[None, :] < duration[:, None], level[:, None], 0.0)
    return flux, rng.uniform(5.0, 80.0, n_events)


def run_rom_benchmark(
    n_events: int = 20_000, full_events: int = 3, refinement: float = 1.0, ambient_c: float = 10.0
) -> RomBenchmark:
    wagon = WagonConfig(wagon_id="BENCH-0001")
    t0 = time.perf_counter()
    rom = ReducedModel.for_wagon(wagon, refinement=refinement)
    build_s = time.perf_counter() - t0
    flux, start_c = random_events(n_events)
    rom.simulate_batch(dt_s=1.0, flux_w_m2=flux[:64], initial_c=start_c[:64], ambient_c=ambient_c)
    t0 = time.perf_counter()
    batch = rom.simulate_batch(dt_s=1.0, flux_w_m2=flux, initial_c=start_c, ambient_c=ambient_c)
    seconds = time.perf_counter() - t0
    model = BlockModel(
        wagon.geometry, wagon.block_material, refinement=refinement, sensor_m=wagon.sensor_point_m
    )
    errors = {"sensor": 0.0, "mean": 0.0, "max": 0.0, "t_sensor": 0.0, "t_mean": 0.0}
    full_seconds = 0.0
    for e in range(full_events):
        t0 = time.perf_counter()
        full = model.simulate(
            dt_s=1.0,
            flux_w_m2=flux[e],
            initial_c=float(start_c[e]),
            ambient_c=ambient_c,
            probes_m=[wagon.sensor_point_m],
        )
        full_seconds += time.perf_counter() - t0
        same = rom.simulate(
            dt_s=1.0,
            flux_w_m2=flux[e],
            initial_c=float(start_c[e]),
            ambient_c=ambient_c,
            scheme="crank-nicolson",
        )
        pairs = {
            "sensor": (full.probe_c[:, 0], same.probe_c[:, 0]),
            "mean": (full.face_mean_c, same.face_mean_c),
            "max": (full.face_max_c, same.face_max_c),
            "t_sensor": (full.probe_c[:, 0], batch.probe_c[e, :, 0]),
            "t_mean": (full.face_mean_c, batch.face_mean_c[e]),
        }
        for key, (a, b) in pairs.items():
            errors[key] = max(errors[key], float(np.abs(a - b).max()))
    full_per_event = full_seconds / full_events
    rom_per_event = seconds / n_events
    return RomBenchmark(
        events=n_events,
        seconds=round(seconds, 4),
        events_per_s=round(n_events / seconds, 1),
        full_events=full_events,
        full_seconds_per_event=round(full_per_event, 4),
        rom_seconds_per_event=rom_per_event,
        speedup_vs_full=round(full_per_event / rom_per_event, 1),
        max_error_sensor_k=round(errors["sensor"], 5),
        max_error_face_mean_k=round(errors["mean"], 5),
        max_error_face_max_k=round(errors["max"], 5),
        time_integration_sensor_k=round(errors["t_sensor"], 5),
        time_integration_face_mean_k=round(errors["t_mean"], 5),
        order=rom.order,
        nodes=model.n_nodes,
        refinement=refinement,
        rom_build_or_load_s=round(build_s, 3),
    )


def report(result: RomBenchmark, as_json: bool) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="reduced model vs full model (700 s event windows)")
    table.add_column("figure")
    table.add_column("value", justify="right")
    for key, value in asdict(result).items():
        table.add_row(key, f"{value}")
    Console().print(table)
    if as_json:
        print(json.dumps(asdict(result)))
