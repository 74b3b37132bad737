"""The bridge's settings: one frozen object, checked when it is made.

Every value a user can give on the command line is a field of :class:`BridgeConfig`; a value
that cannot be used raises :class:`BridgeConfigError` (exit 2) naming the setting.
"""

from __future__ import annotations

import enum
import math
import re
import urllib.parse
from dataclasses import dataclass, fields
from pathlib import Path

from fleetbrake.errors import ConfigError

__all__ = [
    "DEFAULT_CLIENT_ID",
    "DEFAULT_TOPIC",
    "BridgeConfig",
    "BridgeConfigError",
    "BrokerAddress",
    "MqttProtocol",
]

DEFAULT_TOPIC = "fleet/+/samples"
"""The topic filter subscribed to: one topic per wagon, the wagon id at the ``+`` level."""

DEFAULT_CLIENT_ID = "fleetbrake-bridge"
"""The MQTT client id: the name of the broker's persistent session that holds the messages
not yet acknowledged while the bridge is down. Keep it stable across restarts."""

CLIENT_ID_PATTERN = re.compile(r"[A-Za-z0-9_.-]{1,64}")
"""What a client id may be (it also names the bridge's lock and temporary files)."""

RECEIVE_MAXIMUM_LIMIT = 65_535
"""The largest Receive Maximum MQTT 5 can carry."""


class BridgeConfigError(ConfigError):
    """A bridge setting cannot be used (exit 2); the message names the setting."""


class MqttProtocol(enum.StrEnum):
    """The MQTT protocol version spoken to the broker."""

    V5 = "5"
    """MQTT 5: persistent session by ``clean_start=False`` and a session expiry interval; the
    broker sends at most ``max_unacked`` messages without acknowledgement (Receive Maximum)."""
    V311 = "3.1.1"
    """MQTT 3.1.1: persistent session by ``clean_session=False``; how many messages the broker
    sends unacknowledged is the broker's setting (mosquitto: ``max_inflight_messages``)."""


@dataclass(frozen=True)
class BrokerAddress:
    """Where the broker is: ``mqtt://[user[:password]@]host[:port]`` (``mqtts://`` for TLS)."""

    host: str
    port: int
    tls: bool
    username: str | None = None
    password: str | None = None

    @classmethod
    def parse(cls, url: str) -> BrokerAddress:
        """Read a broker URL; :class:`BridgeConfigError` naming it when it is not one.

        Schemes: ``mqtt`` and ``tcp`` (plain, port 1883 by default), ``mqtts`` and ``ssl``
        (TLS with the system's certificate authorities, port 8883 by default).
        """
        parsed = urllib.parse.urlsplit(url)
        scheme = parsed.scheme.lower()
        if scheme not in ("mqtt", "tcp", "mqtts", "ssl"):
            raise BridgeConfigError(
                f"--broker {url!r}: not a broker URL (mqtt://host[:port] or mqtts://host[:port])"
            )
        tls = scheme in ("mqtts", "ssl")
        try:
            port = parsed.port
        except ValueError:
            raise BridgeConfigError(f"--broker {url!r}: the port is not a number") from None
        if not parsed.hostname:
            raise BridgeConfigError(f"--broker {url!r}: no host")
        if parsed.path not in ("", "/") or parsed.query or parsed.fragment:
            raise BridgeConfigError(f"--broker {url!r}: a broker URL has no path or query")
        return cls(
            host=parsed.hostname,
            port=port if port is not None else (8883 if tls else 1883),
            tls=tls,
            username=urllib.parse.unquote(parsed.username) if parsed.username else None,
            password=urllib.parse.unquote(parsed.password) if parsed.password else None,
        )

    def __str__(self) -> str:  # never shows the password
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"


def _topic_levels(topic: str) -> list[str]:
    """The levels of an MQTT topic filter; :class:`BridgeConfigError` if it is not one."""
    if not topic or "\x00" in topic or len(topic.encode("utf-8")) > 65_535:
        raise BridgeConfigError(f"--topic {topic!r}: not an MQTT topic filter")
    levels = topic.split("/")
    for i, level in enumerate(levels):
        if ("+" in level and level != "+") or ("#" in level and level != "#"):
            raise BridgeConfigError(
                f"--topic {topic!r}: a wildcard (+ or #) must be a whole topic level"
            )
        if level == "#" and i != len(levels) - 1:
            raise BridgeConfigError(f"--topic {topic!r}: # must be the last topic level")
    return levels


