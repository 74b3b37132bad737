"""``fleetbrake bench fleet``: a fleet-day from log files to flags, timed end to end.

A synthetic fleet (:func:`fleetbrake.synth.generator.generate_fleet`: ``wagons`` registered wagons over
``days`` UTC days, with the ordinary imperfections of real logs and injected anomalies, no
undeclared effect) is generated first, timed apart (it is not what is measured), then
:func:`fleetbrake.app.run.run_fleet` (``fleetbrake run``) is timed on it into a fresh
database: ingestion, event detection, simulation of every event with the declared model,
flags. The stages' seconds are the ones ``run_fleet`` reports (``RunReport.stage_s``); the
rest of the total is opening the database.

The reduced thermal model is loaded (or built and cached) before the clock starts, as a
fleet server would have it; the refinement (``--refinement``) is 1.0, the default mesh,
unless given; the generator and the run use the same model. The run uses the local engine
of ``--workers`` processes (default: the cores; 1: everything in this process), or with
``--engine ray`` Ray tasks (a local Ray instance of ``--workers`` CPUs, or the cluster at
``--address``): run both on the same ``--fleet`` to print them side by side. On Ray,
``peak_rss_workers_mb`` is the largest process of the local instance this process started
(its workers and its own services; 0 with ``--address``, whose processes are not this
process's descendants), and a local instance's start-up is inside the run's seconds
(``other_s``).

Memory: ``peak_rss_mb`` is the peak resident set of this process (the writer) during the
run: the fleet is generated in a process of its own (what a generator leaves resident is not
the writer's), and this process's peak is reset before the clock starts
(``/proc/self/clear_refs``, then ``VmHWM``; where Linux does not allow it,
``getrusage(RUSAGE_SELF)``, the loading of the model included: ``peak_rss_self_source`` says
which).
``peak_rss_workers_mb`` is the largest resident set of any of this process's descendants
(the engine's workers; 0 with one worker, which runs inline), sampled every
``SAMPLE_S`` by psutil (the descendants listed again every ``CHILDREN_EVERY`` samples and
as each stage begins), as is ``peak_rss_by_stage_mb`` (each stage's largest writer and
worker resident sets: the stage that holds more than a partition shows there). Not
``getrusage(RUSAGE_CHILDREN)``: Linux hands a child that ``exec``s the high-water mark of
the process it was started from, so every worker would look as large as the writer was when
the pool started. ``cpu_s`` is the processor time of the writer and of its descendants (the
workers, and a local Ray instance's processes; sampled with the memory, so what a process
spends in its last ``SAMPLE_S`` is missed), ``cpu_s_by_stage`` the same per stage:
figures a loaded machine distorts far less than the seconds. The figures
carry the machine's CPU count and load average: other processes on the machine slow them
down.
"""

from __future__ import annotations

import datetime as dt
import multiprocessing
import os
import resource
import shutil
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fleetbrake.app.progress import generation_bar
from fleetbrake.bench import BenchConfigError, require_extra

if TYPE_CHECKING:
    from fleetbrake.synth.config import SynthConfig
    from fleetbrake.synth.truth import FleetTruth

__all__ = ["CHILDREN_EVERY", "SAMPLE_S", "bench_fleet", "print_figures"]

SAMPLE_S = 0.05
"""How often the memory sampler reads the resident sets (seconds)."""

CHILDREN_EVERY = 20
"""The sampler lists this process's descendants every this many samples (and as each stage
begins), and reads the listed ones' resident sets at every sample: listing them walks every
process of the machine (``/proc``), which at every sample costs the writer about 2 processor
seconds per 100 wagon-days."""


class _MemorySampler:
    """Samples the resident set of this process and of its descendants every ``SAMPLE_S``
    on a thread, keeping each stage's peaks (``run_fleet(on_stage=)`` names the stage)."""

    def __init__(self) -> None:
        import psutil

        self._me = psutil.Process()
        self._error = psutil.Error
        self.stage = "start"
        self.peaks: dict[str, list[float]] = {}
        self.cpu_s: dict[str, list[float]] = {}
        """Processor seconds of the writer and of the workers (alive then) in each stage."""
        self._cpu_mark: tuple[float, float] | None = None
        self._child_cpu: dict[int, float] = {}
        self._children: list[Any] = []
        self._samples = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss-sampler", daemon=True)

    def _sample(self, *, list_children: bool = False) -> None:
        try:
            mine = self._me.memory_info().rss / 2**20
            self._samples += 1
            if list_children or self._samples % CHILDREN_EVERY == 0:
                self._children = self._me.children(recursive=True)
        except self._error:
            return
        children = self._children
        largest = 0.0
        for child in children:
            try:
                largest = max(largest, child.memory_info().rss / 2**20)
                times = child.cpu_times()
            except self._error:  # ended since it was listed
                continue
            self._child_cpu[child.pid] = times.user + times.system
        peak = self.peaks.setdefault(self.stage, [0.0, 0.0])
        peak[0], peak[1] = max(peak[0], mine), max(peak[1], largest)

    def _run(self) -> None:
        while not self._stop.wait(SAMPLE_S):
            self._sample()

    @property
    def workers_cpu_s(self) -> float:
        """The descendants' processor seconds as last sampled, each process's (alive or
        ended since: the engine's workers once it closed; what a process spent after its
        last sample, at most ``SAMPLE_S`` ago, is not counted)."""
        return sum(list(self._child_cpu.values()))  # a copy: the sampler thread adds

    def on_stage(self, stage: str) -> None:
        """The stage before ends, ``stage`` begins (``run_fleet(on_stage=)``)."""
        self._sample(list_children=True)
        writer, workers = _cpu_s(resource.RUSAGE_SELF), self.workers_cpu_s
        if self._cpu_mark is not None:
            before = self.cpu_s.setdefault(self.stage, [0.0, 0.0])
            before[0] += writer - self._cpu_mark[0]
            before[1] += workers - self._cpu_mark[1]
        self._cpu_mark = (writer, workers)
        self.stage = stage

    def __enter__(self) -> _MemorySampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def workers_mb(self) -> float:
        return max((peak[1] for peak in self.peaks.values()), default=0.0)


