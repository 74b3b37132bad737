"""The ``fleetbrake`` command line (contract: ``shared/spec/interface.md``).

Each command is a thin shell: it parses its arguments into the package's typed
configuration objects, calls one function of the package and prints the outcome. Around
them:

* the global options (``fleetbrake [--log-format text|json] [--quiet | -v] COMMAND``): where
  the library's log records go (:mod:`fleetbrake.cli.logs`), and whether progress bars are
  drawn (only when stdout is a terminal, never with ``--quiet``);
* one mapping of expected failures (:class:`fleetbrake.cli.group.FleetbrakeGroup`): every
  :class:`fleetbrake.errors.FleetbrakeError` a command raises ends as one line on stderr and
  its exit code (1 could not do its job, 2 bad usage or configuration, 75 database held by
  another writer), never a traceback;
* ``--json`` on ``run`` and ``close-loop``: one JSON summary as the last line of stdout
  (:mod:`fleetbrake.cli.output`).
* ``fleetbrake config``: the configuration reference of ``docs/configuration.md``, generated
  from the configuration classes (:mod:`fleetbrake.cli.configref`); the top-level help and
  every command that reads configuration point to it in their epilog.

The benchmarks are the ``bench`` sub-commands (:mod:`fleetbrake.cli.bench`); nothing here
imports their meters or peers.
"""

from __future__ import annotations

import datetime as dt
import logging
import sys
import time
from pathlib import Path
from typing import Annotated, Literal, cast

import typer

from fleetbrake.cli.bench import bench_app
from fleetbrake.cli.bridge import register as register_bridge
from fleetbrake.cli.group import FleetbrakeGroup
from fleetbrake.cli.logs import LogFormat, configure_logging, level_for
from fleetbrake.cli.options import (
    CONFIG_REFERENCE,
    DEFAULT_DB,
    AddressOption,
    DbOption,
    EngineOption,
    FleetDirArgument,
    GlobalOptions,
    OptionError,
    OutputDirError,
    RefinementOption,
    WaitOption,
    WorkersOption,
    existing_database,
    global_options,
    option_values,
)
from fleetbrake.cli.output import (
    close_loop_summary,
    echo_json,
    print_close_loop,
    print_run,
    run_summary,
)
from fleetbrake.cli.threads import blas_single_thread
from fleetbrake.cli.watch import register as register_watch

__all__ = ["app", "main"]

logger = logging.getLogger(__name__)

