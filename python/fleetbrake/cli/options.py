"""What every command shares: the global options (``--log-format``, ``--quiet``,
``--verbose``) as one typed object, the options several commands take, and the error for a
command-line value that cannot be used."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from fleetbrake.cli.logs import LogFormat
from fleetbrake.errors import ConfigError, FleetbrakeError

__all__ = [
    "CONFIG_REFERENCE",
    "DbOption",
    "FleetDirArgument",
    "GlobalOptions",
    "MissingDatabaseError",
    "OptionError",
    "OutputDirError",
    "WaitOption",
    "existing_database",
    "global_options",
    "option_values",
]

DEFAULT_DB = Path("warehouse/fleet.duckdb")
"""``--db`` when not given (contract: ``shared/spec/interface.md``)."""

CONFIG_REFERENCE = (
    "Every setting (registry keys, flag thresholds, options), with its unit, default and "
    "meaning: docs/configuration.md, or `fleetbrake config`."
)
"""The epilog of ``fleetbrake --help`` and of the commands that read configuration."""


class OptionError(ConfigError):
    """A command-line value cannot be used (exit 2); the message names the option."""


class OutputDirError(FleetbrakeError):
    """An output directory given on the command line holds something already (exit 1, as
    ``fleetbrake demo`` refuses one); the message names it."""


class MissingDatabaseError(FleetbrakeError):
    """A command that reads a warehouse was given a path where none exists (exit 1); it is
    refused before anything is opened, so that no file, folder or lock is left behind."""


def existing_database(db: Path) -> Path:
    """``db`` if a warehouse file is there; :class:`MissingDatabaseError` otherwise.

    For the commands that need a warehouse ``run`` made (``close-loop``, ``record``,
    ``report``): opening a path for writing would create an empty database, its folder and
    its lock file before the command finds it has nothing to work on.
    """
    if db.is_file():
        return db
    if db.exists():
        raise MissingDatabaseError(f"{db}: not a database file; nothing was changed")
    raise MissingDatabaseError(
        f"{db}: no such database: run `fleetbrake run` first; nothing was created"
    )


@dataclass(frozen=True)
class GlobalOptions:
    """The options given before the command (``fleetbrake --quiet run ...``).

    Read by: ``fleetbrake``.
    """

    log_format: LogFormat = LogFormat.TEXT
    """Log records on stderr as ``text``, or as ``json`` (one object per line)."""
    log_level: int = logging.WARNING
    """Level of the records shown (``logging``'s numbers): warnings by default, errors only
    with ``--quiet``, info with ``-v``, debug with ``-vv``."""
    quiet: bool = False
    """Errors only on stderr, and no progress bars."""
    progress: bool = False
    """Draw progress bars and spinners: stdout is a terminal and not ``--quiet``."""


def global_options(ctx: typer.Context) -> GlobalOptions:
    """The :class:`GlobalOptions` of the command run in ``ctx`` (the defaults when the
    callback that sets them has not run)."""
    obj = ctx.find_root().obj
    return obj if isinstance(obj, GlobalOptions) else GlobalOptions()


@contextlib.contextmanager
def option_values(*options: str) -> Iterator[None]:
    """Turn the ``ValueError`` of a value built from ``options`` (a configuration object's
    check, a date's parsing) into an :class:`OptionError` naming them (no names: the
    message names the setting already); the library's own expected failures pass through
    as they are."""
    try:
        yield
    except FleetbrakeError:
        raise
    except ValueError as error:
        named = f"{', '.join(options)}: " if options else ""
        raise OptionError(f"{named}{error}") from None


DbOption = Annotated[Path, typer.Option("--db", help="DuckDB warehouse.")]
EngineOption = Annotated[
    str,
    typer.Option(
        "--engine",
        help="Where partitions run: local (worker processes on this machine, default); "
        'ray (Ray tasks: pip install "fleetbrake\\[ray]").',
    ),
]
AddressOption = Annotated[
    str | None,
    typer.Option(
        "--address",
        help="Ray cluster to connect to with --engine ray (default: a local one of --workers "
        "CPUs).",
    ),
]
WorkersOption = Annotated[
    int | None,
    typer.Option(
        "--workers",
        help="Partitions at once: worker processes of the local engine, CPUs of a local Ray "
        "instance (default: the cores; with --address, the cluster's CPUs).",
    ),
]
RefinementOption = Annotated[
    float,
    typer.Option("--refinement", help="Mesh refinement of the model (1.0: the default mesh)."),
]
WaitOption = Annotated[
    float,
    typer.Option("--wait", help="Seconds to wait for another process writing the database."),
]
FleetDirArgument = Annotated[
    Path, typer.Argument(help="Fleet directory: fleet.toml and logs/.", metavar="FLEET_DIR")
]