@dataclass(frozen=True)
class BridgeConfig:
    """Everything ``fleetbrake bridge mqtt`` needs; see ``docs/operations.md``.

    Read by: ``fleetbrake bridge mqtt``.
    """

    broker: str
    """Broker URL, ``mqtt://[user[:password]@]host[:port]`` or ``mqtts://...`` for TLS."""
    landing: Path
    """The fleet directory that receives the log files (``logs/<wagon>/...``); must exist."""
    topic: str = DEFAULT_TOPIC
    """Topic filter subscribed to with QoS 1."""
    wagon_level: int | None = None
    """Index (from 0) of the topic level that holds the wagon id; None: the first ``+``."""
    client_id: str = DEFAULT_CLIENT_ID
    """MQTT client id, the name of the persistent session: the same across restarts."""
    protocol: MqttProtocol = MqttProtocol.V5
    """MQTT protocol version spoken to the broker: ``5`` or ``3.1.1``."""
    password_file: Path | None = None
    """A file whose first line is the broker password (instead of one in the URL, which
    other users of the machine can read in the process list)."""
    session_expiry_s: int = 7 * 24 * 3600
    """MQTT 5: how long the broker keeps the session (and queues messages) while the bridge
    is away."""
    keepalive_s: int = 60
    """MQTT keep-alive: the longest silence towards the broker before a ping."""
    gap_s: float = 300.0
    """A sample more than this after the last one of a wagon's open session ends the session."""
    max_file_s: float = 3600.0
    """A log file spans less than this (time of its last sample minus its first)."""
    idle_s: float = 60.0
    """A wagon's session that has received no new sample for this long (wall clock) is
    written: the longest a message waits for its acknowledgement while its wagon is silent."""
    max_unacked: int = 1000
    """Most messages held unacknowledged (MQTT 5: the Receive Maximum given to the broker);
    reaching it writes every open session."""
    max_buffered_samples: int = 200_000
    """Most samples held in open sessions; reaching it writes every open session."""
    gzip: bool = False
    """Write ``.csv.gz`` files instead of ``.csv``."""
    lookback_s: float = 48 * 3600
    """How far before a session's first sample the wagon's files already landed are read to
    drop samples they hold (a file of the format spans at most 48 h)."""
    max_payload_bytes: int = 16 * 1024 * 1024
    """A larger message is dropped (logged with its topic) and acknowledged."""
    reconnect_min_s: float = 1.0
    """First wait before connecting again after the broker was lost; doubled at each failure."""
    reconnect_max_s: float = 60.0
    """Longest wait between two attempts to connect again."""
    health_every_s: float = 60.0
    """Seconds between two health lines in the log (level INFO)."""
    tick_s: float = 0.2
    """Longest wait of the network loop: how soon timers and a stop request are seen."""

    def __post_init__(self) -> None:
        self.address  # noqa: B018  (parse the URL now: a bad one is a usage error)
        self.wagon_topic_level  # noqa: B018
        if not CLIENT_ID_PATTERN.fullmatch(self.client_id):
            raise BridgeConfigError(
                f"--client-id {self.client_id!r}: must match {CLIENT_ID_PATTERN.pattern}"
            )
        if not 1 <= self.max_unacked <= RECEIVE_MAXIMUM_LIMIT:
            raise BridgeConfigError(
                f"--max-unacked {self.max_unacked}: must be in [1, {RECEIVE_MAXIMUM_LIMIT}]"
            )
        for spec in fields(self):
            value = getattr(self, spec.name)
            if spec.name.endswith("_s") and isinstance(value, int | float):
                if not math.isfinite(value) or value <= 0:
                    raise BridgeConfigError(f"{spec.name} = {value}: must be a positive number")
        if self.gap_s < 1 or self.max_file_s < 1:
            raise BridgeConfigError(
                f"gap_s = {self.gap_s}, max_file_s = {self.max_file_s}: samples are 1 s apart, "
                "both must be at least 1"
            )
        if self.max_buffered_samples < 1 or self.max_payload_bytes < 1:
            raise BridgeConfigError("max_buffered_samples and max_payload_bytes must be positive")
        if self.password_file is not None and self.address.username is None:
            raise BridgeConfigError(
                f"--password-file {self.password_file}: give the user name in --broker "
                "(mqtt://user@host)"
            )
        if self.reconnect_max_s < self.reconnect_min_s:
            raise BridgeConfigError(
                f"reconnect_max_s = {self.reconnect_max_s} is below "
                f"reconnect_min_s = {self.reconnect_min_s}"
            )

    @property
    def address(self) -> BrokerAddress:
        """The broker's address, parsed from :attr:`broker`."""
        return BrokerAddress.parse(self.broker)

    @property
    def wagon_topic_level(self) -> int:
        """Index of the topic level that holds the wagon id."""
        levels = _topic_levels(self.topic)
        if self.wagon_level is None:
            if "+" not in levels:
                raise BridgeConfigError(
                    f"--topic {self.topic!r} has no + level: give --wagon-level, the index of "
                    "the level that holds the wagon id"
                )
            return levels.index("+")
        if self.wagon_level < 0 or (self.wagon_level >= len(levels) and levels[-1] != "#"):
            raise BridgeConfigError(
                f"--wagon-level {self.wagon_level}: --topic {self.topic!r} has no such level"
            )
        return self.wagon_level

    def password(self) -> str | None:
        """The broker password: the first line of :attr:`password_file`, else the URL's."""
        if self.password_file is None:
            return self.address.password
        try:
            text = self.password_file.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as error:
            raise BridgeConfigError(
                f"--password-file {self.password_file}: cannot be read ({error})"
            ) from None
        lines = text.splitlines()
        return lines[0] if lines else ""
