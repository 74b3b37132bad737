"""The ``fleetbrake`` command line (contract: ``shared/spec/interface.md``).

Each command is a thin shell: it parses arguments, calls one function of the package, and
turns expected failures into a clear message and a non-zero exit code.
"""

from __future__ import annotations

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

    Bad files are quarantined and reported (exit 0); exit 1 when the fleet directory, its
    registry or the database cannot be used, 75 when another process is writing the database.
    """
    from fleetbrake.ingest import FleetDirError, print_report, run_ingest
    from fleetbrake.registry import RegistryError
    from fleetbrake.warehouse import WarehouseError, WarehouseLockedError

    try:
        report = run_ingest(fleet_dir, db, wait_s=wait_s)
    except WarehouseLockedError as error:
        typer.echo(f"fleetbrake ingest: {error}", err=True)
        raise typer.Exit(EXIT_LOCKED) from None
    except (FleetDirError, RegistryError, WarehouseError) as error:
        typer.echo(f"fleetbrake ingest: {error}", err=True)
        raise typer.Exit(EXIT_FAILED) from None
    print_report(report)


@bench_app.command("ingest")
def bench_ingest_command(
    json_out: Annotated[bool, typer.Option("--json", help="Last line: one JSON object.")] = False,
    rows: Annotated[
        int, typer.Option("--rows", help="Samples in the synthetic gzip fleet.")
    ] = 2_000_000,
    workdir: Annotated[
        Path | None, typer.Option("--workdir", help="Where to make the temporary directory.")
    ] = None,
) -> None:
    """Ingestion speed and peak memory on a synthetic gzip fleet (events excluded)."""
    import json

    from fleetbrake.bench_ingest import bench_ingest

    figures = bench_ingest(rows, workdir=workdir)
    typer.echo(
        f"ingested {figures['rows']:,} rows ({figures['files']} gzip files, "
        f"{figures['gzip_mb']} MB) in {figures['seconds']} s: "
        f"{figures['rows_per_s']:,} rows/s, peak RSS {figures['peak_rss_mb']} MB"
    )
    if json_out:
        typer.echo(json.dumps(figures))


def main() -> None:
    """Entry point of the ``fleetbrake`` script."""
    app()


if __name__ == "__main__":
    main()
