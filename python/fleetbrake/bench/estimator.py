"""``bench estimator``: the virtual sensor's filter and smoother, the Rust kernel alone and end
to end, beside the floor the project holds it to.

Inputs are generated (not timed) a chunk of wagons at a time: each wagon runs a day as the
synthetic fleet's wagons do (:func:`fleetbrake.synth.operation.operate`: standing, trips with
slowdowns, drag brakings and stops), its unit logging while it moves (logging sessions that
end ``sleep_after_s`` after it stops), the thermistor reading the declared model's block (the
reduced model at ``refinement``) with 0.1 K of noise and a reading missing in
``missing_fraction`` of the seconds. ``distinct_days`` operations are generated and shared
round-robin by the wagons (each with its own noise, gaps and starting temperature): the
filter's cost does not depend on which day a wagon had.

Then, on the same problems, the filter and the smoother (every output: filtered and smoothed
contact mean and maximum with their bands, the unexplained power, the innovations):

* the kernel: the Rust kernel, a chunk of wagons per call (wagons in parallel on the cores),
  timed with and without the preparation of the problems from the series
  (:func:`fleetbrake.model.estimator.prepare`, numpy, serial in this process); wagons are
  prepared and estimated ``chunk`` at a time (memory stays that of a chunk);
* end to end, as ``run`` estimates: the same series, ``chunk`` wagons a partition, handed to
  the local engine's ``workers`` processes (one Rayon thread each), each partition prepared
  and estimated by the Rust kernel in its worker (the clock from the first partition handed
  out to the last result back, the pool started and this module imported in it first; CPU
  time the workers' own, without shipping the series).

A wagon-second is one logged second of one wagon. Each figure is given per second of the clock
and per second of CPU time (of this process, all its threads; of the workers end to end): on a
machine busy with other work the latter is the steadier, and times the cores it is what an idle
machine would give. The floor, :data:`FLOOR_WAGON_SECONDS_PER_S` end to end on two cores,
stands beside the end-to-end figure. That the kernel's estimates are the numpy reference's is
the tests' to check (``tests/test_estimator.py``), not the benchmark's.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fleetbrake.bench import BenchConfigError
from fleetbrake.engine import default_workers, make_engine
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.estimator import (
    EstimatorConfig,
    EstimatorNoise,
    WagonSeries,
    estimate,
    prepare,
    rust_available,
)
from fleetbrake.model.rom import DEFAULT_REFINEMENT, ReducedModel
from fleetbrake.model.timeline import simulate_timeline
from fleetbrake.synth.operation import operate, sessions

__all__ = [
    "FLOOR_WAGON_SECONDS_PER_S",
    "NOISE_K",
    "SeriesMaker",
    "bench_estimator",
    "print_figures",
]

NOISE_K = 0.1
"""The generated thermistor's noise, K (the estimator's σ_v in the benchmark)."""
DAY_S = 86_400
FLOOR_WAGON_SECONDS_PER_S = 500_000
"""The floor the estimator is held to: logged wagon-seconds per second of the clock, end to
end (prepare and kernel, as ``run`` estimates) on two cores (``docs/estimator.md``)."""
FLOOR_CORES = 2

Partition = tuple[ReducedModel, WagonConfig, EstimatorConfig, list[WagonSeries]]


def _prepare_and_estimate(item: Partition) -> tuple[int, float]:
    """A partition of the end-to-end pass (a worker's): its wagons prepared and estimated by
    the Rust kernel; returns the logged wagon-seconds and the worker's CPU seconds for them."""
    rom, wagon, config, series = item
    if not series:
        return 0, 0.0  # the warm-up: this module imported in the worker
    c0 = time.process_time()
    problems = [prepare(rom, wagon, s, config=config) for s in series]
    estimates = estimate(problems, config=config)
    assert len(estimates) == len(series)
    return sum(s.time_s.size for s in series), time.process_time() - c0


class SeriesMaker:
    """One logged day per wagon (see the module docstring), made on demand: ``distinct_days``
    operations shared round-robin, each wagon with its own air, start, noise and gaps."""

    def __init__(
        self,
        rom: ReducedModel,
        wagon: WagonConfig,
        *,
        distinct_days: int = 8,
        sleep_after_s: int = 600,
        missing_fraction: float = 0.001,
        seed: int = 0,
    ) -> None:
        self.rom, self.wagon, self.seed = rom, wagon, seed
        self.missing_fraction = missing_fraction
        self.days = []
        for d in range(distinct_days):
            op = operate(
                np.random.default_rng([seed, d]), DAY_S, wagon, 70_000.0, (45.0, 7.0, 300.0)
            )
            logged = np.zeros(DAY_S, dtype=bool)
            for first, stop in sessions(op.speed_kmh, sleep_after_s):
                logged[first:stop] = True
            self.days.append((op, np.flatnonzero(logged)))

    def series(self, w: int) -> WagonSeries:
        rng = np.random.default_rng([self.seed, 1_000_000 + w])
        op, rows = self.days[w % len(self.days)]
        ambient_c = float(rng.uniform(0.0, 25.0))
        block = simulate_timeline(
            self.rom,
            self.wagon,
            dt_s=1.0,
            p_bar=op.pressure_bar,
            speed_kmh=op.speed_kmh,
            ambient_c=ambient_c,
            initial_c=ambient_c + float(rng.uniform(0.0, 5.0)),
            keep_state=False,
        )
        reading = block.sensor_c[rows] + rng.normal(0.0, NOISE_K, rows.size)
        reading[rng.random(rows.size) < self.missing_fraction] = np.nan
        return WagonSeries.of(
            time_s=rows.astype(np.float64),
            p_bar=op.pressure_bar[rows],
            speed_kmh=op.speed_kmh[rows],
            ambient_c=ambient_c,
            reading_c=reading,
            wagon_id=f"BENCH-{w:04d}",
        )


@dataclass
class _KernelPass:
    """What the kernel's pass over the wagons measured (and the partitions it kept for the
    end-to-end pass)."""

    seconds: int = 0
    grid_seconds: int = 0
    generate_s: float = 0.0
    prepare_s: float = 0.0
    prepare_cpu_s: float = 0.0
    rust_s: float = 0.0
    rust_cpu_s: float = 0.0
    steady_seconds: float = 0.0
    manoeuvre_seconds: int = 0
    partitions: list[Partition] = field(default_factory=list)


def _kernel_pass(
    maker: SeriesMaker, config: EstimatorConfig, wagons: int, chunk: int, keep: bool
) -> _KernelPass:
    """The wagons made, prepared and estimated by the kernel a chunk at a time (memory: a
    chunk's); ``keep``: their series kept as the end-to-end pass's partitions."""
    done = _KernelPass()
    rom, wagon = maker.rom, maker.wagon
    for start in range(0, wagons, chunk):
        t0 = time.perf_counter()
        series = [maker.series(w) for w in range(start, min(start + chunk, wagons))]
        done.generate_s += time.perf_counter() - t0
        if keep:
            done.partitions.append((rom, wagon, config, series))
        done.seconds += sum(s.time_s.size for s in series)
        t0, c0 = time.perf_counter(), time.process_time()
        problems = [prepare(rom, wagon, s, config=config) for s in series]
        done.prepare_s += time.perf_counter() - t0
        done.prepare_cpu_s += time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()
        estimates = estimate(problems, config=config)
        done.rust_s += time.perf_counter() - t0
        done.rust_cpu_s += time.process_time() - c0
        done.steady_seconds += sum(
            e.frozen_fraction * p.n_samples for p, e in zip(problems, estimates, strict=True)
        )
        done.manoeuvre_seconds += sum(
            int(e.manoeuvre.sum()) for e in estimates if e.manoeuvre is not None
        )
        done.grid_seconds += sum(p.n_samples for p in problems)
    return done


def _end_to_end(partitions: list[Partition], workers: int, seconds: int) -> tuple[float, float]:
    """The end-to-end pass on the local engine's ``workers`` processes: its clock seconds and
    the workers' CPU seconds (NaN without workers)."""
    if workers <= 0:
        return float("nan"), float("nan")
    rom, wagon, config, _ = partitions[0]
    with make_engine("local", workers) as engine:
        engine.start()
        list(engine.map(_prepare_and_estimate, [(rom, wagon, config, [])] * workers))
        t0 = time.perf_counter()
        done = list(engine.map(_prepare_and_estimate, partitions))
        end_s = time.perf_counter() - t0
    if sum(n for n, _ in done) != seconds:
        raise BenchConfigError("bench estimator: the end-to-end pass lost wagon-seconds")
    return end_s, sum(c for _, c in done)


def _rate(n: int, s: float) -> float:
    return round(n / s, 1) if s > 0 else float("nan")


def bench_estimator(
    *,
    wagons: int = 100,
    refinement: float = DEFAULT_REFINEMENT,
    config: EstimatorConfig | None = None,
    distinct_days: int = 8,
    seed: int = 0,
    chunk: int = 16,
    rom: ReducedModel | None = None,
    workers: int | None = None,
    show: bool = True,
    echo: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Time the Rust kernel and the end-to-end pass on ``wagons`` wagon-days; returns the
    figures (and prints them beside the floor when ``show``). ``rom``: the reduced model to
    use (default: the reference wagon's at ``refinement``, from the cache). ``workers``: the
    end-to-end pass's processes (None: the cores this process may use; 0: no end-to-end
    pass)."""
    if wagons < 1 or chunk < 1:
        raise BenchConfigError(
            f"bench estimator: need wagons >= 1 and chunk >= 1, got wagons {wagons}, chunk {chunk}"
        )
    if not rust_available():
        raise BenchConfigError(
            "bench estimator: this build of fleetbrake._ext has no estimator kernel "
            "(rebuild: maturin develop --release)"
        )
    config = config or EstimatorConfig(noise=EstimatorNoise(measurement_k=NOISE_K))
    wagon = WagonConfig(wagon_id="BENCH-0000")
    t0 = time.perf_counter()
    if rom is None:
        rom = ReducedModel.for_wagon(wagon, refinement=refinement)
    model_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    maker = SeriesMaker(rom, wagon, distinct_days=min(distinct_days, wagons), seed=seed)
    generate_s = time.perf_counter() - t0
    load_at_start = os.getloadavg()[0]
    workers = default_workers() if workers is None else workers
    kernel = _kernel_pass(maker, config, wagons, chunk, keep=workers > 0)
    end_s, end_cpu_s = _end_to_end(kernel.partitions, workers, kernel.seconds)
    kernel.partitions.clear()
    seconds = kernel.seconds
    figures: dict[str, Any] = {
        "wagons": wagons,
        "wagon_seconds": seconds,
        "order": rom.order,
        "face_nodes": int(rom.c_out.shape[0] - rom.n_probes - 1),
        "refinement": refinement,
        "smoothed": True,
        "rust_s": round(kernel.rust_s, 3),
        "rust_wagon_seconds_per_s": _rate(seconds, kernel.rust_s),
        "rust_with_prepare_wagon_seconds_per_s": _rate(seconds, kernel.rust_s + kernel.prepare_s),
        "rust_cpu_s": round(kernel.rust_cpu_s, 3),
        "rust_wagon_seconds_per_cpu_s": _rate(seconds, kernel.rust_cpu_s),
        "end_to_end_workers": workers,
        "end_to_end_s": round(end_s, 3),
        "end_to_end_wagon_seconds_per_s": _rate(seconds, end_s),
        "end_to_end_cpu_s": round(end_cpu_s, 3),
        "end_to_end_wagon_seconds_per_cpu_s": _rate(seconds, end_cpu_s),
        "floor_wagon_seconds_per_s": FLOOR_WAGON_SECONDS_PER_S,
        "floor_cores": FLOOR_CORES,
        "prepare_s": round(kernel.prepare_s, 3),
        "prepare_cpu_s": round(kernel.prepare_cpu_s, 3),
        "steady_fraction": round(kernel.steady_seconds / max(kernel.grid_seconds, 1), 3),
        "manoeuvre_fraction": round(kernel.manoeuvre_seconds / max(seconds, 1), 4),
        "steady_tolerance": config.steady_tolerance,
        "smoother_tolerance": config.smoother_tolerance,
        "generate_s": round(generate_s + kernel.generate_s, 1),
        "model_s": round(model_s, 2),
        "cpus": os.cpu_count(),
        "load_avg_1min_at_start": round(load_at_start, 2),
    }
    if show:
        print_figures(figures, echo)
    return figures


def print_figures(figures: dict[str, Any], echo: Callable[[str], None] = print) -> None:
    """The kernel alone and end to end, beside the floor, for people."""
    echo(
        f"virtual sensor, filter + smoother: {figures['wagons']} wagon-days, "
        f"{figures['wagon_seconds']:,} logged wagon-seconds; reduced model of order "
        f"{figures['order']} ({figures['face_nodes']} face nodes), refinement "
        f"{figures['refinement']:g}; inputs generated in {figures['generate_s']} s (not timed)"
    )
    floor = figures["floor_wagon_seconds_per_s"]
    rows = [
        ("", "wagon-s/s", "per CPU-second", "floor"),
        (
            "kernel",
            f"{figures['rust_wagon_seconds_per_s']:,.0f}",
            f"{figures['rust_wagon_seconds_per_cpu_s']:,.0f}",
            "",
        ),
        ("kernel + prepare", f"{figures['rust_with_prepare_wagon_seconds_per_s']:,.0f}", "", ""),
    ]
    if figures["end_to_end_workers"] > 0:
        rate = figures["end_to_end_wagon_seconds_per_s"]
        rows.append(
            (
                f"end to end, {figures['end_to_end_workers']} workers",
                f"{rate:,.0f}",
                f"{figures['end_to_end_wagon_seconds_per_cpu_s']:,.0f}",
                f"{floor:,} on {figures['floor_cores']} cores ({rate / floor:.2f}x)",
            )
        )
    for name, a, b, c in rows:
        echo(f"  {name:<22} {a:>12} {b:>15}   {c}".rstrip())
    echo(
        f"covariance steady in {figures['steady_fraction']:.0%} of the seconds, the power "
        f"noise in its manoeuvre mode in {figures['manoeuvre_fraction']:.1%}; prepare "
        f"{figures['prepare_s']} s; {figures['cpus']} CPUs, load average "
        f"{figures['load_avg_1min_at_start']} at start"
    )
