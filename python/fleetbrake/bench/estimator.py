"""``bench estimator``: the virtual sensor's filter and smoother, Rust beside plain numpy.

Inputs are generated (not timed) a chunk of wagons at a time: each wagon runs a day as the synthetic fleet's
wagons do (:func:`fleetbrake.synth.operation.operate`: standing, trips with slowdowns, drag
brakings and stops), its unit logging while it moves (sessions that end ``sleep_after_s``
after it stops), the thermistor reading the declared model's block (the reduced model at
``refinement``) with 0.1 K of noise and a reading missing in ``missing_fraction`` of the
seconds. ``distinct_days`` operations are generated and shared round-robin by the wagons
(each with its own noise, gaps and starting temperature): the filter's cost does not depend
on which day a wagon had.

Then, on the same problems, the filter and the smoother (every output: filtered and smoothed
contact mean and maximum with their bands, the unexplained power, the innovations):

* ``rust``: the Rust kernel, all wagons in one call (wagons in parallel on the cores);
* ``numpy``: :func:`fleetbrake.model.estimator.run_numpy`, the plain numpy implementation of
  the same algorithm, on the first ``numpy_wagons`` wagons (it is slow);

wagons are prepared and estimated ``chunk`` at a time (memory stays that of a chunk);

each timed with and without the preparation of the problems from the series
(:func:`fleetbrake.model.estimator.prepare`, numpy, shared by both, serial in this process).
Then end to end as ``run`` estimates: the same series, ``chunk`` wagons a partition, handed to
the local engine's ``workers`` processes (one Rayon thread each), each partition prepared and
estimated by the Rust kernel in its worker (the clock from the first partition handed out to
the last result back, the pool started and this module imported in it first; CPU time the
workers' own, without shipping the series). A wagon-second is one
logged second of one wagon. Each figure is given per second of the clock and per second of
CPU time of this process (all its threads): on a machine busy with other work the latter is
the steadier, and times the cores it is what an idle machine would give. ``max_difference_k`` is the largest difference of the two
engines' contact temperatures on the wagons both ran.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from fleetbrake.bench import BenchConfigError
from fleetbrake.engine import default_workers, make_engine
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.estimator import (
    ContactEstimate,
    EstimatorConfig,
    EstimatorNoise,
    EstimatorProblem,
    WagonSeries,
    estimate,
    prepare,
    run_numpy,
    rust_available,
)
from fleetbrake.model.rom import DEFAULT_REFINEMENT, ReducedModel
from fleetbrake.model.timeline import simulate_timeline
from fleetbrake.synth.operation import operate, sessions

__all__ = ["SeriesMaker", "bench_estimator", "print_figures"]

NOISE_K = 0.1
DAY_S = 86_400


def _prepare_and_estimate(
    item: tuple[ReducedModel, WagonConfig, EstimatorConfig, list[WagonSeries]],
) -> tuple[int, float]:
    """A partition of the end-to-end pass (a worker's): its wagons prepared and estimated by
    the Rust kernel; returns the logged wagon-seconds and the worker's CPU seconds for them."""
    rom, wagon, config, series = item
    if not series:
        return 0, 0.0  # the warm-up: this module imported in the worker
    c0 = time.process_time()
    problems = [prepare(rom, wagon, s, config=config) for s in series]
    estimates = estimate(problems, config=config, engine="rust")
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


def bench_estimator(
    *,
    wagons: int = 100,
    numpy_wagons: int = 1,
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
    """Time the Rust kernel on ``wagons`` wagon-days and the numpy implementation on the
    first ``numpy_wagons`` of them; returns the figures (and prints them side by side when
    ``show``). ``rom``: the reduced model to use (default: the reference wagon's at
    ``refinement``, from the cache). ``workers``: the end-to-end pass's processes (None: the
    cores this process may use; 0: no end-to-end pass)."""
    if wagons < 1 or not 0 <= numpy_wagons <= min(wagons, chunk) or chunk < 1:
        raise BenchConfigError(
            f"bench estimator: need wagons >= 1, chunk >= 1 and 0 <= numpy_wagons <= "
            f"min(wagons, chunk), got wagons {wagons}, numpy_wagons {numpy_wagons}, chunk {chunk}"
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

    # made, prepared and estimated a chunk of wagons at a time (memory: a chunk's)
    seconds = grid_seconds = numpy_seconds = 0
    prepare_s = prepare_cpu_s = rust_s = rust_cpu_s = 0.0
    steady_seconds = 0.0
    manoeuvre_seconds = 0
    first: list[tuple[EstimatorProblem, ContactEstimate]] = []
    workers = default_workers() if workers is None else workers
    partitions: list[tuple[ReducedModel, WagonConfig, EstimatorConfig, list[WagonSeries]]] = []
    for start in range(0, wagons, chunk):
        t0 = time.perf_counter()
        series = [maker.series(w) for w in range(start, min(start + chunk, wagons))]
        generate_s += time.perf_counter() - t0
        if workers > 0:
            partitions.append((rom, wagon, config, series))
        seconds += sum(s.time_s.size for s in series)
        numpy_seconds += sum(s.time_s.size for s in series[: max(numpy_wagons - start, 0)])
        t0, c0 = time.perf_counter(), time.process_time()
        problems = [prepare(rom, wagon, s, config=config) for s in series]
        prepare_s += time.perf_counter() - t0
        prepare_cpu_s += time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()
        rust = estimate(problems, config=config, engine="rust")
        rust_s += time.perf_counter() - t0
        rust_cpu_s += time.process_time() - c0
        steady_seconds += sum(
            e.frozen_fraction * p.n_samples for p, e in zip(problems, rust, strict=True)
        )
        manoeuvre_seconds += sum(int(e.manoeuvre.sum()) for e in rust if e.manoeuvre is not None)
        grid_seconds += sum(p.n_samples for p in problems)
        first.extend(list(zip(problems, rust, strict=True))[: max(numpy_wagons - start, 0)])

    # end to end as `run` does it: prepare and estimate in the engine's workers
    end_s = end_cpu_s = float("nan")
    if workers > 0:
        with make_engine("local", workers) as engine:
            engine.start()
            list(engine.map(_prepare_and_estimate, [(rom, wagon, config, [])] * workers))
            t0 = time.perf_counter()
            done = list(engine.map(_prepare_and_estimate, partitions))
            end_s = time.perf_counter() - t0
        if sum(n for n, _ in done) != seconds:
            raise BenchConfigError("bench estimator: the end-to-end pass lost wagon-seconds")
        end_cpu_s = sum(c for _, c in done)
    partitions.clear()

    numpy_prepare_s = prepare_s * numpy_seconds / seconds
    t0, c0 = time.perf_counter(), time.process_time()
    peer = [
        run_numpy(
            p,
            config.noise,
            steady_tolerance=config.steady_tolerance,
            smoother_tolerance=config.smoother_tolerance,
            manoeuvre_tolerances=config.manoeuvre_tolerances,
            manoeuvre=config.manoeuvre,
            dt_s=config.dt_s,
        )
        for p, _ in first
    ]
    numpy_s, numpy_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    difference = 0.0
    for (p, fast), raw in zip(first, peer, strict=True):
        rows = p.logged
        for a, b in (
            (raw.mean_c[rows], fast.contact_mean_c),
            (raw.max_c[rows], fast.contact_max_c),
            (
                None if raw.smoothed_mean_c is None else raw.smoothed_mean_c[rows],
                fast.smoothed_contact_mean_c,
            ),
        ):
            if a is not None and b is not None:
                difference = max(difference, float(np.nanmax(np.abs(a - b))))
        if raw.manoeuvre is not None and fast.manoeuvre is not None:
            # the two engines switched the power noise's mode on the same seconds
            if not np.array_equal(raw.manoeuvre[rows], fast.manoeuvre):
                difference = float("inf")

    def rate(n: int, s: float) -> float:
        return round(n / s, 1) if s > 0 else float("nan")

    frozen = steady_seconds / max(grid_seconds, 1)
    figures: dict[str, Any] = {
        "wagons": wagons,
        "wagon_seconds": seconds,
        "order": rom.order,
        "face_nodes": int(rom.c_out.shape[0] - rom.n_probes - 1),
        "refinement": refinement,
        "smoothed": True,
        "rust_s": round(rust_s, 3),
        "rust_wagon_seconds_per_s": rate(seconds, rust_s),
        "rust_with_prepare_wagon_seconds_per_s": rate(seconds, rust_s + prepare_s),
        "rust_cpu_s": round(rust_cpu_s, 3),
        "rust_wagon_seconds_per_cpu_s": rate(seconds, rust_cpu_s),
        "end_to_end_workers": workers,
        "end_to_end_s": round(end_s, 3),
        "end_to_end_wagon_seconds_per_s": rate(seconds, end_s),
        "end_to_end_cpu_s": round(end_cpu_s, 3),
        "end_to_end_wagon_seconds_per_cpu_s": rate(seconds, end_cpu_s),
        "numpy_wagons": numpy_wagons,
        "numpy_wagon_seconds": numpy_seconds,
        "numpy_s": round(numpy_s, 3),
        "numpy_wagon_seconds_per_s": rate(numpy_seconds, numpy_s),
        "numpy_with_prepare_wagon_seconds_per_s": rate(numpy_seconds, numpy_s + numpy_prepare_s),
        "numpy_cpu_s": round(numpy_cpu_s, 3),
        "numpy_wagon_seconds_per_cpu_s": rate(numpy_seconds, numpy_cpu_s),
        "speedup": round((seconds / rust_s) / (numpy_seconds / numpy_s), 1)
        if numpy_seconds and numpy_s > 0 and rust_s > 0
        else float("nan"),
        "max_difference_k": difference,
        "prepare_s": round(prepare_s, 3),
        "prepare_cpu_s": round(prepare_cpu_s, 3),
        "steady_fraction": round(frozen, 3),
        "manoeuvre_fraction": round(manoeuvre_seconds / max(seconds, 1), 4),
        "steady_tolerance": config.steady_tolerance,
        "smoother_tolerance": config.smoother_tolerance,
        "generate_s": round(generate_s, 1),
        "model_s": round(model_s, 2),
        "cpus": os.cpu_count(),
        "load_avg_1min_at_start": round(load_at_start, 2),
    }
    if show:
        print_figures(figures, echo)
    return figures


def print_figures(figures: dict[str, Any], echo: Callable[[str], None] = print) -> None:
    """The two engines side by side, for people."""
    echo(
        f"virtual sensor, filter + smoother: {figures['wagons']} wagon-days, "
        f"{figures['wagon_seconds']:,} logged wagon-seconds; reduced model of order "
        f"{figures['order']} ({figures['face_nodes']} face nodes), refinement "
        f"{figures['refinement']:g}; inputs generated in {figures['generate_s']} s (not timed)"
    )
    rows = [
        ("", "rust", "numpy"),
        ("wagon-seconds", f"{figures['wagon_seconds']:,}", f"{figures['numpy_wagon_seconds']:,}"),
        ("seconds", f"{figures['rust_s']}", f"{figures['numpy_s']}"),
        (
            "wagon-seconds/s",
            f"{figures['rust_wagon_seconds_per_s']:,.0f}",
            f"{figures['numpy_wagon_seconds_per_s']:,.0f}",
        ),
        (
            "per CPU-second",
            f"{figures['rust_wagon_seconds_per_cpu_s']:,.0f}",
            f"{figures['numpy_wagon_seconds_per_cpu_s']:,.0f}",
        ),
        (
            "with prepare",
            f"{figures['rust_with_prepare_wagon_seconds_per_s']:,.0f}",
            f"{figures['numpy_with_prepare_wagon_seconds_per_s']:,.0f}",
        ),
    ]
    for name, a, b in rows:
        echo(f"  {name:<16} {a:>14} {b:>14}")
    if figures["end_to_end_workers"] > 0:
        echo(
            f"end to end (prepare + kernel in {figures['end_to_end_workers']} workers, as run "
            f"does): {figures['end_to_end_wagon_seconds_per_s']:,.0f} wagon-seconds/s, "
            f"{figures['end_to_end_wagon_seconds_per_cpu_s']:,.0f} per CPU-second"
        )
    echo(
        f"rust is {figures['speedup']}x numpy; the engines differ by at most "
        f"{figures['max_difference_k']:.1e} K; covariance steady in "
        f"{figures['steady_fraction']:.0%} of the seconds, the power noise in its manoeuvre "
        f"mode in {figures['manoeuvre_fraction']:.1%}; prepare {figures['prepare_s']} s; "
        f"{figures['cpus']} CPUs, load average {figures['load_avg_1min_at_start']} at start"
    )