def _cpu_s(who: int) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def _reset_peak_rss() -> bool:
    """Reset this process's peak resident set (Linux >= 4.0); False where not allowed."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_rss_self_mb(reset: bool) -> float:
    """This process's peak RSS since :func:`_reset_peak_rss` (``reset``), else since it began."""
    if reset:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1 << 20) if sys.platform == "darwin" else peak / 1024


def _generate(
    fleet_dir: Path, wagons: int, days: int, seed: int, refinement: float, show: bool
) -> FleetTruth:
    from fleetbrake.synth.generator import SynthConfig, load_truth

    if (fleet_dir / "fleet.toml").is_file() and (fleet_dir / "truth").is_dir():
        truth = load_truth(fleet_dir)
        if (truth.config.wagons, truth.config.days, truth.config.seed) != (wagons, days, seed):
            raise BenchConfigError(
                f"{fleet_dir}: holds a fleet of {truth.config.wagons} wagons x "
                f"{truth.config.days} days, seed {truth.config.seed}; give another --fleet"
            )
        return truth
    config = SynthConfig(wagons=wagons, days=days, seed=seed, refinement=refinement)
    # in a process of its own: the generator's memory (5.6 GB at 1,000 wagons) stays resident
    # in the process that ran it, and a peak reset cannot go below the resident set, so a
    # fleet generated here would count as the writer's peak
    spawn = multiprocessing.get_context("spawn")  # never fork a process polars threads run in
    with ProcessPoolExecutor(1, mp_context=spawn) as child:
        child.submit(_generate_here, fleet_dir, config, show).result()
    return load_truth(fleet_dir)


def _generate_here(fleet_dir: Path, config: SynthConfig, show: bool) -> None:
    """Write the fleet of ``config`` into ``fleet_dir``, with its bar."""
    from fleetbrake.synth.generator import generate_fleet

    total = config.wagons + int(config.unregistered_wagon) + int(config.bad_registry_entry)
    with generation_bar(total, show) as step:
        generate_fleet(fleet_dir, config, progress=step)


