"""``fleetbrake bridge mqtt`` against a real broker: Debian's mosquitto, started by the fixture
on a free port of 127.0.0.1 with its own configuration and persistence, stopped afterwards.

What is checked: samples of two wagons land as log files that read back exactly and ingest
exactly; bad messages are logged with their topic, counted, acknowledged, and never stop the
bridge; samples delivered again (a publisher that sends twice, acknowledgements lost before a
restart) land once; a broker restarted mid-stream is reconnected to and the session resumed;
the bridge killed with SIGKILL mid-stream and started again loses nothing and duplicates
nothing in the warehouse, and SIGTERM writes what it holds and exits 0.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import getpass
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import polars as pl
import pytest
import typer
from paho.mqtt.enums import CallbackAPIVersion
from typer.testing import CliRunner

from fleetbrake.bridge.config import BridgeConfig, BridgeConfigError, MqttProtocol
from fleetbrake.bridge.landing import LandingBusyError, LandingFolder, read_seconds
from fleetbrake.bridge.mqtt import MqttBridge
from fleetbrake.bridge.sessions import SessionBuffer
from fleetbrake.cli.bridge import register
from fleetbrake.errors import EXIT_LOCKED, EXIT_USAGE
from fleetbrake.fleet.logfile import COLUMNS, TIME_FORMAT, gzip_bytes, log_name, to_csv_bytes
from fleetbrake.ingest.files import ingest_fleet
from fleetbrake.ingest.reading import read_log
from fleetbrake.warehouse.connection import open_warehouse
from fleetgen import simple_session, write_registry

T0_UTC = dt.datetime(2024, 3, 1, 6, 0, 0)
WAIT_S = 20.0
"""Longest wait for anything to happen (a bound, not an expectation)."""


# --------------------------------------------------------------------------------------------
# Helpers


def wait_until(condition: Callable[[], bool], what: str, timeout_s: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting: {what}")
        time.sleep(0.05)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Broker:
    """mosquitto on 127.0.0.1 with its own configuration and persistence, as
    docs/operations.md asks of a broker (sessions kept, everything queued while away)."""

    def __init__(self, exe: str, home: Path) -> None:
        self.exe = exe
        self.home = home
        self.port = free_port()
        self.conf = home / "mosquitto.conf"
        self.conf.write_text(
            f"listener {self.port} 127.0.0.1\n"
            "allow_anonymous true\n"
            "persistence true\n"
            f"persistence_location {home}/\n"
            "max_queued_messages 0\n"
            # as root, mosquitto would become the user mosquitto, who cannot save in home
            f"user {getpass.getuser()}\n",
            encoding="utf-8",
        )
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def start(self) -> None:
        with open(self.home / "mosquitto.log", "ab") as log:
            self.process = subprocess.Popen(
                [self.exe, "-c", str(self.conf)], stdout=log, stderr=subprocess.STDOUT
            )
        process = self.process

        def listening() -> bool:
            assert process.poll() is None, (self.home / "mosquitto.log").read_text()
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.port)):
                return True
            return False

        wait_until(listening, "mosquitto listening")

    def stop(self) -> None:
        """SIGTERM: mosquitto saves its sessions and queues, and exits."""
        if self.process is None:
            return
        self.process.terminate()
        try:
            self.process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(timeout=5)
        self.process = None


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    exe = shutil.which("mosquitto") or next(
        (p for p in ("/usr/sbin/mosquitto", "/usr/bin/mosquitto") if os.access(p, os.X_OK)), None
    )
    if exe is None:
        pytest.fail("mosquitto is not installed: apt-get install mosquitto (make setup does)")
    home = tmp_path / "mosquitto"
    home.mkdir()
    broker = Broker(exe, home)
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()


class Publisher:
    """A QoS 1 publisher (MQTT 5) that waits for the broker's acknowledgement of each message."""

    def __init__(self, broker: Broker) -> None:
        self.client = mqtt.Client(
            CallbackAPIVersion.VERSION2, client_id="test-publisher", protocol=mqtt.MQTTv5
        )
        self.client.connect("127.0.0.1", broker.port)
        self.client.loop_start()

    def send(self, messages: list[tuple[str, bytes]], pace_s: float = 0.0) -> None:
        infos = []
        for topic, payload in messages:
            infos.append(self.client.publish(topic, payload, qos=1))
            if pace_s:
                time.sleep(pace_s)
        for info in infos:
            info.wait_for_publish(timeout=WAIT_S)
            assert info.is_published()

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


