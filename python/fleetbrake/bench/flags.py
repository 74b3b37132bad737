"""``fleetbrake bench flags``: the flags' precision, recall, false flags and detection delay,
per class, on generated fleets whose anomalies only the generator knows.

``fleets`` synthetic fleets with anomalies (seeds ``seed``, ``seed + 1``, ...: dragging and
weak brakes and sensor faults in some wagons, the ordinary imperfections of real logs) and
``clean_fleets`` without any (the seeds after those) are generated (not timed; by the
reduced model, or the full finite-element model with ``solver="full"``), each is ``run`` into
a fresh database, and its flags are scored against the truth
(:func:`fleetbrake.synth.scoring.score_flags`). Per class: precision and recall per fleet and
pooled, the detection delays (median and largest), and on the clean fleets the false flags
per 100 wagon-days. ``docs/flags.md`` has the current figures.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fleetbrake.bench import BenchConfigError

__all__ = ["bench_flags", "print_figures"]


def bench_flags(
    fleets: int = 4,
    clean_fleets: int = 2,
    *,
    wagons: int = 10,
    days: int = 2,
    seed: int = 100,
    solver: str = "rom",
    refinement: float = 1.0,
    workdir: str | Path | None = None,
    workers: int | None = None,
) -> dict[str, Any]:
    """Generate, run and score the fleets (module docstring); return the figures."""
    from fleetbrake.synth.config import SynthConfig
    from fleetbrake.synth.scoring import SCORED_KINDS

    if fleets < 1 or clean_fleets < 0 or wagons < 1 or days < 1:
        raise BenchConfigError(
            "fleets must be >= 1, clean fleets >= 0, wagons and days >= 1, got "
            f"{fleets}, {clean_fleets}, {wagons}, {days}"
        )
    if solver not in ("rom", "full"):
        raise BenchConfigError(f"solver must be rom or full, got {solver!r}")
    base = SynthConfig(wagons=wagons, days=days, refinement=refinement, solver=solver)  # type: ignore[arg-type]
    load_at_start = os.getloadavg()[0]
    scratch = Path(tempfile.mkdtemp(prefix="fleetbrake-bench-flags-", dir=workdir))
    per_fleet: list[dict[str, Any]] = []
    try:
        for index in range(fleets + clean_fleets):
            anomalies = index < fleets
            config = dataclasses.replace(base, seed=seed + index, anomalies=anomalies)
            per_fleet.append(_one_fleet(scratch / f"fleet-{index}", config, refinement, workers))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    with_anomalies = [f for f in per_fleet if f["anomalies"]]
    clean = [f for f in per_fleet if not f["anomalies"]]
    clean_wagon_days = sum(f["wagon_days"] for f in clean)
    classes = {}
    for kind in SCORED_KINDS:
        scores = [f["by_kind"][kind] for f in with_anomalies]
        delays = [d for s in scores for d in s["delays_s"]]
        false_clean = sum(f["by_kind"][kind]["flags"] for f in clean)
        classes[kind] = {
            "precision_per_fleet": [s["precision"] for s in scores],
            "recall_per_fleet": [s["recall"] for s in scores],
            "precision": _ratio(
                sum(s["true_flags"] for s in scores), sum(s["flags"] for s in scores)
            ),
            "recall": _ratio(sum(s["found"] for s in scores), sum(s["anomalies"] for s in scores)),
            "anomalies": sum(s["anomalies"] for s in scores),
            "delay_median_s": statistics.median(delays) if delays else None,
            "delay_max_s": max(delays) if delays else None,
            "false_per_100_wagon_days": (
                round(100.0 * false_clean / clean_wagon_days, 2) if clean_wagon_days else None
            ),
        }
    return {
        "fleets": fleets,
        "clean_fleets": clean_fleets,
        "wagons": wagons,
        "days": days,
        "seed": seed,
        "solver": solver,
        "refinement": refinement,
        "classes": classes,
        "per_fleet": per_fleet,
        "cpus": os.cpu_count(),
        "load_avg_1min_at_start": round(load_at_start, 2),
    }


def _ratio(num: int, den: int) -> float:
    return round(num / den, 3) if den else 1.0


def _one_fleet(fleet: Path, config: Any, refinement: float, workers: int | None) -> dict[str, Any]:
    """Generate one fleet, run it into a fresh database and score its flags."""
    from fleetbrake.app.run import run_fleet
    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.synth.generator import generate_fleet
    from fleetbrake.synth.scoring import score_flags, wagon_days

    t = time.perf_counter()
    truth = generate_fleet(fleet, config)
    generate_s = time.perf_counter() - t
    db = fleet.parent / f"{fleet.name}.duckdb"
    t = time.perf_counter()
    run_fleet(
        fleet,
        db,
        simulation=SimulationConfig(refinement=refinement),
        progress=False,
        workers=workers,
    )
    run_s = time.perf_counter() - t
    score = score_flags(db, truth)
    return {
        "seed": config.seed,
        "anomalies": config.anomalies,
        "wagon_days": wagon_days(truth),
        "generate_s": round(generate_s, 1),
        "run_s": round(run_s, 1),
        "precision": round(score.precision, 3),
        "recall": round(score.recall, 3),
        "by_kind": {
            kind: {
                "flags": k.flags,
                "true_flags": k.true_flags,
                "anomalies": k.anomalies,
                "found": k.found,
                "precision": round(k.precision, 3),
                "recall": round(k.recall, 3),
                "delays_s": k.delays_s,
            }
            for kind, k in score.by_kind.items()
        },
        "misses": score.misses,
    }


def print_figures(figures: dict[str, Any], echo: Callable[[str], None] = print) -> None:
    """The figures for people (the JSON line is printed by the caller)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(
        title=(
            f"flags on {figures['fleets']} fleets with anomalies and {figures['clean_fleets']} "
            f"without ({figures['wagons']} wagons x {figures['days']} days, {figures['solver']}, "
            f"load {figures['load_avg_1min_at_start']})"
        )
    )
    for column in (
        "class",
        "precision",
        "recall",
        "per fleet P / R (min)",
        "delay median / max s",
        "false per 100 wagon-days",
        "target",
    ):
        table.add_column(column)
    for kind, c in figures["classes"].items():
        table.add_row(
            kind,
            f"{c['precision']:.3f}",
            f"{c['recall']:.3f} of {c['anomalies']}",
            f"{min(c['precision_per_fleet']):.2f} / {min(c['recall_per_fleet']):.2f}",
            "-"
            if c["delay_median_s"] is None
            else f"{c['delay_median_s']:.0f} / {c['delay_max_s']:.0f}",
            "-" if c["false_per_100_wagon_days"] is None else f"{c['false_per_100_wagon_days']}",
            "P, R >= 0.9 per fleet; <= 1 false per 100",
        )
    console = Console(width=140)
    with console.capture() as captured:
        console.print(table)
    echo(captured.get().rstrip("\n"))
