"""``fleetbrake bridge ...``: the bridge commands, added to the command line by
:func:`register` (``register(app)`` in ``fleetbrake.cli.main``).

``fleetbrake bridge mqtt --broker URL --topic PATTERN --landing FLEET_DIR`` runs until SIGTERM
or SIGINT, then writes what it holds, acknowledges it and exits 0, after one summary line on
stdout (and one JSON object with ``--json``). Expected failures are
:class:`~fleetbrake.errors.FleetbrakeError`: a bad setting (exit 2), a landing folder that is
missing or cannot be written (exit 1), another bridge with the same client id on the folder
(exit 75).
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Annotated, Any

import typer
from typer.core import TyperGroup

from fleetbrake.bridge.config import (
    DEFAULT_CLIENT_ID,
    DEFAULT_TOPIC,
    BridgeConfig,
    MqttProtocol,
)
from fleetbrake.cli.options import CONFIG_REFERENCE
from fleetbrake.cli.signals import stop_on_signals

__all__ = ["bridge_app", "register", "stop_on_signals"]

bridge_app = typer.Typer(
    help="Land samples from other transports as log files of the fleet format.",
    no_args_is_help=True,
)

_DEFAULTS = BridgeConfig(broker="mqtt://localhost", landing=Path("."))
"""The defaults shown in ``--help`` (the one place they are set is :class:`BridgeConfig`)."""


def register(app: typer.Typer) -> None:
    """Add the ``bridge`` command group to ``app``, with ``app``'s group class (the one that
    maps :class:`~fleetbrake.errors.FleetbrakeError` to its message and exit code)."""
    options: dict[str, Any] = {}
    group_class = app.info.cls
    if isinstance(group_class, type) and issubclass(group_class, TyperGroup):
        options["cls"] = group_class
    app.add_typer(bridge_app, name="bridge", **options)


@bridge_app.command("mqtt", epilog=CONFIG_REFERENCE)
def mqtt_command(
    broker: Annotated[
        str,
        typer.Option(
            "--broker",
            help="Broker URL: mqtt://[user[:password]@]host[:port], mqtts://... for TLS.",
        ),
    ],
    landing: Annotated[
        Path,
        typer.Option("--landing", help="Fleet directory that receives logs/<wagon>/*.csv."),
    ],
    topic: Annotated[
        str, typer.Option("--topic", help="Topic filter, the wagon id at one level.")
    ] = DEFAULT_TOPIC,
    wagon_level: Annotated[
        int | None,
        typer.Option(
            "--wagon-level", help="Topic level (from 0) of the wagon id; default: the first +."
        ),
    ] = None,
    client_id: Annotated[
        str,
        typer.Option(
            "--client-id", help="MQTT client id: the broker's session; keep it across restarts."
        ),
    ] = DEFAULT_CLIENT_ID,
    protocol: Annotated[
        MqttProtocol, typer.Option("--protocol", help="MQTT protocol version.")
    ] = MqttProtocol.V5,
    password_file: Annotated[
        Path | None,
        typer.Option("--password-file", help="File whose first line is the broker password."),
    ] = None,
    gap_s: Annotated[
        float,
        typer.Option("--gap", help="Seconds between two samples that end a wagon's session."),
    ] = _DEFAULTS.gap_s,
    max_file_s: Annotated[
        float, typer.Option("--max-file", help="Longest span of one log file, seconds.")
    ] = _DEFAULTS.max_file_s,
    idle_s: Annotated[
        float,
        typer.Option(
            "--idle", help="Seconds without new samples after which a session is written."
        ),
    ] = _DEFAULTS.idle_s,
    max_unacked: Annotated[
        int,
        typer.Option(
            "--max-unacked", help="Most messages held unacknowledged (MQTT 5 Receive Maximum)."
        ),
    ] = _DEFAULTS.max_unacked,
    session_expiry_s: Annotated[
        int,
        typer.Option(
            "--session-expiry", help="MQTT 5: seconds the broker keeps the session while away."
        ),
    ] = _DEFAULTS.session_expiry_s,
    gzip: Annotated[bool, typer.Option("--gzip", help="Write .csv.gz files.")] = False,
    json_out: Annotated[
        bool, typer.Option("--json", help="Last line of stdout: one JSON summary.")
    ] = False,
) -> None:
    """Receive samples over MQTT and write them as log files into the landing folder.

    A message is acknowledged once the file holding its samples is on disk; a bad message
    is logged with its topic and acknowledged. SIGTERM or SIGINT: write what is held,
    acknowledge it, exit 0. Exit 2 bad setting, 1 landing folder unusable, 75 another
    bridge with this client id writes into the folder.
    """
    from fleetbrake.bridge.mqtt import run_bridge

    config = BridgeConfig(
        broker=broker,
        landing=landing,
        topic=topic,
        wagon_level=wagon_level,
        client_id=client_id,
        protocol=protocol,
        password_file=password_file,
        gap_s=gap_s,
        max_file_s=max_file_s,
        idle_s=idle_s,
        max_unacked=max_unacked,
        session_expiry_s=session_expiry_s,
        gzip=gzip,
    )
    config.password()  # an unreadable password file is a usage error, before connecting
    stop = threading.Event()
    with stop_on_signals(stop):
        report = run_bridge(config, stop)
    typer.echo(f"bridge stopped: {report.line()}")
    if json_out:
        typer.echo(json.dumps(report.as_dict()))
