"""``fleetbrake watch FLEET_DIR --db PATH [--poll S] [--settle S] [--rescan S] [--json]``.

Registered on the main command line by :func:`register`. SIGTERM and SIGINT let the unit in
progress finish and commit, then the command exits 0. Exit 1 when the fleet directory is
missing or goes away, or it cannot be watched; 2 for a bad option or registry; 75 is never
returned for a busy database: the service waits and tries again.
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Literal, cast

import typer

from fleetbrake.cli.options import (
    CONFIG_REFERENCE,
    AddressOption,
    EngineOption,
    RefinementOption,
    WorkersOption,
)
from fleetbrake.cli.signals import stop_on_signals
from fleetbrake.errors import ConfigError

__all__ = ["register", "watch_command"]

SERVICE_LOGGER = "fleetbrake.app.watch"


class WatchOptionError(ConfigError):
    """An option of ``fleetbrake watch`` cannot be used (exit 2); the message names it."""


@contextlib.contextmanager
def _service_log_level() -> Iterator[None]:
    """The service's own records (health line, units) at info level at least, unless the
    command line asked for errors only (``--quiet``)."""
    ours = logging.getLogger(SERVICE_LOGGER)
    before = ours.level
    effective = logging.getLogger("fleetbrake").getEffectiveLevel()
    if effective <= logging.WARNING:
        ours.setLevel(min(effective, logging.INFO))
    try:
        yield
    finally:
        ours.setLevel(before)


def watch_command(
    fleet_dir: Annotated[
        Path, typer.Argument(help="Fleet directory: fleet.toml and logs/.", metavar="FLEET_DIR")
    ],
    db: Annotated[Path, typer.Option("--db", help="DuckDB warehouse.")] = Path(
        "warehouse/fleet.duckdb"
    ),
    poll_s: Annotated[
        float | None,
        typer.Option(
            "--poll",
            help="Poll logs/ every S seconds instead of inotify (network filesystems).",
            metavar="S",
        ),
    ] = None,
    settle_s: Annotated[
        float,
        typer.Option(
            "--settle",
            help="A file neither renamed into place nor closed is taken once unchanged for S "
            "seconds.",
            metavar="S",
        ),
    ] = 5.0,
    rescan_s: Annotated[
        float,
        typer.Option(
            "--rescan",
            help="Full rescan against the ingestion ledger every S seconds.",
            metavar="S",
        ),
    ] = 300.0,
    wait_s: Annotated[
        float,
        typer.Option(
            "--wait",
            help="Seconds a unit waits for the database (readers, another writer) before it is "
            "tried again later.",
        ),
    ] = 30.0,
    flag_config: Annotated[
        Path | None, typer.Option("--flag-config", help="TOML file of flag thresholds.")
    ] = None,
    solver: Annotated[
        str, typer.Option("--solver", help="Model of a new `declared` revision: rom or full.")
    ] = "rom",
    refinement: RefinementOption = 1.0,
    engine: EngineOption = "local",
    workers: WorkersOption = None,
    address: AddressOption = None,
    json_lines: Annotated[
        bool,
        typer.Option("--json", help="One JSON object per processed file on stdout."),
    ] = False,
    rerun: Annotated[
        str | None,
        typer.Option(
            "--rerun",
            help="Stream each processed file's new timeline to the rerun viewer at ADDR "
            "(HOST:PORT or rerun+http://HOST:PORT/proxy), as `record` lays it out; a viewer "
            "that is not there is a warning, tried again at the next file.",
            metavar="ADDR",
        ),
    ] = None,
) -> None:
    """Watch FLEET_DIR/logs/ and take every file that lands complete through `run`.

    A file is taken once renamed into place, closed after writing, or unchanged for --settle
    seconds; a full rescan at start and every --rescan seconds. The database is held only
    while a unit is processed (readers get in between). SIGTERM/SIGINT: finish the unit in
    progress, commit, exit 0. Exit 1 when the fleet directory is missing or gone or cannot
    be watched, 2 for a bad option, registry or --flag-config.
    """
    from fleetbrake.app.watch.service import FileOutcome, WatchConfig, watch_fleet
    from fleetbrake.flags import load_flag_config
    from fleetbrake.simulation.config import SimulationConfig

    if solver not in ("rom", "full"):
        raise WatchOptionError(f"--solver must be rom or full, got {solver!r}")
    if not refinement > 0:
        raise WatchOptionError(f"--refinement must be > 0, got {refinement}")
    if flag_config is not None:
        load_flag_config(flag_config)  # a bad file is a usage error before watching
    if rerun is not None:
        from fleetbrake.viz.live import viewer_url

        viewer_url(rerun)  # not a viewer's address: a usage error (exit 2) before watching
    try:
        config = WatchConfig(
            poll_s=poll_s,
            settle_s=settle_s,
            rescan_s=rescan_s,
            wait_s=wait_s,
            flag_config_path=flag_config,
            engine=engine,
            workers=workers,
            address=address,
            rerun=rerun,
            simulation=SimulationConfig(
                solver=cast(Literal["rom", "full"], solver), refinement=refinement
            ),
        )
    except ValueError as error:
        raise WatchOptionError(f"--poll, --settle, --rescan, --wait, --workers: {error}") from None

    def on_file(outcome: FileOutcome) -> None:
        if json_lines:
            typer.echo(json.dumps(outcome.as_dict()))
            return
        flags = ", ".join(f"{n} {k}" for k, n in outcome.flags.items()) or "no flags"
        why = f": {outcome.reason}" if outcome.reason else ""
        typer.echo(
            f"{outcome.status} {outcome.path} (wagon {outcome.wagon}, "
            f"{outcome.seconds:.1f} s, {flags}){why}"
        )

    stop = threading.Event()
    with _service_log_level(), stop_on_signals(stop, logging.getLogger(SERVICE_LOGGER)):
        report = watch_fleet(fleet_dir, db, config, stop, on_file=on_file)
    if not json_lines:
        typer.echo(f"watch stopped: {report.line()}")


def register(app: typer.Typer) -> None:
    """Add the ``watch`` command to ``app``."""
    app.command("watch", epilog=CONFIG_REFERENCE)(watch_command)