app = typer.Typer(
    cls=FleetbrakeGroup,
    name="fleetbrake",
    help="Thermal watch over the cast-iron brake blocks of a freight-wagon fleet.",
    epilog=CONFIG_REFERENCE,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.add_typer(bench_app, name="bench")
register_bridge(app)
register_watch(app)

SOLVERS = ("rom", "full")


@app.callback()
def global_options_callback(
    ctx: typer.Context,
    log_format: Annotated[
        LogFormat,
        typer.Option(
            "--log-format", help="Log records on stderr as text, or one JSON object per line."
        ),
    ] = LogFormat.TEXT,
    quiet: Annotated[
        bool, typer.Option("--quiet", "-q", help="Errors only on stderr; no progress bars.")
    ] = False,
    verbose: Annotated[
        int,
        typer.Option("--verbose", "-v", count=True, help="More log records: -v info, -vv debug."),
    ] = 0,
) -> None:
    """Thermal watch over the cast-iron brake blocks of a freight-wagon fleet.

    Exit codes: 0 done, 1 could not do its job, 2 bad usage or configuration, 75 the
    database is held by another writer (run again later, or --wait).
    """
    level = level_for(quiet=quiet, verbose=verbose)
    ctx.obj = GlobalOptions(
        log_format=log_format,
        log_level=level,
        quiet=quiet,
        progress=not quiet and sys.stdout.isatty(),
    )
    ctx.call_on_close(configure_logging(log_format, level))
    if quiet and verbose:
        raise OptionError("--quiet and --verbose: give one of them")


@app.command("ingest", epilog=CONFIG_REFERENCE)
def ingest_command(
    ctx: typer.Context,
    fleet_dir: FleetDirArgument,
    db: DbOption = DEFAULT_DB,
    wait_s: WaitOption = 0.0,
) -> None:
    """Ingest the log files not yet ingested and detect braking events.

    Bad files are quarantined and reported: exit 0.
    Exit 1 when the fleet directory, its registry or the database cannot be used.
    Exit 75 when another process is writing the database (run again later, or --wait).
    """
    from fleetbrake.ingest.files import print_report, run_ingest

    report = run_ingest(fleet_dir, db, wait_s=wait_s, progress=global_options(ctx).progress)
    print_report(report)


@app.command("run", epilog=CONFIG_REFERENCE)
def run_command(
    ctx: typer.Context,
    fleet_dir: FleetDirArgument,
    db: DbOption = DEFAULT_DB,
    flag_config: Annotated[
        Path | None, typer.Option("--flag-config", help="TOML file of flag thresholds.")
    ] = None,
    wait_s: WaitOption = 0.0,
    solver: Annotated[
        str,
        typer.Option(
            "--solver",
            help="Model of a new `declared` revision: rom (reduced, default) or full (FE).",
        ),
    ] = "rom",
    json_summary: Annotated[
        bool, typer.Option("--json", help="Last line of stdout: one JSON summary.")
    ] = False,
    engine: EngineOption = "local",
    workers: WorkersOption = None,
    address: AddressOption = None,
) -> None:
    """Ingest new files, detect events, simulate every new event, raise flags.

    Idempotent and incremental: a second run over the same directory adds nothing. Bad files
    are quarantined and reported (exit 0); exit 1 when the fleet directory, its registry or
    the database cannot be used, 2 for a bad --flag-config, --solver, --engine or --workers
    or an invalid registry value of a wagon the database holds results of (nothing written),
    75 when another process is writing the database.
    """
    from fleetbrake.app.run import run_fleet
    from fleetbrake.ingest.files import print_report
    from fleetbrake.simulation.config import SimulationConfig

    if solver not in SOLVERS:
        raise OptionError(f"--solver must be one of {', '.join(SOLVERS)}, got {solver!r}")
    with option_values("--solver"):
        simulation = SimulationConfig(solver=cast(Literal["rom", "full"], solver))
    report = run_fleet(
        fleet_dir,
        db,
        wait_s=wait_s,
        flag_config_path=flag_config,
        simulation=simulation,
        progress=global_options(ctx).progress,
        engine=engine,
        workers=workers,
        address=address,
    )
    print_report(report.ingest)
    print_run(report)
    if json_summary:
        echo_json(run_summary(report))


def _holdout_date(text: str) -> dt.date:
    try:
        return dt.date.fromisoformat(text)
    except ValueError:
        raise OptionError(f"--holdout-from {text!r} is not a date YYYY-MM-DD") from None


@app.command("close-loop", epilog=CONFIG_REFERENCE)
def close_loop_command(
    ctx: typer.Context,
    holdout_from: Annotated[
        str,
        typer.Option("--holdout-from", help="YYYY-MM-DD: events on or after it are never fitted."),
    ],
    json_out: Annotated[Path, typer.Option("--json", help="Where to write the JSON report.")],
    db: DbOption = DEFAULT_DB,
    wait_s: WaitOption = 0.0,
    engine: Annotated[
        str,
        typer.Option(
            "--engine",
            help="Where candidates are fitted and the new revision simulated: local (worker "
            "processes on this machine, default); inline (this process); ray (Ray tasks: pip "
            'install "fleetbrake\\[ray]").',
        ),
    ] = "local",
    workers: WorkersOption = None,
    address: AddressOption = None,
) -> None:
    """Find the effect the model lacks, add it as a new model revision, and report.

    Compares predictions with measurements, fits the effect on the events before the
    holdout date, records the new model revision, re-simulates, and writes the report. The last line of stdout is one JSON summary (the report itself is in --json's file).
    Exit 1 when the database does not exist (nothing is created) or cannot be used for it,
    2 for a bad --holdout-from, --engine or
    --workers, 75 when another process is writing the database.
    """
    from fleetbrake.app.progress import spinner
    from fleetbrake.closeloop.loop import run_close_loop

    holdout = _holdout_date(holdout_from)
    existing_database(db)
    with spinner("finding the effect the model lacks", global_options(ctx).progress):
        report = run_close_loop(
            db, holdout, json_out, wait_s=wait_s, engine=engine, workers=workers, address=address
        )
    print_close_loop(report, json_out)
    echo_json(close_loop_summary(report, json_out))


@app.command("paper", epilog=CONFIG_REFERENCE)
def paper_command(
    ctx: typer.Context,
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

    from fleetbrake.app.progress import spinner
    from fleetbrake.paper.outputs import write_outputs
    from fleetbrake.paper.report import print_report, print_study
    from fleetbrake.paper.reproduction import reproduce_paper
    from fleetbrake.paper.study import run_study

    show = global_options(ctx).progress
    with spinner("manoeuvres A and B on the full model", show):
        rep = reproduce_paper()
    print_report(rep)
    studied = None
    if study:
        with spinner("the study: sensor depth, convection, cylinder bore", show):
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


@app.command("synth", epilog=CONFIG_REFERENCE)
def synth_command(
    ctx: typer.Context,
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
            "convection_speed:gain=2,exponent=0.8 or sensor_lag:tau_s=40; a law other than "
            "the first with law=LAW, e.g. convection_speed:law=flat_plate,multiplier=0.5.",
        ),
    ] = None,
    random_effect: Annotated[
        list[str] | None,
        typer.Option(
            "--random-effect",
            help="Undeclared effect with its parameters drawn at random (from --seed) within "
            "its law's physical ranges, NAME or NAME:law=LAW (repeatable), e.g. "
            "friction_speed or convection_speed:law=flat_plate; never empirical.",
        ),
    ] = None,
    effect_drift: Annotated[
        list[str] | None,
        typer.Option(
            "--effect-drift",
            help="A parameter of an --effect or --random-effect that drifts over the days, "
            "PARAMETER=RATE per day (repeatable), e.g. gain=0.2: a component that degrades.",
        ),
    ] = None,
    solar_heating: Annotated[
        float,
        typer.Option(
            "--solar-heating",
            help="An effect OUTSIDE the vocabulary (to see the close loop say 'not adequate'): "
            "sunshine absorbed by the block, W/m^2 at noon UTC, following the hour of day "
            "(sol-air temperature of its air-cooled faces); 0 = none.",
        ),
    ] = 0.0,
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
    refinement: RefinementOption = 1.0,
    solver: Annotated[
        str,
        typer.Option(
            "--solver",
            help="What simulates the blocks: rom (the reduced model) or full (the finite-element "
            "model, exact for inputs held over a step: data the pipeline's reduced model did not "
            "make; slower, use a coarse --refinement).",
        ),
    ] = "rom",
) -> None:
    """Write a synthetic fleet and its truth.

    The fleet as fleet-data.md describes it (fleet.toml and logs/) and its truth
    (OUT_DIR/truth: 1 Hz series, events, anomalies, effects, bad files).
    """
    from fleetbrake.app.progress import generation_bar
    from fleetbrake.model.effects import EffectSet, parse_effect
    from fleetbrake.synth.config import draw_effect
    from fleetbrake.synth.generator import SynthConfig, generate_fleet, summary

    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise OutputDirError(f"{out_dir}: not empty; give a new or empty directory")
    with option_values("--effect"):
        effects = EffectSet(tuple(parse_effect(text) for text in effect or []))
    with option_values("--random-effect"):
        for index, text in enumerate(random_effect or []):
            effects = EffectSet((*effects, draw_effect(text, seed, index)))
    with option_values("--effect-drift"):
        drift = {k.strip(): float(v) for k, _, v in (t.partition("=") for t in effect_drift or [])}
    with option_values("--start"):
        first_day = dt.date.fromisoformat(start)
    make = SynthConfig if imperfections else SynthConfig.clean
    with option_values():  # the message names the setting (wagons, days, ...)
        config = make(
            wagons=wagons,
            days=days,
            seed=seed,
            start=first_day,
            effects=effects,
            anomalies=anomalies,
            gzip_fraction=gzip_fraction,
            refinement=refinement,
            solver=cast(Literal["rom", "full"], solver),  # SynthConfig checks the value
            solar_heating_w_m2=solar_heating,
            effect_drift_per_day=drift,
        )
    total = config.wagons + int(config.unregistered_wagon) + int(config.bad_registry_entry)
    began = time.perf_counter()
    with blas_single_thread(), generation_bar(total, global_options(ctx).progress) as step:
        truth = generate_fleet(out_dir, config, progress=step)
    typer.echo(summary(truth))
    typer.echo(f"generated in {time.perf_counter() - began:.1f} s")


