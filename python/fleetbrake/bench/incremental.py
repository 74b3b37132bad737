"""``fleetbrake bench incremental``: ``fleetbrake run`` day after day on a growing warehouse.

A fleet of ``wagons`` x ``days`` days is generated once, in a process of its own, not timed
(as ``bench fleet`` generates it; ``--fleet DIR`` keeps and reuses it). Its log files are held
back in a staging folder, one folder a UTC day (a file's day is the day of its first sample).
Then, for each day in order, that day's files are renamed into the fleet's ``logs/``
and :func:`fleetbrake.app.run.run_fleet` (``fleetbrake run``, the local engine, as ``bench
fleet`` runs it) is timed on it, into the same database: each run ingests the new day's
files into a warehouse that already holds every day before it, detects their events,
simulates them and raises flags.

What it shows: whether a day costs the same with sixty days in the warehouse as with none.
The figure is ``last_over_first``, the seconds of the last day's run over the first's (target
at most :data:`LIMIT_LAST_OVER_FIRST`); beside it the same ratio of the medians of the first
and last :data:`EDGE_DAYS` days, and of the processor seconds (the writer's and its
workers', sampled as ``bench fleet`` samples them), which a loaded machine distorts far less.
Per day, the figures also hold the rows and files landed, the events its run simulated, the
flags of the wagons it judged, its stages' seconds and the warehouse's size on disk after it;
beside them the machine's load averages at the start (as ``uptime`` gives them)."""

from __future__ import annotations

import datetime as dt
import os
import resource
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fleetbrake.bench import BenchConfigError, require_extra
from fleetbrake.bench.fleet import _cpu_s, _generate, _MemorySampler

if TYPE_CHECKING:
    from fleetbrake.synth.truth import FleetTruth

__all__ = ["EDGE_DAYS", "LIMIT_LAST_OVER_FIRST", "bench_incremental", "print_figures"]

LIMIT_LAST_OVER_FIRST = 1.2
"""The target: the last day's run takes at most this many times the first day's."""

EDGE_DAYS = 5
"""How many days at each end the steadier ratio (of medians) takes (fewer, half the days,
in a shorter run)."""


def _stage(truth: FleetTruth, source: Path, tmp: Path) -> tuple[Path, list[list[str]]]:
    """A fleet in ``tmp`` with the registry of ``source`` and an empty ``logs/``; every log
    file of ``source`` linked (copied across filesystems) into ``tmp/staging/<day>/``. Returns
    the fleet and, per day, the relative paths of its files."""
    fleet = tmp / "fleet"
    (fleet / "logs").mkdir(parents=True)
    shutil.copy2(source / "fleet.toml", fleet / "fleet.toml")
    by_day: list[list[str]] = [[] for _ in range(truth.config.days)]
    for file in truth.files:
        day = (file.start_utc.date() - truth.config.start).days
        if not 0 <= day < truth.config.days:
            raise BenchConfigError(
                f"{source / file.path}: its first sample, {file.start_utc:%Y-%m-%d}, is outside "
                f"the fleet's {truth.config.days} days from {truth.config.start}"
            )
        staged = _staged(tmp, day, file.path)
        staged.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(source / file.path, staged)
        except OSError:
            shutil.copy2(source / file.path, staged)
        by_day[day].append(file.path)
    return fleet, by_day


def _staged(tmp: Path, day: int, relpath: str) -> Path:
    return tmp / "staging" / f"day-{day + 1:03d}" / relpath


def _land(tmp: Path, fleet: Path, day: int, relpaths: list[str]) -> None:
    """Rename the staged files of ``day`` into ``fleet``'s ``logs/``."""
    for relpath in relpaths:
        target = fleet / relpath
        target.parent.mkdir(parents=True, exist_ok=True)
        os.rename(_staged(tmp, day, relpath), target)


def _warehouse_mb(db: Path) -> float:
    """The database's size on disk, its write-ahead log included."""
    wal = db.with_name(db.name + ".wal")
    return sum(p.stat().st_size for p in (db, wal) if p.exists()) / 2**20


