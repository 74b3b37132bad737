"""The MQTT bridge: samples from a broker into log files of the landing folder.

::

    from fleetbrake.bridge import BridgeConfig, run_bridge

    stop = threading.Event()                       # set it (a signal handler) to stop
    report = run_bridge(BridgeConfig("mqtt://broker:1883", Path("fleet")), stop)

How it behaves (``docs/operations.md`` for the operator's view):

* **Connection.** paho-mqtt 2 (callback API version 2), a stable client id, a persistent
  session (MQTT 5: ``clean_start=False`` with a session expiry interval; 3.1.1:
  ``clean_session=False``), the topic filter subscribed with QoS 1 at every connection. A lost
  or refused connection is tried again after a wait that doubles from ``reconnect_min_s`` up
  to ``reconnect_max_s``; meanwhile sessions still close and are written. One thread: the
  network loop, the sessions, the writing and the acknowledgements take turns, so nothing is
  shared between threads.
* **Messages** (format: :mod:`fleetbrake.bridge.payload`) are acknowledged by hand
  (``manual_ack=True``): a message is acknowledged once every session holding one of its
  samples is written durably (:mod:`fleetbrake.bridge.landing`). A message that is not one of
  the format is logged (level ERROR, naming the topic and the reason), counted, and
  acknowledged at once: a poison message must not come back forever, nor stop the bridge.
* **Sessions** (:mod:`fleetbrake.bridge.sessions`) close on a gap in the samples' time, at the
  longest file span, after ``idle_s`` without new samples, when ``max_unacked`` messages or
  ``max_buffered_samples`` samples are held (every open session is written then), and when the
  bridge stops.
* **Redelivery.** After a reconnection to a session the broker kept, it sends again what was
  not acknowledged, with the same packet ids: such a message is recognised by its id and the
  samples it brings again are duplicates of held ones. When the broker kept no session
  (``session present`` false), ids of the old session mean nothing any more: their messages
  are not acknowledged, but their samples are still written. Samples that a crash left in a
  file before their message was acknowledged are dropped by the landing folder.
* **Stopping.** When ``stop`` is set (the command sets it on SIGTERM and SIGINT): every open
  session is written, its messages acknowledged, the connection closed; :func:`run_bridge`
  returns its :class:`BridgeReport`.
"""

from __future__ import annotations

import logging
import ssl
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.reasoncodes import ReasonCode

from fleetbrake.bridge.config import BridgeConfig, MqttProtocol
from fleetbrake.bridge.landing import LandingFolder
from fleetbrake.bridge.payload import PayloadError, parse_message, utc_of
from fleetbrake.bridge.sessions import Session, SessionBuffer
from fleetbrake.fleet.logfile import TIME_FORMAT

__all__ = ["BridgeReport", "MqttBridge", "run_bridge"]

logger = logging.getLogger(__name__)

_DISCONNECT_WAIT_S = 5.0
"""Longest wait for the last acknowledgements and the DISCONNECT to go out when stopping."""


@dataclass
class BridgeReport:
    """What a bridge did, from its start to its stop."""

    messages: int = 0
    """Messages received, rejected ones included (a redelivered one counts again)."""
    samples: int = 0
    """Samples taken into sessions (not duplicates of held ones)."""
    rejected: int = 0
    """Messages not of the format: logged, counted, acknowledged."""
    duplicates: int = 0
    """Samples dropped because their wagon's second was held already (in a session or a file)."""
    conflicts: int = 0
    """Samples dropped because a file that is not the bridge's holds their file name."""
    files: int = 0
    """Log files written."""
    rows: int = 0
    """Samples written into them."""
    acked: int = 0
    """Acknowledgements sent."""
    connections: int = 0
    """Successful connections to the broker."""

    def as_dict(self) -> dict[str, int]:
        return asdict(self)

    def line(self) -> str:
        """One sentence for a person."""
        return (
            f"{self.messages} messages ({self.rejected} rejected), {self.samples} samples, "
            f"{self.files} files of {self.rows} rows written, {self.duplicates} duplicate "
            f"samples dropped, {self.acked} acknowledged"
        )


