"""``fleetbrake bench ...``: the benchmarks (``docs/benchmarks.md``). Their meters and peers
come with the ``bench`` extra; a benchmark without them says what to install (exit 2)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from fleetbrake.cli.group import FleetbrakeGroup
from fleetbrake.cli.options import (
    AddressOption,
    EngineOption,
    RefinementOption,
    WorkersOption,
    global_options,
)
from fleetbrake.cli.threads import blas_single_thread

__all__ = ["bench_app"]

bench_app = typer.Typer(
    cls=FleetbrakeGroup,
    help="Benchmarks that print their figures (last line: one JSON object). Their meters and "
    'peers: pip install "fleetbrake\\[bench]".',
    no_args_is_help=True,
)

JsonFlag = Annotated[bool, typer.Option("--json", help="Last line: one JSON object.")]
WorkdirOption = Annotated[
    Path | None, typer.Option("--workdir", help="Where to make the temporary directory.")
]
BenchFleetOption = Annotated[
    Path | None,
    typer.Option("--fleet", help="Make the fleet here and keep it; reuse it if it exists."),
]


@bench_app.command("ingest")
def bench_ingest_command(
    json_out: JsonFlag = False,
    rows: Annotated[
        int, typer.Option("--rows", help="Samples in the synthetic gzip fleet.")
    ] = 2_000_000,
    workdir: WorkdirOption = None,
    fleet_dir: BenchFleetOption = None,
) -> None:
    """Ingestion speed and peak memory on a synthetic gzip fleet (events excluded)."""
    from fleetbrake.bench.ingest import bench_ingest

    figures = bench_ingest(rows, workdir=workdir, fleet_dir=fleet_dir)
    typer.echo(
        f"ingested {figures['rows']:,} rows ({figures['files']} gzip files, "
        f"{figures['gzip_mb']} MB) in {figures['seconds']} s: "
        f"{figures['rows_per_s']:,} rows/s, peak RSS {figures['peak_rss_mb']} MB"
    )
    if json_out:
        typer.echo(json.dumps(figures))


@bench_app.command("solver")
def bench_solver_command(
    json_out: JsonFlag = False,
    element: Annotated[str, typer.Option("--element", help="hex20 or hex8.")] = "hex20",
    steps: Annotated[int, typer.Option("--steps", help="Time steps of 1 s.")] = 600,
    refinement: Annotated[
        float, typer.Option("--refinement", help="Mesh refinement (1.0: ~21,600 hex20 nodes).")
    ] = 1.0,
    cholesky: Annotated[
        str, typer.Option("--cholesky", help="auto, simplicial or supernodal (ours).")
    ] = "auto",
    precision: Annotated[
        str,
        typer.Option(
            "--precision",
            help="Factor values in the solves: mixed (single, default) or double; "
            "the other is timed too.",
        ),
    ] = "mixed",
    repeats: Annotated[
        int,
        typer.Option(
            "--repeats", help="Runs of each engine, alternately; the fastest of each is kept."
        ),
    ] = 3,
) -> None:
    """Our block model against scikit-fem on manoeuvre A: time, memory, traffic bound."""
    from fleetbrake.bench.solver import bench_solver, print_table

    figures = bench_solver(element, steps, refinement, cholesky, precision, repeats)
    print_table(figures)
    if json_out:
        typer.echo(json.dumps(figures))


@bench_app.command("rom")
def bench_rom_command(
    json_out: JsonFlag = False,
    events: Annotated[int, typer.Option(help="Events in the reduced-model batch.")] = 20_000,
    full_events: Annotated[int, typer.Option(help="Events also run by the full model.")] = 3,
    refinement: Annotated[float, typer.Option(help="Mesh refinement (1.0: default).")] = 1.0,
) -> None:
    """Reduced model vs full model on 700-second event windows, in the same run."""
    from fleetbrake.bench.rom import report, run_rom_benchmark

    report(run_rom_benchmark(events, full_events, refinement), json_out)


@bench_app.command("estimator")
def bench_estimator_command(
    json_out: JsonFlag = False,
    wagons: Annotated[
        int, typer.Option("--wagons", help="Wagon-days run through the Rust kernel.")
    ] = 100,
    refinement: RefinementOption = 1.0,
) -> None:
    """The virtual sensor (Kalman filter and smoother): wagon-seconds per second of the Rust
    kernel alone and end to end (prepare and kernel in the engine's workers, as run does),
    beside the floor of 500,000 end to end on two cores."""
    import json

    from fleetbrake.bench.estimator import bench_estimator

    figures = bench_estimator(wagons=wagons, refinement=refinement, echo=typer.echo)
    if json_out:
        typer.echo(json.dumps(figures))


@bench_app.command("fleet")
def bench_fleet_command(
    ctx: typer.Context,
    json_out: JsonFlag = False,
    wagons: Annotated[int, typer.Option("--wagons", help="Registered wagons.")] = 100,
    days: Annotated[int, typer.Option("--days", help="UTC days of operation.")] = 1,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the synthetic fleet.")] = 0,
    workdir: WorkdirOption = None,
    fleet_dir: BenchFleetOption = None,
    refinement: RefinementOption = 1.0,
    workers: WorkersOption = None,
    engine: EngineOption = "local",
    address: AddressOption = None,
) -> None:
    """A fleet-day from log files to flags: `fleetbrake run` timed end to end (and per
    stage) on a generated fleet (generation not timed)."""
    from fleetbrake.bench.fleet import bench_fleet, print_figures

    with blas_single_thread():
        figures = bench_fleet(
            wagons,
            days,
            seed=seed,
            workdir=workdir,
            fleet_dir=fleet_dir,
            refinement=refinement,
            progress=global_options(ctx).progress,
            workers=workers,
            engine=engine,
            address=address,
        )
    print_figures(figures, typer.echo)
    if json_out:
        typer.echo(json.dumps(figures))


@bench_app.command("incremental")
def bench_incremental_command(
    ctx: typer.Context,
    json_out: JsonFlag = False,
    wagons: Annotated[int, typer.Option("--wagons", help="Registered wagons.")] = 20,
    days: Annotated[int, typer.Option("--days", help="UTC days, landed one at a time.")] = 60,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the synthetic fleet.")] = 0,
    workdir: WorkdirOption = None,
    fleet_dir: BenchFleetOption = None,
    db_path: Annotated[
        Path | None, typer.Option("--db", help="Keep the warehouse in this new database.")
    ] = None,
    refinement: RefinementOption = 1.0,
    workers: WorkersOption = None,
) -> None:
    """`fleetbrake run` timed day after day on a generated fleet (generation not timed): each
    day's files renamed into logs/, then run into the same warehouse; the last day's seconds
    over the first's, beside the limit of 1.2."""
    from fleetbrake.bench.incremental import bench_incremental, print_figures

    with blas_single_thread():
        figures = bench_incremental(
            wagons,
            days,
            seed=seed,
            workdir=workdir,
            fleet_dir=fleet_dir,
            db_path=db_path,
            progress=global_options(ctx).progress,
            refinement=refinement,
            workers=workers,
            echo=typer.echo,
        )
    print_figures(figures)
    if json_out:
        typer.echo(json.dumps(figures))


@bench_app.command("close-loop")
def bench_close_loop_command(
    json_out: JsonFlag = False,
    wagons: Annotated[int, typer.Option("--wagons", help="Registered wagons.")] = 10,
    days: Annotated[int, typer.Option("--days", help="UTC days (the last held out).")] = 4,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the synthetic fleet.")] = 7,
    effect: Annotated[
        str, typer.Option("--effect", help="The fleet's undeclared effect, NAME[:k=v,...].")
    ] = "convection_speed:gain=2.0,exponent=0.8",
    workdir: WorkdirOption = None,
    fleet_dir: BenchFleetOption = None,
    refinement: RefinementOption = 1.0,
    workers: WorkersOption = None,
    engine: Annotated[
        str, typer.Option("--engine", help="close-loop's --engine: local, inline or ray.")
    ] = "local",
    address: AddressOption = None,
) -> None:
    """The whole `fleetbrake close-loop` command timed on a generated fleet with an undeclared
    effect and anomalies (generation and `run` not timed): seconds, candidates fitted, kernel
    calls, what it found."""
    from fleetbrake.bench.closeloop import bench_close_loop, print_figures

    with blas_single_thread():
        figures = bench_close_loop(
            wagons,
            days,
            seed=seed,
            effect=effect,
            workdir=workdir,
            fleet_dir=fleet_dir,
            refinement=refinement,
            engine=engine,
            workers=workers,
            address=address,
        )
    print_figures(figures, typer.echo)
    if json_out:
        typer.echo(json.dumps(figures))


@bench_app.command("watch")
def bench_watch_command(
    json_out: JsonFlag = False,
    wagons: Annotated[int, typer.Option("--wagons", help="Registered wagons.")] = 4,
    history_days: Annotated[
        int, typer.Option("--history-days", help="Days of history run before the service starts.")
    ] = 1,
    files: Annotated[
        int, typer.Option("--files", help="One-hour session files dropped into logs/.")
    ] = 20,
    rate: Annotated[
        float, typer.Option("--rate", help="Files dropped per minute, at a steady pace.")
    ] = 12.0,
    idle_s: Annotated[
        float, typer.Option("--idle", help="Seconds the idle service's CPU is measured over.")
    ] = 10.0,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the synthetic fleet.")] = 0,
    workdir: WorkdirOption = None,
    fleet_dir: BenchFleetOption = None,
    refinement: RefinementOption = 1.0,
    workers: WorkersOption = None,
    engine: EngineOption = "local",
    service_log: Annotated[
        Path | None, typer.Option("--service-log", help="Keep the service's log in this file.")
    ] = None,
) -> None:
    """`fleetbrake watch` as a user runs it: one-hour files dropped at a steady rate into a
    fleet with history; per file, the seconds from its rename into place to its flags being
    queryable from another process; p50, p95, max, and the service's idle CPU."""
    from fleetbrake.bench.watch import bench_watch, print_figures

    figures = bench_watch(
        wagons=wagons,
        history_days=history_days,
        files=files,
        rate_per_min=rate,
        idle_s=idle_s,
        seed=seed,
        workdir=workdir,
        fleet_dir=fleet_dir,
        refinement=refinement,
        workers=workers,
        engine=engine,
        service_log=service_log,
        echo=typer.echo,
    )
    print_figures(figures, typer.echo)
    if json_out:
        typer.echo(json.dumps(figures))


@bench_app.command("flags")
def bench_flags_command(
    json_out: JsonFlag = False,
    fleets: Annotated[int, typer.Option("--fleets", help="Fleets with anomalies.")] = 4,
    clean_fleets: Annotated[
        int, typer.Option("--clean-fleets", help="Fleets without any anomaly.")
    ] = 2,
    wagons: Annotated[int, typer.Option("--wagons", help="Registered wagons a fleet.")] = 10,
    days: Annotated[int, typer.Option("--days", help="UTC days a fleet.")] = 2,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the first fleet.")] = 100,
    solver: Annotated[
        str, typer.Option("--solver", help="What writes the fleets: rom or full (FE).")
    ] = "rom",
    workdir: WorkdirOption = None,
    refinement: RefinementOption = 1.0,
) -> None:
    """Flags' precision, recall, detection delay and false flags per 100 wagon-days, per
    class, on generated fleets scored against their truth (generation and runs not timed)."""
    from fleetbrake.bench.flags import bench_flags, print_figures

    with blas_single_thread():
        figures = bench_flags(
            fleets,
            clean_fleets,
            wagons=wagons,
            days=days,
            seed=seed,
            solver=solver,
            refinement=refinement,
            workdir=workdir,
        )
    print_figures(figures, typer.echo)
    if json_out:
        typer.echo(json.dumps(figures))