@app.command("record", epilog=CONFIG_REFERENCE)
def record_command(
    ctx: typer.Context,
    wagon: Annotated[str, typer.Option("--wagon", help="Wagon id.")],
    out: Annotated[Path, typer.Option("--out", help="Rerun recording to write (.rrd).")],
    db: Annotated[
        Path, typer.Option("--db", help="DuckDB warehouse (opened read-only).")
    ] = DEFAULT_DB,
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
    wait_s: WaitOption = 0.0,
) -> None:
    """Write a rerun recording of a wagon's timeline (or one event) for incident review.

    Exit 1 when the database does not exist (nothing is created) or cannot be read, or the
    wagon, event or revision is unknown, 75
    when another process is writing the database. Open the file with ``rerun FILE.rrd``.
    """
    from fleetbrake.app.progress import spinner
    from fleetbrake.viz.record import record, wagon_config

    existing_database(db)
    config = wagon_config(wagon, registry) if registry is not None else None
    with spinner(f"recording {event or wagon}", global_options(ctx).progress):
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


@app.command("report")
def report_command(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option("--out", help="Directory for report.md and its plots.")],
    db: Annotated[
        Path, typer.Option("--db", help="DuckDB warehouse (opened read-only).")
    ] = DEFAULT_DB,
    close_loop: Annotated[
        Path | None,
        typer.Option(
            "--close-loop", help="A close-loop JSON report to include (what --json wrote)."
        ),
    ] = None,
) -> None:
    """Write the fleet report: Markdown with plots, from the database's public views only.

    Files, events, predictions against measurements, flags on a timeline, model revisions and,
    with --close-loop, the closed loop's error before and after. Exit 1 when the database does
    not exist (nothing is created) or it or the close-loop report cannot be read.
    """
    import json

    from fleetbrake.app.progress import spinner
    from fleetbrake.app.report import ReportInputError, write_report

    existing_database(db)
    loop: dict[str, object] | None = None
    if close_loop is not None:
        try:
            loop = json.loads(close_loop.read_text(encoding="utf-8"))
        except (OSError, ValueError) as error:
            raise ReportInputError(
                f"{close_loop}: not a readable close-loop report ({error})"
            ) from None
    with spinner("writing the report", global_options(ctx).progress):
        result = write_report(db, out, close_loop=loop)
    typer.echo(f"wrote {result.path} with {len(result.pictures)} pictures")