@dataclass
class _Held:
    """A message with samples in open sessions, not acknowledged yet."""

    mid: int | None
    """Its packet id while it can be acknowledged (None: QoS 0, or an id of a session the
    broker no longer has)."""
    holds: int = 0
    """Open sessions holding its samples, plus one while it is being taken in."""


def _reason(code: ReasonCode | MQTTErrorCode | int) -> str:
    return getattr(code, "getName", lambda: str(code))()


class MqttBridge:
    """One bridge: a paho client, the open sessions, the messages held, the landing folder."""

    def __init__(self, config: BridgeConfig, landing: LandingFolder) -> None:
        self.config = config
        self.landing = landing
        self.report = BridgeReport()
        self._wagon_level = config.wagon_topic_level
        self._buffer = SessionBuffer(config.gap_s, config.max_file_s)
        self._held: dict[int, _Held] = {}
        self._key_of_mid: dict[int, int] = {}
        self._next_key = 0
        self._online = False
        self._stopping = False
        self.subscribed = False
        """The broker acknowledged the subscription on the current connection."""
        self._backoff_s = config.reconnect_min_s
        self._next_health_s = time.monotonic() + config.health_every_s
        self._next_idle_check_s = 0.0
        self._client = self._make_client()

    # ------------------------------------------------------------------ client

    def _make_client(self) -> mqtt.Client:
        config = self.config
        if config.protocol is MqttProtocol.V5:
            client = mqtt.Client(
                CallbackAPIVersion.VERSION2,
                client_id=config.client_id,
                protocol=mqtt.MQTTv5,
                manual_ack=True,
                reconnect_on_failure=False,
            )
        else:
            client = mqtt.Client(
                CallbackAPIVersion.VERSION2,
                client_id=config.client_id,
                clean_session=False,
                protocol=mqtt.MQTTv311,
                manual_ack=True,
                reconnect_on_failure=False,
            )
        address = config.address
        if address.username is not None:
            client.username_pw_set(address.username, config.password())
        if address.tls:
            client.tls_set(cert_reqs=ssl.CERT_REQUIRED)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        client.on_subscribe = self._on_subscribe
        return client

    def _connect(self) -> None:
        """Open the connection (the CONNACK comes in the loop); OSError if it cannot."""
        config = self.config
        address = config.address
        if config.protocol is MqttProtocol.V5:
            properties = Properties(PacketTypes.CONNECT)  # type: ignore[no-untyped-call]  # paho leaves it unannotated
            properties.SessionExpiryInterval = config.session_expiry_s
            properties.ReceiveMaximum = config.max_unacked
            self._client.connect(
                address.host,
                address.port,
                keepalive=config.keepalive_s,
                clean_start=False,
                properties=properties,
            )
        else:
            self._client.connect(address.host, address.port, keepalive=config.keepalive_s)

    def _on_connect(
        self,
        client: mqtt.Client,
        userdata: Any,
        flags: mqtt.ConnectFlags,
        reason_code: ReasonCode,
        properties: Properties | None,
    ) -> None:
        if reason_code.is_failure:
            logger.error(
                "broker %s refused the connection of %s: %s",
                self.config.address,
                self.config.client_id,
                _reason(reason_code),
            )
            return
        self._online = True
        self._backoff_s = self.config.reconnect_min_s
        self.report.connections += 1
        if not flags.session_present:
            if self._key_of_mid:
                logger.warning(
                    "broker %s kept no session for %s: %d messages of the old session cannot "
                    "be acknowledged (their samples are written all the same)",
                    self.config.address,
                    self.config.client_id,
                    len(self._key_of_mid),
                )
            for held in self._held.values():
                held.mid = None
            self._key_of_mid.clear()
        logger.info(
            "connected to %s as %s (session %s), subscribing to %s",
            self.config.address,
            self.config.client_id,
            "resumed" if flags.session_present else "new",
            self.config.topic,
        )
        client.subscribe(self.config.topic, qos=1)

    def _on_subscribe(
        self,
        client: mqtt.Client,
        userdata: Any,
        mid: int,
        reason_codes: list[ReasonCode],
        properties: Properties | None,
    ) -> None:
        for code in reason_codes:
            if code.is_failure:
                logger.error(
                    "broker %s refused the subscription to %s: %s",
                    self.config.address,
                    self.config.topic,
                    _reason(code),
                )
                return
            if code.value < 1:
                logger.warning(
                    "broker %s granted %s with QoS 0 only: messages may be lost",
                    self.config.address,
                    self.config.topic,
                )
        self.subscribed = True
        logger.info("subscribed to %s", self.config.topic)

    def _on_disconnect(
        self,
        client: mqtt.Client,
        userdata: Any,
        flags: mqtt.DisconnectFlags,
        reason_code: ReasonCode,
        properties: Properties | None,
    ) -> None:
        if self._online and not self._stopping:
            logger.warning("disconnected from %s: %s", self.config.address, _reason(reason_code))
        self._online = self.subscribed = False

    # ------------------------------------------------------------------ messages

    def _key_for(self, message: mqtt.MQTTMessage) -> int:
        """The key of a message: a redelivery (same packet id, not acknowledged yet) keeps
        the key of its first delivery."""
        if message.qos > 0 and message.mid in self._key_of_mid:
            return self._key_of_mid[message.mid]
        key = self._next_key
        self._next_key += 1
        self._held[key] = _Held(message.mid if message.qos > 0 else None)
        if message.qos > 0:
            self._key_of_mid[message.mid] = key
        return key

    def _on_message(self, client: mqtt.Client, userdata: Any, message: mqtt.MQTTMessage) -> None:
        key = self._key_for(message)
        held = self._held[key]
        held.holds += 1  # until every sample is in a session
        self.report.messages += 1
        topic = "?"
        try:
            topic = message.topic
            batch = parse_message(
                topic, message.payload, self._wagon_level, max_bytes=self.config.max_payload_bytes
            )
        except PayloadError as error:
            self._reject(str(error))
        except UnicodeDecodeError:  # of the topic (parse_message judges the payload)
            self._reject(f"topic {message._topic!r} is not UTF-8")  # paho's raw topic bytes
        except Exception as error:  # a bug must not make a poison message block the session
            logger.exception("%s: message rejected (unexpected error)", topic)
            self._reject(f"{topic}: {type(error).__name__}: {error}")
        else:
            now_s = time.monotonic()
            for second, row in zip(batch.seconds, batch.rows, strict=True):
                placed = self._buffer.add(batch.wagon_id, second, row, key, now_s)
                if placed.new:
                    self.report.samples += 1
                else:
                    self.report.duplicates += 1
                if placed.attached:
                    held.holds += 1
                for session in placed.ended:
                    self._write(session)
            if logger.isEnabledFor(logging.DEBUG):
                logger.debug(
                    "%s: %d samples %s..%s (packet %d%s)",
                    topic,
                    len(batch.seconds),
                    utc_of(min(batch.seconds)).strftime(TIME_FORMAT),
                    utc_of(max(batch.seconds)).strftime(TIME_FORMAT),
                    message.mid,
                    ", again" if message.dup else "",
                )
        self._release(key)
        if (
            len(self._held) >= self.config.max_unacked
            or self._buffer.samples >= self.config.max_buffered_samples
        ):
            self._write_all("held messages or samples at their limit")

    def _reject(self, reason: str) -> None:
        self.report.rejected += 1
        logger.error("message rejected: %s", reason)

    def _release(self, key: int) -> None:
        """One hold of message ``key`` less; acknowledge it when none is left."""
        held = self._held[key]
        held.holds -= 1
        if held.holds > 0:
            return
        del self._held[key]
        if held.mid is None or self._key_of_mid.get(held.mid) != key:
            return
        del self._key_of_mid[held.mid]
        if self._online and self._client.ack(held.mid, 1) == MQTTErrorCode.MQTT_ERR_SUCCESS:
            self.report.acked += 1
        # offline: the broker sends it again, and the landing folder drops its samples

    # ------------------------------------------------------------------ writing

    def _write(self, session: Session) -> None:
        written = self.landing.write(session.wagon_id, session.rows)
        self.report.duplicates += written.duplicates
        self.report.conflicts += written.conflicts
        if written.path is not None:
            self.report.files += 1
            self.report.rows += written.rows
            logger.info(
                "wrote %s: %d samples%s",
                written.path,
                written.rows,
                f" ({written.duplicates} already landed)" if written.duplicates else "",
            )
        for key in session.keys:
            self._release(key)

    def _write_all(self, why: str) -> None:
        sessions = self._buffer.drain()
        if sessions:
            logger.debug("writing %d open sessions: %s", len(sessions), why)
        for session in sessions:
            self._write(session)

    def _tick(self, now_s: float) -> None:
        if now_s >= self._next_idle_check_s:  # not at every packet: it visits every session
            self._next_idle_check_s = now_s + min(1.0, self.config.idle_s / 4)
            for session in self._buffer.idle(now_s, self.config.idle_s):
                self._write(session)
        if now_s >= self._next_health_s:
            self._next_health_s = now_s + self.config.health_every_s
            logger.info(
                "health: %s, %s; %d samples in %d open sessions, %d messages unacknowledged",
                "online" if self._online else "offline",
                self.report.line(),
                self._buffer.samples,
                self._buffer.sessions,
                len(self._held),
            )

    # ------------------------------------------------------------------ the loop

    def run(self, stop: threading.Event) -> BridgeReport:
        """Run until ``stop`` is set; then write what is held, acknowledge it, disconnect."""
        connected = False  # a socket is open (the CONNACK may still be on its way)
        next_attempt_s = 0.0
        try:
            while not stop.is_set():
                now_s = time.monotonic()
                if not connected:
                    if now_s >= next_attempt_s:
                        try:
                            self._connect()
                            connected = True
                        except OSError as error:
                            next_attempt_s = self._retry_later(now_s, f"cannot connect: {error}")
                    else:
                        stop.wait(min(self.config.tick_s, next_attempt_s - now_s))
                else:
                    rc = self._client.loop(timeout=self.config.tick_s)
                    if rc != MQTTErrorCode.MQTT_ERR_SUCCESS:
                        connected = self._online = self.subscribed = False
                        next_attempt_s = self._retry_later(
                            time.monotonic(), f"connection lost: {_reason(rc)}"
                        )
                self._tick(time.monotonic())
            self._write_all("stopping")
        finally:
            if connected:
                self._disconnect()
        return self.report

    def _retry_later(self, now_s: float, why: str) -> float:
        wait_s = self._backoff_s
        self._backoff_s = min(2 * self._backoff_s, self.config.reconnect_max_s)
        logger.warning("broker %s: %s; trying again in %.1f s", self.config.address, why, wait_s)
        return now_s + wait_s

    def _disconnect(self) -> None:
        """Send what is queued (acknowledgements), then DISCONNECT; bounded in time."""
        self._stopping = True
        try:
            self._client.disconnect()
            deadline_s = time.monotonic() + _DISCONNECT_WAIT_S
            while self._online and time.monotonic() < deadline_s:
                if self._client.loop(timeout=0.1) != MQTTErrorCode.MQTT_ERR_SUCCESS:
                    break
        finally:
            self._online = False


def run_bridge(config: BridgeConfig, stop: threading.Event | None = None) -> BridgeReport:
    """``fleetbrake bridge mqtt``: take samples from the broker into the landing folder until
    ``stop`` is set (never, if None), then write what is held and return.

    Raises :class:`~fleetbrake.bridge.landing.LandingError` (the landing folder is missing or
    cannot be written: what was not written stays unacknowledged at the broker),
    :class:`~fleetbrake.bridge.landing.LandingBusyError` (another bridge with this client id
    writes there) and :class:`~fleetbrake.bridge.config.BridgeConfigError`.
    """
    stop = stop if stop is not None else threading.Event()
    with LandingFolder.of(config) as landing:
        bridge = MqttBridge(config, landing)
        logger.info("bridge from %s %s into %s", config.address, config.topic, config.landing)
        return bridge.run(stop)