def _run_day(fleet: Path, db: Path, refinement: float, workers: int | None) -> dict[str, Any]:
    """One ``run_fleet`` into ``db``, timed; its seconds, processor seconds and counts."""
    from fleetbrake.app.run import run_fleet
    from fleetbrake.simulation.config import SimulationConfig

    cpu_self = _cpu_s(resource.RUSAGE_SELF)
    began = time.perf_counter()
    with _MemorySampler() as sampler:
        report = run_fleet(
            fleet,
            db,
            simulation=SimulationConfig(refinement=refinement),
            progress=False,
            engine="local",
            workers=workers,
            on_stage=sampler.on_stage,
        )
        seconds = time.perf_counter() - began
        sampler.on_stage("end")
    ingest: Any = report.ingest
    flag_report: Any = report.flags
    return {
        "seconds": seconds,
        "cpu_s": _cpu_s(resource.RUSAGE_SELF) - cpu_self + sampler.workers_cpu_s,
        "cpu_s_workers": sampler.workers_cpu_s,
        "rows": ingest.rows,
        "events_simulated": report.simulation.events_simulated,
        "flags": len(flag_report.flags) if flag_report is not None else None,
        "stages_s": {k: round(v, 2) for k, v in report.stage_s.items()},
        "warehouse_mb": _warehouse_mb(db),
    }


def _ratio(last: float, first: float) -> float | None:
    return round(last / first, 3) if first > 0 else None