@pytest.fixture
def publisher(broker: Broker) -> Iterator[Publisher]:
    pub = Publisher(broker)
    yield pub
    pub.close()


def sample_dicts(frame: pl.DataFrame) -> list[dict[str, Any]]:
    """The frame's rows as the payload's samples (time as text, numbers as numbers)."""
    return frame.with_columns(pl.col("time_utc").dt.strftime(TIME_FORMAT)).to_dicts()


def batches(
    wagon_id: str, frame: pl.DataFrame, size: int, *, absent: tuple[str, ...] = ()
) -> list[tuple[str, bytes]]:
    """One message per ``size`` samples (one sample: the object alone, not an array), without
    the keys ``absent``."""
    samples = [{k: v for k, v in s.items() if k not in absent} for s in sample_dicts(frame)]
    topic = f"fleet/{wagon_id}/samples"
    if size == 1:
        return [(topic, json.dumps(s).encode()) for s in samples]
    return [
        (topic, json.dumps(samples[i : i + size]).encode()) for i in range(0, len(samples), size)
    ]


def landed(fleet: Path) -> list[Path]:
    return sorted((fleet / "logs").glob("*/*.csv*"))


def landed_seconds(fleet: Path) -> int:
    """Rows in the landed files (each file read as the bridge reads them)."""
    return sum(len(read_seconds(p)) for p in landed(fleet))


def config_for(broker: Broker, fleet: Path, **changes: Any) -> BridgeConfig:
    base = BridgeConfig(
        broker=broker.url,
        landing=fleet,
        gap_s=30,
        idle_s=0.5,
        tick_s=0.05,
        reconnect_min_s=0.1,
        reconnect_max_s=0.5,
        health_every_s=1.0,
    )
    return replace(base, **changes)


@contextlib.contextmanager
def bridge_thread(config: BridgeConfig) -> Iterator[MqttBridge]:
    """A bridge running in a thread (its report can be watched live); stopped on leaving."""
    stop = threading.Event()
    errors: list[BaseException] = []
    with LandingFolder.of(config) as landing:
        bridge = MqttBridge(config, landing)

        def target() -> None:
            try:
                bridge.run(stop)
            except BaseException as error:  # raised by the test below
                errors.append(error)

        thread = threading.Thread(target=target, name="bridge")
        thread.start()
        try:
            wait_until(lambda: bridge.subscribed or bool(errors), "the bridge subscribed")
            yield bridge
        finally:
            stop.set()
            thread.join(timeout=WAIT_S)
            assert not thread.is_alive(), "bridge did not stop"
    if errors:
        raise errors[0]


def warehouse_counts(fleet: Path, db: Path) -> tuple[int, int, dict[str, int], int]:
    """Ingest the landing folder into a fresh warehouse: (samples, distinct (wagon, time),
    samples per wagon, files quarantined)."""
    with open_warehouse(db) as wh:
        report = ingest_fleet(fleet, wh, progress=False)
        total, distinct = wh.con.execute(
            "SELECT count(*), count(DISTINCT (wagon_id, time_utc)) FROM samples"
        ).fetchone()
        per_wagon = dict(
            wh.con.execute("SELECT wagon_id, count(*) FROM samples GROUP BY ALL").fetchall()
        )
    return total, distinct, per_wagon, len(report.quarantined)


# --------------------------------------------------------------------------------------------
# Round trip


