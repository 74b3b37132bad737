"""The one place where expected failures become a message and an exit code.

Every expected failure of the package is a :class:`fleetbrake.errors.FleetbrakeError`
carrying its exit code (1 could not do its job, 2 bad usage or configuration, 75 database
held by another writer). :class:`FleetbrakeGroup` is the class of the ``fleetbrake`` command
group (and of its sub-groups): when the command it runs raises one, it writes
``fleetbrake COMMAND: message`` on stderr (a JSON log record with ``--log-format json``), no
traceback, and exits with the error's code. It works alike for the installed ``fleetbrake``
script and for :class:`typer.testing.CliRunner`. Anything else that escapes is a bug and
shows its traceback.
"""

from __future__ import annotations

import logging
from typing import Any

import typer
from typer.core import TyperGroup

from fleetbrake.cli.logs import LogFormat
from fleetbrake.cli.options import global_options
from fleetbrake.errors import FleetbrakeError

__all__ = ["FleetbrakeGroup", "command_name"]

logger = logging.getLogger(__name__)


def command_name(ctx: typer.Context) -> str:
    """``fleetbrake`` and the (sub)command names that led to ``ctx``'s invoked subcommand,
    e.g. ``fleetbrake bench solver``."""
    names: list[str] = []
    here: Any = ctx
    while here.parent is not None:
        names.insert(0, here.info_name or "")
        here = here.parent
    if ctx.invoked_subcommand:
        names.append(ctx.invoked_subcommand)
    return " ".join(["fleetbrake", *names])


def report_error(ctx: typer.Context, error: FleetbrakeError) -> None:
    """The error's one line, on stderr: as text, or as a JSON log record."""
    command = command_name(ctx)
    if global_options(ctx).log_format is LogFormat.JSON:
        logger.error(
            "%s: %s", command, error, extra={"command": command, "exit_code": error.exit_code}
        )
    else:
        typer.echo(f"{command}: {error}", err=True)


class FleetbrakeGroup(TyperGroup):
    """A command group that maps :class:`FleetbrakeError` to its message and exit code."""

    def invoke(self, ctx: typer.Context) -> Any:  # type: ignore[override]  # typer's Context
        try:
            return super().invoke(ctx)
        except FleetbrakeError as error:
            report_error(ctx, error)
            raise typer.Exit(error.exit_code) from None