def bench_incremental(
    wagons: int = 20,
    days: int = 60,
    *,
    seed: int = 0,
    workdir: str | Path | None = None,
    fleet_dir: str | Path | None = None,
    db_path: str | Path | None = None,
    progress: bool | None = None,
    refinement: float = 1.0,
    workers: int | None = None,
    echo: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Generate the fleet (or reuse ``fleet_dir`` if it holds the same one), then land and
    ``run`` it day by day into one database (see the module); return the figures. ``db_path``:
    the database, kept (it must not exist); otherwise it is made in the temporary directory
    (in ``workdir``), removed after with everything else but a given ``fleet_dir``.
    ``echo``: where each day's line goes as it ends. ``progress``: show the generation's bar
    (None: when stdout is a terminal). Needs psutil (the ``bench`` extra)."""
    require_extra("bench incremental", "psutil")
    for name, value in (("wagons", wagons), ("days", days)):
        if value < 1:
            raise BenchConfigError(f"{name} must be >= 1, got {value}")
    if not refinement > 0:
        raise BenchConfigError(f"refinement must be > 0, got {refinement}")
    if db_path is not None and Path(db_path).exists():
        raise BenchConfigError(f"{db_path}: exists; --db takes a new database")
    from fleetbrake.engine import make_engine
    from fleetbrake.fleet.registry import WagonConfig
    from fleetbrake.model.rom import ReducedModel

    make_engine("local", workers).close()  # a bad worker count: refused before any work
    say = echo or (lambda _line: None)
    show = sys.stdout.isatty() if progress is None else progress
    tmp = Path(tempfile.mkdtemp(prefix="fleetbrake-bench-incremental-", dir=workdir))
    try:
        source = Path(fleet_dir) if fleet_dir is not None else tmp / "generated"
        began = time.perf_counter()
        truth = _generate(source, wagons, days, seed, refinement, show)
        generate_s = time.perf_counter() - began
        # the generator built (or found) the reduced model in the cache: loaded here before
        # the first day, whose run would otherwise load it
        ReducedModel.for_wagon(WagonConfig(wagon_id="SGG-0001"), refinement=refinement)
        fleet, by_day = _stage(truth, source, tmp)

        db = Path(db_path) if db_path is not None else tmp / "warehouse.duckdb"
        load = os.getloadavg()
        runs: list[dict[str, Any]] = []
        for day, relpaths in enumerate(by_day):
            _land(tmp, fleet, day, relpaths)
            run = _run_day(fleet, db, refinement, workers) | {"files": len(relpaths)}
            runs.append(run)
            say(
                f"day {day + 1}/{days}: {run['seconds']:.2f} s, {run['cpu_s']:.1f} processor-s, "
                f"{run['rows']:,} rows in {run['files']} files, "
                f"{run['events_simulated']} events simulated; "
                f"warehouse {run['warehouse_mb']:.1f} MB"
            )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return _figures(runs, wagons=wagons, seed=seed, refinement=refinement, workers=workers) | {
        "generate_s": round(generate_s, 1),
        "cpus": os.cpu_count(),
        "load_avg_at_start": [round(x, 2) for x in load],
        "load_avg_1min_at_start": round(load[0], 2),
        "date_utc": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def _figures(
    runs: list[dict[str, Any]], *, wagons: int, seed: int, refinement: float, workers: int | None
) -> dict[str, Any]:
    """The figures of the day's runs (the setting's beside them)."""
    day_s = [round(r["seconds"], 3) for r in runs]
    day_cpu_s = [round(r["cpu_s"], 2) for r in runs]
    edge = max(1, min(EDGE_DAYS, len(runs) // 2))
    return {
        "benchmark": "incremental",
        "wagons": wagons,
        "days": len(runs),
        "seed": seed,
        "refinement": refinement,
        "engine": "local",
        "workers": workers,
        "day_s": day_s,
        "last_over_first": _ratio(day_s[-1], day_s[0]),
        "limit_last_over_first": LIMIT_LAST_OVER_FIRST,
        "edge_days": edge,
        "last_over_first_median_s": _ratio(
            statistics.median(day_s[-edge:]), statistics.median(day_s[:edge])
        ),
        "median_day_s": round(statistics.median(day_s), 3),
        "total_s": round(sum(day_s), 2),
        "day_cpu_s": day_cpu_s,
        "day_cpu_s_workers": [round(r["cpu_s_workers"], 2) for r in runs],
        "last_over_first_cpu": _ratio(day_cpu_s[-1], day_cpu_s[0]),
        "last_over_first_median_cpu": _ratio(
            statistics.median(day_cpu_s[-edge:]), statistics.median(day_cpu_s[:edge])
        ),
        "day_rows": [r["rows"] for r in runs],
        "day_files": [r["files"] for r in runs],
        "day_events_simulated": [r["events_simulated"] for r in runs],
        "day_flags": [r["flags"] for r in runs],
        "day_stages_s": [r["stages_s"] for r in runs],
        "day_warehouse_mb": [round(r["warehouse_mb"], 1) for r in runs],
        "warehouse_mb": round(runs[-1]["warehouse_mb"], 1),
        "rows": sum(r["rows"] for r in runs),
    }


def print_figures(figures: dict[str, Any]) -> None:
    """The figures for people, a table (rich) on stdout: the first, median and last day, and
    the ratio beside its limit (the JSON line is printed by the caller)."""
    from rich.console import Console
    from rich.table import Table

    f = figures
    days = f["days"]
    table = Table(
        title=(
            f"run day by day: {f['wagons']} wagons x {days} days, refinement {f['refinement']:g}"
        )
    )
    for column in ("", "seconds", "processor-s", "rows"):
        table.add_column(column, justify="left" if not column else "right")

    def day_row(label: str, k: int) -> None:
        table.add_row(
            label, f"{f['day_s'][k]:.2f}", f"{f['day_cpu_s'][k]:.1f}", f"{f['day_rows'][k]:,}"
        )

    day_row("day 1", 0)
    table.add_row(
        f"median of {days} days",
        f"{f['median_day_s']:.2f}",
        f"{statistics.median(f['day_cpu_s']):.1f}",
        f"{round(statistics.median(f['day_rows'])):,}",
    )
    day_row(f"day {days}", days - 1)
    table.add_row(
        f"day {days} / day 1",
        f"[bold]{f['last_over_first']}[/bold] (limit {f['limit_last_over_first']:g})",
        f"{f['last_over_first_cpu']}",
        "",
    )
    table.add_row(
        f"median of last / first {f['edge_days']} days",
        f"{f['last_over_first_median_s']}",
        f"{f['last_over_first_median_cpu']}",
        "",
    )
    console = Console()
    console.print(table)
    load = ", ".join(f"{x:g}" for x in f["load_avg_at_start"])
    console.print(
        f"warehouse {f['warehouse_mb']:,.1f} MB after day {days}, {f['rows']:,} rows; fleet "
        f"generated in {f['generate_s']} s (not timed); {f['cpus']} CPUs, load average {load} "
        "at start",
        highlight=False,
    )
