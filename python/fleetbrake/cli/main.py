"""The ``fleetbrake`` command line (contract: ``shared/spec/interface.md``).

Each command is a thin shell: it parses arguments, calls one function of the package, and
turns expected failures into a clear message and a non-zero exit code.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    name="fleetbrake",
    help="Thermal watch over the cast-iron brake blocks of a freight-wagon fleet.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks that print their figures (last line: one JSON object).")
app.add_typer(bench_app, name="bench")

EXIT_FAILED = 1
"""The command could not do its job (no registry, unusable database, ...)."""
EXIT_LOCKED = 75
"""The database is being written by another process (EX_TEMPFAIL: try again later)."""


@contextlib.contextmanager
def _exit_on(
    command: str,
    failed: tuple[type[BaseException], ...],
    *,
    locked: tuple[type[BaseException], ...] = (),
) -> Iterator[None]:
    """Turn the errors a command expects into its message on stderr and its exit code:
    ``locked`` (another process holds the database) 75, ``failed`` 1."""
    try:
        yield
    except locked as error:
        typer.echo(f"fleetbrake {command}: {error}", err=True)
        raise typer.Exit(EXIT_LOCKED) from None
    except failed as error:
        typer.echo(f"fleetbrake {command}: {error}", err=True)
        raise typer.Exit(EXIT_FAILED) from None


@app.command("ingest")
def ingest_command(
    fleet_dir: Annotated[Path, typer.Argument(help="Fleet directory: fleet.toml and logs/.")],
    db: Annotated[Path, typer.Option("--db", help="DuckDB warehouse.")] = Path(
        "warehouse/fleet.duckdb"
    ),
    wait_s: Annotated[
        float,
        typer.Option("--wait", help="Seconds to wait for another process writing the database."),
    ] = 0.0,
) -> None:
    """Ingest the log files not yet ingested and detect braking events.

    Bad files are quarantined and reported: exit 0.
    Exit 1 when the fleet directory, its registry or the database cannot be used.
    Exit 75 when another process is writing the database (run again later, or --wait).
    """
    from fleetbrake.fleet.registry import RegistryError
    from fleetbrake.ingest.files import FleetDirError, print_report, run_ingest
    from fleetbrake.warehouse.connection import WarehouseError, WarehouseLockedError

    with _exit_on(
        "ingest", (FleetDirError, RegistryError, WarehouseError), locked=(WarehouseLockedError,)
    ):
        report = run_ingest(fleet_dir, db, wait_s=wait_s)
    print_report(report)


@app.command("run")
def run_command(
    fleet_dir: Annotated[Path, typer.Argument(help="Fleet directory: fleet.toml and logs/.")],
    db: Annotated[Path, typer.Option("--db", help="DuckDB warehouse.")] = Path(
        "warehouse/fleet.duckdb"
    ),
    flag_config: Annotated[
        Path | None, typer.Option("--flag-config", help="TOML file of flag thresholds.")
    ] = None,
    wait_s: Annotated[
        float,
        typer.Option("--wait", help="Seconds to wait for another process writing the database."),
    ] = 0.0,
    solver: Annotated[
        str,
        typer.Option(
            "--solver",
            help="Model of a new `declared` revision: rom (reduced, default) or full (FE).",
        ),
    ] = "rom",
) -> None:
    """Ingest new files, detect events, simulate every new event, raise flags.

    Idempotent and incremental: a second run over the same directory adds nothing. Bad files
    are quarantined and reported (exit 0); exit 1 when the fleet directory, its registry or
    the database cannot be used, 75 when another process is writing the database.
    """
    from fleetbrake.app.run import run_fleet
    from fleetbrake.fleet.registry import RegistryError
    from fleetbrake.ingest.files import FleetDirError, print_report
    from fleetbrake.warehouse.connection import WarehouseError, WarehouseLockedError

    with _exit_on(
        "run",
        (FleetDirError, RegistryError, WarehouseError, OSError, ValueError),
        locked=(WarehouseLockedError,),
    ):
        if solver not in ("rom", "full"):
            raise ValueError(f"--solver must be rom or full, got {solver!r}")
        from fleetbrake.simulation.predictions import SimulationConfig

        report = run_fleet(
            fleet_dir,
            db,
            wait_s=wait_s,
            flag_config_path=flag_config,
            simulation=SimulationConfig(solver=solver),  # type: ignore[arg-type]
        )
    print_report(report.ingest)
    sim = report.simulation
    typer.echo(
        f"simulated {sim.events_simulated} events with revision {report.revision} "
        f"({sim.prediction_rows:,} prediction rows)"
    )
    for reason in sim.skipped:
        typer.echo(f"  not simulated: {reason}")
    flags = getattr(report.flags, "flags", None) or []
    by_kind: dict[str, int] = {}
    for flag in flags:
        by_kind[flag.kind] = by_kind.get(flag.kind, 0) + 1
    summary = ", ".join(f"{n} {kind}" for kind, n in sorted(by_kind.items())) or "none"
    typer.echo(f"flags: {summary}")
    for flag in flags:
        typer.echo(f"  [{flag.severity}] {flag.kind} {flag.wagon_id}: {flag.evidence}")


@app.command("close-loop")
def close_loop_command(
    holdout_from: Annotated[
        str,
        typer.Option("--holdout-from", help="YYYY-MM-DD: events on or after it are never fitted."),
    ],
    json_out: Annotated[Path, typer.Option("--json", help="Where to write the JSON report.")],
    db: Annotated[Path, typer.Option("--db", help="DuckDB warehouse.")] = Path(
        "warehouse/fleet.duckdb"
    ),
    wait_s: Annotated[
        float,
        typer.Option("--wait", help="Seconds to wait for another process writing the database."),
    ] = 0.0,
) -> None:
    """Compare predictions with measurements, find the effect the model lacks, fit it before
    the holdout date, record a new model revision, re-simulate, and write the report."""
    import datetime as dt

    from fleetbrake.closeloop.loop import CloseLoopError, run_close_loop
    from fleetbrake.warehouse.connection import WarehouseError, WarehouseLockedError

    try:
        holdout = dt.date.fromisoformat(holdout_from)
    except ValueError:
        typer.echo(
            f"fleetbrake close-loop: --holdout-from {holdout_from!r} is not YYYY-MM-DD", err=True
        )
        raise typer.Exit(2) from None
    with _exit_on("close-loop", (CloseLoopError, WarehouseError), locked=(WarehouseLockedError,)):
        report = run_close_loop(db, holdout, json_out, wait_s=wait_s)
    if report["new_revision"]:
        typer.echo(
            f"added {report['effect']} {report['parameters']} as {report['new_revision']}: "
            f"holdout RMSE {report['holdout'].get('rmse_before_k')} -> "
            f"{report['holdout'].get('rmse_after_k')} K"
        )
    else:
        typer.echo("no significant effect is missing: nothing added")
    typer.echo(f"report: {json_out} and {Path(json_out).with_suffix('.md')}")


# options the data-side benchmarks share
WorkdirOption = Annotated[
    Path | None, typer.Option("--workdir", help="Where to make the temporary directory.")
]
BenchFleetOption = Annotated[
    Path | None,
    typer.Option("--fleet", help="Make the fleet here and keep it; reuse it if it exists."),
]


@bench_app.command("ingest")
def bench_ingest_command(
    json_out: Annotated[bool, typer.Option("--json", help="Last line: one JSON object.")] = False,
    rows: Annotated[
        int, typer.Option("--rows", help="Samples in the synthetic gzip fleet.")
    ] = 2_000_000,
    workdir: WorkdirOption = None,
    fleet_dir: BenchFleetOption = None,
) -> None:
    """Ingestion speed and peak memory on a synthetic gzip fleet (events excluded)."""
    import json

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
    json_out: Annotated[bool, typer.Option("--json", help="Last line: one JSON object.")] = False,
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
    import json

    from fleetbrake.bench.solver import bench_solver, print_table

    with _exit_on("bench solver", (ValueError, RuntimeError)):
        figures = bench_solver(element, steps, refinement, cholesky, precision, repeats)
    print_table(figures)
    if json_out:
        typer.echo(json.dumps(figures))


@bench_app.command("rom")
def bench_rom_command(
    json_out: Annotated[bool, typer.Option("--json", help="Last line: one JSON object.")] = False,
    events: Annotated[int, typer.Option(help="Events in the reduced-model batch.")] = 20_000,
    full_events: Annotated[int, typer.Option(help="Events also run by the full model.")] = 3,
    refinement: Annotated[float, typer.Option(help="Mesh refinement (1.0: default).")] = 1.0,
) -> None:
    """Reduced model vs full model on 700-second event windows, in the same run."""
    from fleetbrake.bench.rom import report, run_rom_benchmark

    report(run_rom_benchmark(events, full_events, refinement), json_out)


@bench_app.command("fleet")
def bench_fleet_command(
    json_out: Annotated[bool, typer.Option("--json", help="Last line: one JSON object.")] = False,
    wagons: Annotated[int, typer.Option("--wagons", help="Registered wagons.")] = 100,
    days: Annotated[int, typer.Option("--days", help="UTC days of operation.")] = 1,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the synthetic fleet.")] = 0,
    workdir: WorkdirOption = None,
    fleet_dir: BenchFleetOption = None,
) -> None:
    """A fleet-day from log files to flags: `fleetbrake run` timed end to end (and per
    stage) on a generated fleet (generation not timed)."""
    import json
    import os

    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # tiny matrices: threads only cost

    from fleetbrake.bench.fleet import bench_fleet, print_figures

    with _exit_on("bench fleet", (ValueError, OSError, RuntimeError)):
        figures = bench_fleet(wagons, days, seed=seed, workdir=workdir, fleet_dir=fleet_dir)
    print_figures(figures, typer.echo)
    if json_out:
        typer.echo(json.dumps(figures))


@app.command("paper")
def paper_command(
    out: Annotated[
        Path | None,
        typer.Option(
            "--out", help="Write the pictures (PNG) and fields (VTU) into this directory."
        ),
    ] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Last line: one JSON object.")] = False,
    study: Annotated[
        bool,
        typer.Option(
            "--study", help="Also the study: sensor depth, convection, cylinder bore (minutes)."
        ),
    ] = False,
) -> None:
    """The paper's manoeuvres A and B in the declared model with the registry defaults.

    Force chain, heat input, sensor temperature over 1200 s, time to the sensor's maximum
    against the paper's 271 s and 220 s, friction-face temperatures, and one sensor depth
    calibrated to both manoeuvres. See docs/paper-reproduction.md.
    """
    import json

    from fleetbrake.paper.reproduction import (
        print_report,
        print_study,
        reproduce_paper,
        run_study,
        write_outputs,
    )

    with _exit_on("paper", (ValueError, RuntimeError, OSError)):
        rep = reproduce_paper()
        print_report(rep)
        studied = None
        if study:
            studied = run_study(rep)
            print_study(studied)
        if out is not None:
            for path in write_outputs(rep, out, studied):
                typer.echo(f"wrote {path}")
    if json_out:
        figures = rep.to_dict()
        if studied is not None:
            figures["study"] = studied.to_dict()
        typer.echo(json.dumps(figures))


@app.command("synth")
def synth_command(
    out_dir: Annotated[
        Path, typer.Argument(help="New (or empty) directory for the fleet and its truth.")
    ],
    wagons: Annotated[int, typer.Option("--wagons", help="Registered wagons.")] = 4,
    days: Annotated[int, typer.Option("--days", help="UTC days of operation.")] = 2,
    seed: Annotated[int, typer.Option("--seed", help="Same seed, same bytes.")] = 0,
    effect: Annotated[
        list[str] | None,
        typer.Option(
            "--effect",
            help="Undeclared effect acting on every wagon, NAME[:k=v,...] (repeatable), e.g. "
            "convection_speed:gain=2,exponent=0.8 or sensor_lag:tau_s=40.",
        ),
    ] = None,
    anomalies: Annotated[
        bool,
        typer.Option(
            "--anomalies/--no-anomalies",
            help="Dragging brake, weak brake and sensor faults in some wagons.",
        ),
    ] = True,
    imperfections: Annotated[
        bool,
        typer.Option(
            "--imperfections/--no-imperfections",
            help="Missing/duplicated/swapped rows, empty cells, GPS faults, bad files, "
            "registry problems.",
        ),
    ] = True,
    start: Annotated[str, typer.Option("--start", help="First UTC day, YYYY-MM-DD.")] = (
        "2024-03-04"
    ),
    gzip_fraction: Annotated[
        float, typer.Option("--gzip-fraction", help="Share of the log files gzipped.")
    ] = 0.5,
) -> None:
    """Write a synthetic fleet (fleet.toml and logs/, exactly as fleet-data.md) and its truth
    (OUT_DIR/truth: 1 Hz series, events, anomalies, effects, bad files)."""
    import datetime as dt
    import os
    import time

    # the reduced model's matrices are tiny (~40 x 40): BLAS threads only cost (set before
    # numpy is first imported, which this command does below)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

    from fleetbrake.model.effects import EffectSet, parse_effect
    from fleetbrake.synth.generator import SynthConfig, generate_fleet, summary

    with _exit_on("synth", (ValueError, FileExistsError, OSError)):
        effects = EffectSet(tuple(parse_effect(text) for text in effect or []))
        settings = {
            "wagons": wagons,
            "days": days,
            "seed": seed,
            "start": dt.date.fromisoformat(start),
            "effects": effects,
            "anomalies": anomalies,
            "gzip_fraction": gzip_fraction,
        }
        config = SynthConfig(**settings) if imperfections else SynthConfig.clean(**settings)
        began = time.perf_counter()
        truth = generate_fleet(out_dir, config, progress=lambda text: typer.echo(text, err=True))
    typer.echo(summary(truth))
    typer.echo(f"generated in {time.perf_counter() - began:.1f} s")


@app.command("record")
def record_command(
    wagon: Annotated[str, typer.Option("--wagon", help="Wagon id.")],
    out: Annotated[Path, typer.Option("--out", help="Rerun recording to write (.rrd).")],
    db: Annotated[Path, typer.Option("--db", help="DuckDB warehouse (opened read-only).")] = Path(
        "warehouse/fleet.duckdb"
    ),
    event: Annotated[
        str | None,
        typer.Option("--event", help="Record this event only, with the block's temperature field."),
    ] = None,
    revision: Annotated[
        str | None,
        typer.Option("--revision", help="Model revision of the predictions (default: current)."),
    ] = None,
    registry: Annotated[
        Path | None,
        typer.Option(
            "--registry",
            help="fleet.toml (or its fleet directory): the wagon's block and sensor seat for "
            "--event (default: as the last run stored it, else the spec's defaults).",
        ),
    ] = None,
    wait_s: Annotated[
        float,
        typer.Option("--wait", help="Seconds to wait for another process writing the database."),
    ] = 0.0,
) -> None:
    """Write a rerun recording of a wagon's timeline (or one event) for incident review.

    Exit 1 when the database cannot be read or the wagon, event or revision is unknown, 75
    when another process is writing the database. Open the file with ``rerun FILE.rrd``.
    """
    from fleetbrake.viz.record import RecordError, RecordLockedError, record, wagon_config

    with _exit_on("record", (RecordError,), locked=(RecordLockedError,)):
        config = wagon_config(wagon, registry) if registry is not None else None
        summary = record(
            db, wagon, out, event_id=event, revision=revision, wagon=config, wait_s=wait_s
        )
    what = f"event {summary.event_id}" if summary.event_id else f"wagon {summary.wagon_id}"
    counts = summary.counts
    fields = f", {counts['block/mesh']} block fields" if "block/mesh" in counts else ""
    typer.echo(
        f"wrote {summary.out}: {what}, revision {summary.revision or 'none'}, "
        f"samples {counts.get('wagon/speed_kmh', 0):,}, events {counts['events']}, "
        f"flags {counts['flags']}{fields} ({summary.seconds:.1f} s)"
    )
    for note in summary.notes:
        typer.echo(f"  note: {note}")


@app.command("demo")
def demo_command(
    out: Annotated[
        Path, typer.Option("--out", help="Directory for everything the demo writes.")
    ] = Path("demo-out"),
    force: Annotated[
        bool, typer.Option("--force", help="Wipe the results of an earlier demo in --out first.")
    ] = False,
    wagons: Annotated[int, typer.Option("--wagons", help="Registered wagons.")] = 4,
    days: Annotated[
        int, typer.Option("--days", help="UTC days (the last is the closed loop's holdout).")
    ] = 2,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the synthetic fleet.")] = 7,
    refinement: Annotated[
        float | None,
        typer.Option(
            "--refinement",
            help="Mesh refinement of the reduced model (default: $FLEETBRAKE_REFINEMENT or "
            "1.0; 0.6 builds it in a fifth of the time).",
        ),
    ] = None,
) -> None:
    """Make a synthetic fleet with an undeclared effect and anomalies in it, run everything
    on it (run, close-loop, record) and leave the fleet, database, close-loop report,
    recordings and a report with plots in --out. A few minutes on 2 cores."""
    import os

    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # tiny matrices: threads only cost

    from fleetbrake.app.demo import DemoConfig, DemoError, print_summary, run_demo

    with _exit_on("demo", (DemoError, ValueError)):
        config = DemoConfig(wagons=wagons, days=days, seed=seed, refinement=refinement)
        result = run_demo(out, config, force=force)
    typer.echo("")
    print_summary(result)


def main() -> None:
    """Entry point of the ``fleetbrake`` script."""
    app()


if __name__ == "__main__":
    main()