@app.command("demo", epilog=CONFIG_REFERENCE)
def demo_command(
    ctx: typer.Context,
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
        float,
        typer.Option(
            "--refinement",
            help="Mesh refinement of the reduced model (1.0: the default mesh; 0.6 builds it "
            "in a fifth of the time).",
        ),
    ] = 1.0,
) -> None:
    """Run everything on a synthetic fleet with an undeclared effect and anomalies in it.

    Makes the fleet, runs run, close-loop and record on it, and leaves the fleet, database,
    close-loop report, recordings and a report with plots in --out. A few minutes on 2 cores.
    """
    from fleetbrake.app.demo import DemoConfig, print_summary, run_demo

    config = DemoConfig(wagons=wagons, days=days, seed=seed, refinement=refinement)
    with blas_single_thread():
        result = run_demo(out, config, force=force, progress=global_options(ctx).progress)
    typer.echo("")
    print_summary(result)


@app.command("config")
def config_command(
    check: Annotated[
        Path | None,
        typer.Option(
            "--check",
            help="Print nothing; exit 1 when FILE is not the reference (`make docs` rewrites "
            "docs/configuration.md).",
            metavar="FILE",
        ),
    ] = None,
) -> None:
    """Print the configuration reference (Markdown): every setting, its unit, default and meaning.

    Generated from the configuration classes; docs/configuration.md holds the same text.
    """
    from fleetbrake.cli.configref import render

    text = render()
    if check is None:
        typer.echo(text, nl=False)
        return
    try:
        current = check.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        typer.echo(f"{check}: cannot be read ({error})", err=True)
        raise typer.Exit(1) from None
    if current != text:
        typer.echo(
            f"{check}: not the configuration reference of this code; run `make docs`", err=True
        )
        raise typer.Exit(1)


def main() -> None:
    """Entry point of the ``fleetbrake`` script."""
    app()


if __name__ == "__main__":
    main()