@pytest.mark.parametrize("gzip", [False, True])
def test_round_trip_two_wagons(
    broker: Broker,
    publisher: Publisher,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    gzip: bool,
) -> None:
    """Batches of one wagon (with a gap that ends its session) and single samples of another
    (without the optional column) land as the log files a unit would write: names of their
    first samples, exact bytes, read back exactly, ingested exactly; every message
    acknowledged."""
    fleet = tmp_path / "fleet"
    write_registry(fleet, ["SGG-0001", "SGG-0002"])
    a = simple_session(T0_UTC, 240, seed=1)
    a = pl.concat([a[:100], a[200:]])  # 100 s without samples: more than gap_s = 30
    b = simple_session(T0_UTC + dt.timedelta(hours=1), 90, seed=2).with_columns(
        pl.lit(None, dtype=pl.Float64).alias("ambient_temp_c")  # a unit without air sensor
    )
    expected = {
        log_name("SGG-0001", T0_UTC, gzip=gzip): a[:100],
        log_name("SGG-0001", T0_UTC + dt.timedelta(seconds=200), gzip=gzip): a[100:],
        log_name("SGG-0002", T0_UTC + dt.timedelta(hours=1), gzip=gzip): b,
    }
    caplog.set_level(logging.INFO, logger="fleetbrake.bridge")
    messages = batches("SGG-0001", a, 20) + batches("SGG-0002", b, 1, absent=("ambient_temp_c",))
    with bridge_thread(config_for(broker, fleet, gzip=gzip)) as bridge:
        publisher.send(messages)
        wait_until(lambda: bridge.report.acked == len(messages), "every message acknowledged")
    report = bridge.report

    assert [p.name for p in landed(fleet)] == sorted(expected)
    for path in landed(fleet):
        frame = expected[path.name]
        csv = to_csv_bytes(frame.select(COLUMNS))
        assert path.read_bytes() == (gzip_bytes(csv) if gzip else csv)
        parsed = read_log(path.read_bytes(), path.name, frame["time_utc"][0])
        assert parsed.repairs.text() is None
        assert parsed.frame.select(COLUMNS).equals(frame.select(COLUMNS))
    assert not list((fleet / "logs").glob("*/.*")), "temporary files left behind"

    assert report.messages == len(messages) and report.rejected == 0
    assert report.acked == len(messages)
    assert (report.files, report.rows, report.duplicates) == (3, a.height + b.height, 0)
    assert any("wrote" in r.getMessage() for r in caplog.records)

    total, distinct, per_wagon, quarantined = warehouse_counts(fleet, tmp_path / "w.duckdb")
    assert (total, distinct, quarantined) == (a.height + b.height, a.height + b.height, 0)
    assert per_wagon == {"SGG-0001": a.height, "SGG-0002": b.height}


# --------------------------------------------------------------------------------------------
# Bad messages