def bench_fleet(
    wagons: int = 100,
    days: int = 1,
    *,
    seed: int = 0,
    workdir: str | Path | None = None,
    fleet_dir: str | Path | None = None,
    progress: bool | None = None,
    refinement: float = 1.0,
    workers: int | None = None,
    engine: str = "local",
    address: str | None = None,
) -> dict[str, Any]:
    """Generate the fleet (or reuse ``fleet_dir`` if it holds the same one), then time
    ``run_fleet`` on it into a fresh database; return the figures. Everything but a given
    ``fleet_dir`` is made in a temporary directory (in ``workdir``) and removed after.
    ``progress``: show progress bars (None: when stdout is a terminal). Needs psutil (the
    ``bench`` extra)."""
    require_extra("bench fleet", "psutil")
    for name, value in (("wagons", wagons), ("days", days)):
        if value < 1:
            raise BenchConfigError(f"{name} must be >= 1, got {value}")
    if not refinement > 0:
        raise BenchConfigError(f"refinement must be > 0, got {refinement}")
    import psutil

    from fleetbrake.app.run import run_fleet
    from fleetbrake.fleet.registry import WagonConfig
    from fleetbrake.model.rom import ReducedModel
    from fleetbrake.simulation.config import SimulationConfig

    show = sys.stdout.isatty() if progress is None else progress
    tmp = Path(tempfile.mkdtemp(prefix="fleetbrake-bench-fleet-", dir=workdir))
    try:
        began = time.perf_counter()
        ReducedModel.for_wagon(WagonConfig(wagon_id="SGG-0001"), refinement=refinement)
        model_s = time.perf_counter() - began

        fleet = Path(fleet_dir) if fleet_dir is not None else tmp / "fleet"
        began = time.perf_counter()
        truth = _generate(fleet, wagons, days, seed, refinement, show)
        generate_s = time.perf_counter() - began

        db = tmp / "fleet.duckdb"
        reset = _reset_peak_rss()
        load = os.getloadavg()[0]
        cpu_self = _cpu_s(resource.RUSAGE_SELF)
        began = time.perf_counter()
        with _MemorySampler() as sampler:
            report = run_fleet(
                fleet,
                db,
                simulation=SimulationConfig(refinement=refinement),
                progress=show,
                engine=engine,
                workers=workers,
                address=address,
                on_stage=sampler.on_stage,
            )
            seconds = time.perf_counter() - began
            sampler.on_stage("end")
        peak_self_mb = _peak_rss_self_mb(reset)
        cpu_s = {
            "writer": round(_cpu_s(resource.RUSAGE_SELF) - cpu_self, 1),
            "workers": round(sampler.workers_cpu_s, 1),
        }
        stages = report.stage_s
        ingest: Any = report.ingest
        sim = report.simulation
        flag_report: Any = report.flags
        events = ingest.events.total if ingest.events is not None else sim.events_simulated
        figures: dict[str, Any] = {
            "benchmark": "fleet",
            "wagons": wagons,
            "days": days,
            "wagon_days": wagons * days,
            "wagons_with_logs": len(truth.wagons),
            "files": ingest.files_seen,
            "files_quarantined": len(ingest.quarantined),
            "rows": ingest.rows,
            "events": events,
            "events_simulated": sim.events_simulated,
            "prediction_rows": sim.prediction_rows,
            "estimated_wagon_seconds": report.estimation.rows if report.estimation else None,
            "flags": len(flag_report.flags) if flag_report is not None else None,
            "seconds": round(seconds, 2),
            "events_per_s": round(sim.events_simulated / seconds, 1) if seconds else None,
            "rows_per_s": round(ingest.rows / seconds) if seconds else None,
            "stages_s": {k: round(v, 2) for k, v in stages.items()},
            "engine": report.engine,
            "other_s": round(seconds - sum(stages.values()), 2),
            "generate_s": round(generate_s, 1),
            "model_s": round(model_s, 1),
            "refinement": refinement,
            "cpus": os.cpu_count(),
            "load_avg_1min_at_start": round(load, 2),
            "rss_end_mb": round(psutil.Process().memory_info().rss / 2**20),
            "peak_rss_mb": round(peak_self_mb),
            "peak_rss_workers_mb": round(sampler.workers_mb),
            "peak_rss_by_stage_mb": {
                stage: [round(writer), round(worker)]
                for stage, (writer, worker) in sampler.peaks.items()
            },
            "cpu_s": cpu_s,
            "cpu_s_by_stage": {
                stage: [round(writer, 1), round(worker, 1)]
                for stage, (writer, worker) in sampler.cpu_s.items()
            },
            "peak_rss_self_source": "VmHWM after reset" if reset else "ru_maxrss",
            "date_utc": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        }
        return figures
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def print_figures(figures: dict[str, Any], echo: Callable[[str], None] = print) -> None:
    """The figures for people (the JSON line is printed by the caller)."""
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in figures["stages_s"].items())
    echo(
        f"fleet of {figures['wagons']} wagons x {figures['days']} day(s) "
        f"({figures['wagons_with_logs']} wagons with logs, {figures['files']} files, "
        f"{figures['files_quarantined']} quarantined, {figures['rows']:,} rows), "
        f"generated in {figures['generate_s']} s (not timed)"
    )
    echo(
        f"run_fleet: {figures['events_simulated']:,} of {figures['events']:,} events simulated, "
        f"{figures['flags']} flags, in {figures['seconds']} s: "
        f"{figures['events_per_s']} events/s, {figures['rows_per_s']:,} rows/s"
    )
    echo(f"stages: {stages}, other {figures['other_s']:.1f} s; engine {figures['engine']}")
    echo(
        f"reduced model at refinement {figures['refinement']:g} (ready in "
        f"{figures['model_s']} s before timing); {figures['cpus']} CPUs, load average "
        f"{figures['load_avg_1min_at_start']} at start; RSS {figures['rss_end_mb']} MB at the end, "
        f"peak {figures['peak_rss_mb']} MB (writer), {figures['peak_rss_workers_mb']} MB "
        "(largest worker)"
    )
    by_stage = ", ".join(
        f"{stage} {writer}/{worker}"
        for stage, (writer, worker) in figures["peak_rss_by_stage_mb"].items()
    )
    echo(
        f"peak RSS by stage, writer/largest worker MB: {by_stage}; processor time: writer "
        f"{figures['cpu_s']['writer']} s, workers {figures['cpu_s']['workers']} s"
    )
    cpu = ", ".join(
        f"{stage} {writer}/{worker}"
        for stage, (writer, worker) in figures["cpu_s_by_stage"].items()
    )
    echo(f"processor seconds by stage, writer/workers: {cpu}")
