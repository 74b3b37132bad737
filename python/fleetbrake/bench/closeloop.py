"""``fleetbrake bench close-loop``: the whole ``close-loop`` command, timed on a generated fleet.

A synthetic fleet (:func:`fleetbrake.synth.generator.generate_fleet`: ``wagons`` registered
wagons over ``days`` UTC days, with an undeclared effect acting on every wagon, the injected
anomalies and the ordinary imperfections of real logs) is generated and ``fleetbrake run`` is
run on it first, neither of them timed; then ``fleetbrake close-loop`` (the last day held
out) is run as a command of its own (a new process: start-up, imports and the engine's workers
included) and timed from start to exit. Its report gives what was found and what it cost: the
candidates fitted and the calls of the chain kernel (``cost`` in the JSON report, counted by
:mod:`fleetbrake.closeloop.fitdata`), and the seconds of each phase inside it.

The figures carry the machine's CPU count and load average: other processes on the machine
slow them down; ``processor_s`` (user + system seconds of the command and its workers) is
what the work cost whatever the load. ``docs/benchmarks.md`` ("``fleetbrake bench
close-loop``: the closed loop") has the current figures.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fleetbrake.bench import BenchConfigError

__all__ = ["DEFAULT_EFFECT", "bench_close_loop", "print_figures"]

DEFAULT_EFFECT = "convection_speed:gain=2.0,exponent=0.8"
"""The undeclared effect of the generated fleet (the demo's)."""


def bench_close_loop(
    wagons: int = 10,
    days: int = 4,
    *,
    seed: int = 7,
    effect: str = DEFAULT_EFFECT,
    workdir: str | Path | None = None,
    fleet_dir: str | Path | None = None,
    refinement: float = 1.0,
    engine: str = "local",
    workers: int | None = None,
    address: str | None = None,
) -> dict[str, Any]:
    """Generate the fleet (or reuse ``fleet_dir``'s), run ``fleetbrake run`` on it into a
    fresh database, then time ``fleetbrake close-loop`` on that database; return the
    figures."""
    from fleetbrake.app.run import run_fleet
    from fleetbrake.model.effects import EffectSet, parse_effect
    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    if wagons < 1 or days < 2:
        raise BenchConfigError(f"wagons must be >= 1 and days >= 2, got {wagons} and {days}")
    if not refinement > 0:
        raise BenchConfigError(f"refinement must be > 0, got {refinement}")
    try:
        effects = EffectSet((parse_effect(effect),))
    except ValueError as error:
        raise BenchConfigError(f"effect: {error}") from None
    config = SynthConfig(
        wagons=wagons, days=days, seed=seed, effects=effects, anomalies=True, refinement=refinement
    )
    holdout = config.start + dt.timedelta(days=days - 1)
    scratch = Path(tempfile.mkdtemp(prefix="fleetbrake-bench-closeloop-", dir=workdir))
    try:
        fleet = Path(fleet_dir) if fleet_dir is not None else scratch / "fleet"
        t = time.perf_counter()
        if not (fleet / "fleet.toml").is_file():
            generate_fleet(fleet, config)
        generate_s = time.perf_counter() - t
        db = scratch / "fleet.duckdb"
        t = time.perf_counter()
        run_fleet(
            fleet,
            db,
            simulation=SimulationConfig(refinement=refinement),
            progress=False,
            engine=engine,
            workers=workers,
            address=address,
        )
        run_s = time.perf_counter() - t
        report_path = scratch / "close-loop.json"
        command = [
            sys.executable,
            "-m",
            "fleetbrake.cli.main",
            "--quiet",
            "close-loop",
            "--db",
            str(db),
            "--holdout-from",
            holdout.isoformat(),
            "--json",
            str(report_path),
            "--engine",
            engine,
            *(["--workers", str(workers)] if workers is not None else []),
            *(["--address", address] if address is not None else []),
        ]
        load_at_start = os.getloadavg()[0]
        used = resource.getrusage(resource.RUSAGE_CHILDREN)
        t = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        seconds = time.perf_counter() - t
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        processor_s = (after.ru_utime - used.ru_utime) + (after.ru_stime - used.ru_stime)
        report = json.loads(report_path.read_text(encoding="utf-8"))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    cost = report.get("cost", {})
    return {
        "wagons": wagons,
        "days": days,
        "seed": seed,
        "undeclared_effect": effect,
        "refinement": refinement,
        "engine": engine,
        "workers": workers,
        "generate_s": round(generate_s, 2),
        "run_s": round(run_s, 2),
        "seconds": round(seconds, 2),
        "processor_s": round(processor_s, 2),
        "fit_events": report["fit"]["events"],
        "holdout_events": report["holdout"]["events"],
        "candidates_fitted": cost.get("candidates_fitted"),
        "kernel_calls": cost.get("kernel_calls"),
        "phases_s": cost.get("seconds", {}),
        "effect": report.get("effect"),
        "parameters": report.get("parameters", {}),
        "holdout_rmse_before_k": report["holdout"].get("rmse_before_k"),
        "holdout_rmse_after_k": report["holdout"].get("rmse_after_k"),
        "cpus": os.cpu_count(),
        "load_avg_1min_at_start": round(load_at_start, 2),
        "load_avg_1min_at_end": round(os.getloadavg()[0], 2),
    }


def print_figures(figures: dict[str, Any], echo: Callable[[str], None] = print) -> None:
    """The figures for people (the JSON line is printed by the caller)."""
    parameters = ", ".join(f"{k} {v:.4g}" for k, v in figures["parameters"].items())
    phases = ", ".join(f"{k} {v:.1f}" for k, v in figures["phases_s"].items())
    echo(
        f"fleet of {figures['wagons']} wagons x {figures['days']} days with "
        f"{figures['undeclared_effect']} and anomalies: generated in {figures['generate_s']} s, "
        f"run in {figures['run_s']} s (neither timed)"
    )
    echo(
        f"close-loop ({figures['engine']} engine): {figures['seconds']} s "
        f"({figures['processor_s']} processor-s, its workers included) for "
        f"{figures['fit_events']} fit and {figures['holdout_events']} holdout events, "
        f"{figures['candidates_fitted']} candidate fits, {figures['kernel_calls']} kernel calls"
    )
    echo(f"phases (s): {phases}")
    echo(
        f"found {figures['effect']} ({parameters}); holdout RMSE "
        f"{figures['holdout_rmse_before_k']:.3f} -> {figures['holdout_rmse_after_k']:.3f} K"
        if figures["effect"]
        else "found nothing"
    )
    echo(
        f"{figures['cpus']} CPUs, load average {figures['load_avg_1min_at_start']} at start, "
        f"{figures['load_avg_1min_at_end']} at end"
    )