def test_bad_messages_are_logged_counted_acknowledged(
    broker: Broker, publisher: Publisher, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    good = sample_dicts(simple_session(T0_UTC, 3, seed=3))
    topic = "fleet/SGG-0001/samples"

    def without(key: str) -> bytes:
        return json.dumps({k: v for k, v in good[0].items() if k != key}).encode()

    def changed(**values: Any) -> bytes:
        return json.dumps({**good[0], **values}).encode()

    bad = {
        "not JSON": (topic, b"{time_utc: 1"),
        "not UTF-8": (topic, b"\xff\xfe\x00"),
        "NaN": (topic, b'{"time_utc": "2024-03-01T06:00:00Z", "speed_kmh": NaN}'),
        "empty array": (topic, b"[]"),
        "missing required column brake_pressure_bar": (topic, without("brake_pressure_bar")),
        "not YYYY-MM-DDTHH:MM:SSZ": (topic, changed(time_utc="2024-03-01 06:00:00")),
        "not a valid time": (topic, changed(time_utc="2024-02-30T06:00:00Z")),
        "not a number or null": (topic, changed(speed_kmh="61.2")),
        "not the topic's wagon": (topic, changed(wagon_id="SGG-0002")),
        "is not a wagon id": ("fleet/SGG.0001/samples", json.dumps(good[0]).encode()),
        "sample 1": (topic, json.dumps([good[0], 7]).encode()),
    }
    caplog.set_level(logging.ERROR, logger="fleetbrake.bridge")
    config = config_for(broker, fleet)
    with bridge_thread(config) as bridge:
        publisher.send([*bad.values(), (topic, json.dumps(good).encode())])
        wait_until(lambda: bridge.report.acked == len(bad) + 1, "every message acknowledged")
    report = bridge.report
    assert report.rejected == len(bad)
    assert report.acked == len(bad) + 1
    assert report.files == 1 and report.rows == 3
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == len(bad)
    for reason, (bad_topic, _) in bad.items():
        assert any(reason in e and bad_topic in e for e in errors), (reason, errors)

    # acknowledged, so not sent again: a restarted bridge gets only what comes after them
    with bridge_thread(config) as bridge:
        publisher.send([(topic, json.dumps(good[:1]).encode())])
        wait_until(lambda: bridge.report.acked == 1, "the message after them acknowledged")
    report = bridge.report
    assert (report.messages, report.rejected, report.files, report.duplicates) == (1, 0, 0, 1)


# --------------------------------------------------------------------------------------------
# Delivered more than once


def test_samples_delivered_again_land_once(
    broker: Broker, publisher: Publisher, tmp_path: Path
) -> None:
    """A publisher that sends a batch again after it landed, and a batch overlapping it:
    only the seconds not landed yet make a new file (named by its first new second)."""
    fleet = tmp_path / "fleet"
    write_registry(fleet, ["SGG-0001"])
    frame = simple_session(T0_UTC, 90, seed=4)
    with bridge_thread(config_for(broker, fleet)) as bridge:
        publisher.send(batches("SGG-0001", frame[:60], 60))
        wait_until(lambda: bridge.report.acked == 1, "first batch acknowledged")
        publisher.send(batches("SGG-0001", frame[:60], 60) + batches("SGG-0001", frame[30:], 60))
        wait_until(lambda: bridge.report.acked == 3, "the others acknowledged")
    report = bridge.report
    assert [p.name for p in landed(fleet)] == [
        log_name("SGG-0001", T0_UTC, gzip=False),
        log_name("SGG-0001", T0_UTC + dt.timedelta(seconds=60), gzip=False),
    ]
    assert report.duplicates == 60 + 30 and report.rows == 90
    total, distinct, _, _ = warehouse_counts(fleet, tmp_path / "w.duckdb")
    assert total == distinct == 90


@pytest.mark.parametrize("protocol", list(MqttProtocol))
def test_acknowledgements_lost_then_restart_lands_once(
    broker: Broker,
    publisher: Publisher,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    protocol: MqttProtocol,
) -> None:
    """Files written but their acknowledgements lost (as when the bridge dies between the two):
    the broker sends those messages again to the restarted bridge (same client id, persistent
    session, in either protocol); their samples are in the landing folder already and are
    dropped."""
    fleet = tmp_path / "fleet"
    write_registry(fleet, ["SGG-0001"])
    frame = simple_session(T0_UTC, 200, seed=5)
    config = config_for(broker, fleet, max_file_s=50, protocol=protocol)
    real_ack = mqtt.Client.ack
    dropped: list[int] = []

    def lossy_ack(self: mqtt.Client, mid: int, qos: int) -> Any:
        if len(dropped) < 2:  # the first two acknowledgements never reach the broker
            dropped.append(mid)
            return mqtt.MQTTErrorCode.MQTT_ERR_SUCCESS
        return real_ack(self, mid, qos)

    with monkeypatch.context() as patch:
        patch.setattr(mqtt.Client, "ack", lossy_ack)
        with bridge_thread(config) as bridge:
            publisher.send(batches("SGG-0001", frame, 10))
            wait_until(lambda: bridge.report.acked == 20, "every message 'acknowledged'")
    assert len(dropped) == 2 and bridge.report.files == 4
    before = {p.name: p.read_bytes() for p in landed(fleet)}

    with bridge_thread(config) as bridge:
        wait_until(lambda: bridge.report.acked == 2, "the two sent again acknowledged")
    report = bridge.report
    assert (report.messages, report.files, report.duplicates) == (2, 0, 20)
    assert {p.name: p.read_bytes() for p in landed(fleet)} == before
    total, distinct, _, _ = warehouse_counts(fleet, tmp_path / "w.duckdb")
    assert total == distinct == 200


def test_broker_restart_mid_stream_reconnects_and_resumes(
    broker: Broker, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The broker goes away while the bridge holds unacknowledged messages, and comes back
    (its sessions persisted): the bridge reconnects (after waits that double), resumes its
    session, gets what was not acknowledged again (the acknowledgements on their way when the
    broker went included), and lands every sample once."""
    fleet = tmp_path / "fleet"
    write_registry(fleet, ["SGG-0001"])
    frame = simple_session(T0_UTC, 300, seed=6)
    messages = batches("SGG-0001", frame, 10)
    last = json.loads(messages[-1][1])
    caplog.set_level(logging.DEBUG, logger="fleetbrake.bridge")
    with bridge_thread(config_for(broker, fleet, max_file_s=100, idle_s=30)) as bridge:
        publisher = Publisher(broker)
        publisher.send(messages[:15])
        publisher.close()
        wait_until(lambda: bridge.report.files == 1, "the first file landed")
        broker.stop()  # five messages held unacknowledged in an open session
        wait_until(lambda: not bridge.subscribed, "the bridge saw the broker go")
        broker.start()
        wait_until(lambda: bridge.subscribed, "the bridge reconnected")
        publisher = Publisher(broker)
        publisher.send(messages[15:])
        publisher.close()
        mark = f"{last[0]['time_utc']}..{last[-1]['time_utc']}"
        wait_until(lambda: any(mark in r.getMessage() for r in caplog.records), "last taken")
    report = bridge.report  # the last session written when stopping
    assert report.connections == 2 and report.rows == 300
    assert any("session resumed" in r.getMessage() for r in caplog.records)
    assert any(", again)" in r.getMessage() for r in caplog.records)
    assert report.acked >= len(messages)
    assert landed_seconds(fleet) == 300
    total, distinct, _, _ = warehouse_counts(fleet, tmp_path / "w.duckdb")
    assert total == distinct == 300


# --------------------------------------------------------------------------------------------
# Killed mid-stream


BRIDGE_SCRIPT = """
import logging, sys
import typer
from fleetbrake.cli.bridge import register
logging.basicConfig(level=logging.DEBUG, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
logging.getLogger("paho").setLevel(logging.WARNING)
app = typer.Typer()
@app.callback()
def main() -> None:
    pass
register(app)
app(prog_name="fleetbrake")
"""
"""``fleetbrake -vv bridge mqtt ...`` in a process of its own (the command's function, its
signal handling and its exit code), whether or not the main command line registers it yet."""


def start_bridge(broker: Broker, fleet: Path, log: Path, *options: str) -> subprocess.Popen[bytes]:
    with open(log, "wb") as stderr:
        return subprocess.Popen(
            [
                *(sys.executable, "-c", BRIDGE_SCRIPT, "bridge", "mqtt", "--broker", broker.url),
                *("--landing", str(fleet), "--gap", "30", *options),
            ],
            stdout=subprocess.PIPE,
            stderr=stderr,
        )


def test_killed_mid_stream_loses_nothing_and_duplicates_nothing(
    broker: Broker, publisher: Publisher, tmp_path: Path
) -> None:
    """The bridge (a process) is killed with SIGKILL while messages flow and sessions are
    open; the stream goes on while it is down; a new bridge with the same client id gets what
    was not acknowledged, then SIGTERM: it writes what it holds and exits 0. Every published
    sample is in the warehouse exactly once."""
    fleet = tmp_path / "fleet"
    wagons = ["SGG-0001", "SGG-0002"]
    write_registry(fleet, wagons)
    frames = {w: simple_session(T0_UTC, 400, seed=10 + i) for i, w in enumerate(wagons)}
    streams = {w: batches(w, frames[w], 5) for w in wagons}  # 80 messages per wagon
    interleaved = [m for pair in zip(*streams.values(), strict=True) for m in pair]
    first, second = interleaved[:100], interleaved[100:]

    # files every 40 s of samples, sessions otherwise held (idle 60 s): at the kill, some
    # samples have landed and been acknowledged, others are held unacknowledged
    log = tmp_path / "bridge-1.log"
    one = start_bridge(broker, fleet, log, "--max-file", "40", "--idle", "60")
    wait_until(lambda: "subscribed to" in log.read_text(), "the first bridge subscribed")
    killed = threading.Event()
    sender = threading.Thread(
        target=lambda: (
            publisher.send(first, pace_s=0.01),
            killed.wait(WAIT_S),
            publisher.send(second),
        )
    )
    try:
        sender.start()
        wait_until(lambda: len(landed(fleet)) >= 4, "first files landed")
        one.send_signal(signal.SIGKILL)
        assert one.wait(timeout=WAIT_S) == -signal.SIGKILL
    finally:
        if one.poll() is None:
            one.kill()
            one.wait()
        killed.set()
        sender.join(timeout=WAIT_S)
    assert not sender.is_alive()
    assert landed_seconds(fleet) < 800, "killed after everything landed: not mid-stream"

    log = tmp_path / "bridge-2.log"
    two = start_bridge(broker, fleet, log, "--max-file", "40", "--idle", "60", "--json")
    try:
        # the last message of each wagon was published while no bridge ran: once the new one
        # has taken it, it has taken everything before it
        lasts = [json.loads(streams[w][-1][1]) for w in wagons]
        marks = [
            f"fleet/{w}/samples: 5 samples {last[0]['time_utc']}..{last[-1]['time_utc']}"
            for w, last in zip(wagons, lasts, strict=True)
        ]
        wait_until(lambda: all(m in log.read_text() for m in marks), "the last messages taken")
        assert landed_seconds(fleet) < 800, "the last sessions are written only when stopping"
        two.send_signal(signal.SIGTERM)
        out, _ = two.communicate(timeout=WAIT_S)
    finally:
        if two.poll() is None:
            two.kill()
            two.wait()
    assert two.returncode == 0, log.read_text()[-2000:]
    summary = json.loads(out.decode().splitlines()[-1])
    assert summary["rejected"] == 0 and summary["acked"] > 0

    total, distinct, per_wagon, quarantined = warehouse_counts(fleet, tmp_path / "w.duckdb")
    assert quarantined == 0
    assert per_wagon == {w: 400 for w in wagons}
    assert total == distinct == 800
    with open_warehouse(tmp_path / "w.duckdb", read_only=True) as wh:
        for w in wagons:
            stored = wh.con.execute(
                "SELECT time_utc, speed_kmh, block_temp_c FROM samples WHERE wagon_id = $w "
                "ORDER BY time_utc",
                {"w": w},
            ).fetchall()
            assert stored == frames[w].select("time_utc", "speed_kmh", "block_temp_c").rows()


# --------------------------------------------------------------------------------------------
# Pieces without a broker


def test_sessions_end_on_gap_span_and_idle() -> None:
    buffer = SessionBuffer(gap_s=30, max_file_s=100)
    row = (1.0,) * 8
    for t in range(0, 50):
        assert buffer.add("W", t, row, key=t, now_s=0.0).ended == []
    placed = buffer.add("W", 49 + 31, row, key=99, now_s=1.0)  # a gap of 31 s
    assert [(s.first_s, s.last_s, len(s.rows)) for s in placed.ended] == [(0, 49, 50)]
    assert buffer.add("W", 80, row, key=100, now_s=1.0).new is False  # held already
    for t in range(81, 180):
        assert buffer.add("W", t, row, key=t, now_s=2.0).ended == []
    ended = buffer.add("W", 180, row, key=180, now_s=2.0).ended
    assert [(s.first_s, s.last_s) for s in ended] == [(80, 179)]  # a span of 100 s reached
    late = buffer.add("W", 10, row, key=200, now_s=3.0)  # older than the open session
    assert late.new and late.ended == [] and buffer.sessions == 2
    assert [(s.first_s, s.last_s) for s in buffer.idle(now_s=3.5, idle_s=1.0)] == [(180, 180)]
    assert [(s.first_s, s.last_s) for s in buffer.drain()] == [(10, 10)]
    assert buffer.samples == 0 and buffer.sessions == 0


def test_landing_drops_seconds_already_landed_and_is_locked(tmp_path: Path) -> None:
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    rows = {1_700_000_000 + i: (float(i),) * 8 for i in range(10)}
    with LandingFolder(fleet, "test") as landing:
        first = landing.write("W-1", dict(list(rows.items())[:6]))
        again = landing.write("W-1", rows)
        nothing = landing.write("W-1", dict(list(rows.items())[2:4]))
        with pytest.raises(LandingBusyError) as busy:
            LandingFolder(fleet, "test").open()
        assert busy.value.exit_code == EXIT_LOCKED and "test" in str(busy.value)
    assert (first.rows, first.duplicates) == (6, 0)
    assert (again.rows, again.duplicates) == (4, 6)
    assert again.path is not None and again.path.name == "W-1_20231114T221326Z.csv"
    assert (nothing.path, nothing.duplicates) == (None, 2)
    with LandingFolder(fleet, "test") as landing:  # a new process: reads the files landed
        assert landing.write("W-1", rows).duplicates == 10


def test_landing_never_overwrites_a_file_it_did_not_write(tmp_path: Path) -> None:
    """A file by the name a session would take that does not hold its first sample (garbage
    from elsewhere) is left alone: that sample is dropped, counted and logged. A temporary
    file that a killed bridge of this client id left is removed."""
    wagon_dir = tmp_path / "logs" / "W-1"
    wagon_dir.mkdir(parents=True)
    foreign = wagon_dir / "W-1_20231114T221320Z.csv"
    foreign.write_bytes(b"\x00garbage")
    stale = wagon_dir / ".W-1_20231114T221000Z.csv.test.tmp"
    stale.write_bytes(b"time_utc,spe")
    rows = {1_700_000_000 + i: (float(i),) * 8 for i in range(5)}  # 22:13:20 .. 22:13:24
    with LandingFolder(tmp_path, "test") as landing:
        written = landing.write("W-1", rows)
    assert (written.rows, written.conflicts, written.duplicates) == (4, 1, 0)
    assert written.path is not None and written.path.name == "W-1_20231114T221321Z.csv"
    assert foreign.read_bytes() == b"\x00garbage" and not stale.exists()


@pytest.mark.parametrize(
    ("changes", "named"),
    [
        ({"broker": "http://host"}, "--broker"),
        ({"broker": "mqtt://host:port"}, "--broker"),
        ({"topic": "fleet/samples"}, "--wagon-level"),
        ({"topic": "fleet/a+/samples"}, "--topic"),
        ({"topic": "fleet/#/samples"}, "--topic"),
        ({"client_id": "a b"}, "--client-id"),
        ({"max_unacked": 70_000}, "--max-unacked"),
        ({"idle_s": 0.0}, "idle_s"),
        ({"password_file": Path("pw")}, "user name"),
    ],
)
def test_bad_settings_are_usage_errors(changes: dict[str, Any], named: str) -> None:
    with pytest.raises(BridgeConfigError) as error:
        BridgeConfig(**{"broker": "mqtt://127.0.0.1", "landing": Path("."), **changes})
    assert error.value.exit_code == EXIT_USAGE and named in str(error.value)


def test_command_maps_errors_to_exit_codes(tmp_path: Path) -> None:
    from fleetbrake.cli.group import FleetbrakeGroup

    app = typer.Typer(cls=FleetbrakeGroup)

    @app.callback()
    def main() -> None:
        pass

    register(app)
    runner = CliRunner()
    bad = runner.invoke(app, ["bridge", "mqtt", "--broker", "nonsense", "--landing", "."])
    assert bad.exit_code == EXIT_USAGE and "--broker" in bad.output
    missing = runner.invoke(
        app, ["bridge", "mqtt", "--broker", "mqtt://127.0.0.1:1", "--landing", str(tmp_path / "x")]
    )
    assert missing.exit_code == 1 and "no such landing folder" in missing.output
