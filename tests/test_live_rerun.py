"""``fleetbrake watch --rerun ADDR``: each processed file's new timeline streamed to a live rerun
viewer over rerun's gRPC protocol, on the entity paths and blueprint of ``fleetbrake record``.

The viewer is a real rerun gRPC sink on 127.0.0.1: the ``rerun`` binary of the SDK, started by
the test with ``--save`` (it takes what SDKs send it over gRPC and writes it to an ``.rrd``
file), read back with ``rerun.chunk.RrdReader`` once the sink is stopped. The service runs
in this process (``watch_fleet`` on a thread, one worker), over a small generated fleet.
"""

from __future__ import annotations

import datetime as dt
import logging
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import polars as pl
import pytest
from rerun.chunk import RrdReader

from fleetbrake.app.watch.service import FileOutcome, WatchConfig, watch_fleet
from fleetbrake.fleet.logfile import log_relpath, write_log
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.viz.live import (
    APPLICATION_ID,
    LiveAddressError,
    recording_id,
    viewer_url,
)
from fleetgen import T0_UTC, make_session, write_registry

WAGONS = ["SGG-0001", "SGG-0002"]
BOUND_S = 180.0
"""The longest any wait of these tests may take (the first unit may build the reduced model)."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.fixture
def sink(tmp_path: Path) -> Iterator[dict[str, Any]]:
    """A rerun gRPC sink on 127.0.0.1 saving what it receives to ``sink.rrd``; ``stop()``
    ends it (SIGINT) so that the file is whole."""
    port = _free_port()
    out = tmp_path / "sink.rrd"
    rerun = Path(sys.executable).with_name("rerun")
    log = open(tmp_path / "sink.log", "wb")
    process = subprocess.Popen(
        [str(rerun), "--save", str(out), "--bind", "127.0.0.1", "--port", str(port)],
        stdout=log,
        stderr=subprocess.STDOUT,
        cwd=tmp_path,
    )

    def stop() -> None:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=30)

    deadline = time.monotonic() + 60
    while not _listening(port):
        assert process.poll() is None, (tmp_path / "sink.log").read_text()
        assert time.monotonic() < deadline, "the rerun sink did not start"
        time.sleep(0.1)
    try:
        yield {"url": f"rerun+http://127.0.0.1:{port}/proxy", "out": out, "stop": stop}
    finally:
        stop()
        log.close()


PLAN = ((WAGONS[0], 0), (WAGONS[0], 3), (WAGONS[1], 0))
"""The sessions of the fleet: two of the first wagon (3 h apart), one of the second."""


def _relpath(k: int) -> str:
    wagon, hour = PLAN[k]
    return log_relpath(wagon, T0_UTC + dt.timedelta(hours=hour), gzip=False).as_posix()


def _land_fleet(fleet: Path, sessions: range = range(len(PLAN))) -> list[tuple[str, str]]:
    """The sessions ``sessions`` of :data:`PLAN` in ``logs/``: their (path, wagon). The first
    has two minutes of out-of-range readings (a broken wire: a sensor-fault flag)."""
    write_registry(fleet, WAGONS)
    landed = []
    for k in sessions:
        wagon, hour = PLAN[k]
        start = T0_UTC + dt.timedelta(hours=hour)
        frame = make_session(np.random.default_rng(300 + k), start, n_events=4).frame
        if k == 0:
            broken = pl.int_range(pl.len()).is_between(600, 719)
            frame = frame.with_columns(
                block_temp_c=pl.when(broken).then(900.0).otherwise(pl.col("block_temp_c"))
            )
        write_log(fleet / _relpath(k), frame)
        landed.append((_relpath(k), wagon))
    return landed


def _watch(
    fleet: Path,
    db: Path,
    rerun: str,
    refinement: float,
    paths: set[str],
    after_first: Callable[[], None] | None = None,
) -> list[FileOutcome]:
    """``watch_fleet`` on a thread until every path in ``paths`` was processed, then stopped;
    ``after_first`` is called once the first file was processed (to land more)."""
    outcomes: list[FileOutcome] = []
    stop = threading.Event()
    config = WatchConfig(
        settle_s=0.5,
        tick_s=0.1,
        workers=1,
        rerun=rerun,
        simulation=SimulationConfig(refinement=refinement),
    )
    failure: list[BaseException] = []

    def service() -> None:
        try:
            watch_fleet(fleet, db, config, stop, on_file=outcomes.append)
        except BaseException as error:  # reported by the test
            failure.append(error)

    thread = threading.Thread(target=service)
    thread.start()
    deadline = time.monotonic() + BOUND_S
    try:
        while not paths <= {o.path for o in outcomes}:
            if after_first is not None and outcomes:
                after_first()
                after_first = None
            assert not failure, failure
            assert thread.is_alive() and time.monotonic() < deadline, "the unit did not finish"
            time.sleep(0.1)
    finally:
        stop.set()
        thread.join(timeout=BOUND_S)
    assert not thread.is_alive() and not failure, failure
    return outcomes


def _expected(db: Path, wagon: str) -> dict[str, int]:
    """What the warehouse holds of ``wagon`` in the time ranges of its files: values per entity
    path, as a live recording of each file logs them, and its flags and events."""
    con = duckdb.connect(str(db), read_only=True)
    try:
        spans = con.execute(
            "SELECT min(s.time_utc), max(s.time_utc) FROM samples s JOIN files f USING (file_id) "
            "WHERE f.wagon_id = ? GROUP BY f.path",
            [wagon],
        ).fetchall()
        ((revision,),) = con.execute(
            "SELECT model_revision FROM model_revisions WHERE is_current"
        ).fetchall()
        views = {r[0] for r in con.execute("SELECT view_name FROM duckdb_views()").fetchall()}
        counts: dict[str, int] = defaultdict(int)
        for a, b in spans:
            inside = [wagon, a, b]

            def count(query: str, *more: object, inside: list[object] = inside) -> int:
                return int(con.execute(query, [*inside, *more]).fetchall()[0][0])

            where = "wagon_id = ? AND time_utc BETWEEN ? AND ?"
            counts["/wagon/speed_kmh"] += count(
                f"SELECT count(speed_kmh) FROM samples WHERE {where}"
            )
            counts["/wagon/brake_pressure_bar"] += count(
                f"SELECT count(brake_pressure_bar) FROM samples WHERE {where}"
            )
            counts["/wagon/temperature/measured_sensor_c"] += count(
                f"SELECT count(block_temp_c) FROM samples WHERE {where}"
            )
            counts["/wagon/temperature/predicted_sensor_c"] += count(
                f"SELECT count(predicted_sensor_c) FROM v_predictions WHERE {where} "
                "AND model_revision = ?",
                revision,
            )
            if "v_contact_estimates" in views:  # every logged second's estimate (recomputed
                # where the warehouse holds the minute's row)
                counts["/wagon/temperature/estimated_contact_mean_c"] += count(
                    f"SELECT count(DISTINCT time_utc) FROM samples WHERE {where}"
                )
        counts["flags"] = int(
            con.execute("SELECT count(*) FROM v_flags WHERE wagon_id = ?", [wagon]).fetchall()[0][0]
        )
        counts["events"] = int(
            con.execute("SELECT count(*) FROM v_events WHERE wagon_id = ?", [wagon]).fetchall()[0][
                0
            ]
        )
        return counts
    finally:
        con.close()


def _streamed(out: Path) -> dict[str, dict[str, int]]:
    """Per recording id of the sink's file: temporal values per entity path, and the number
    of flags and events logged (their start text logs)."""
    reader = RrdReader(out)
    found: dict[str, dict[str, int]] = {}
    for store in reader.recordings():
        assert store.application_id == APPLICATION_ID
        counts: dict[str, int] = defaultdict(int)
        for chunk in reader.stream(store=store):
            if chunk.is_static:
                continue
            batch = chunk.to_record_batch()
            for name in ("Scalars:scalars", "TextLog:text"):
                if name in batch.schema.names:
                    column = batch.column(name)
                    counts[chunk.entity_path] += len(column) - column.null_count
                    if chunk.entity_path in ("/log/flags", "/log/events"):
                        kind = chunk.entity_path.removeprefix("/log/")
                        counts[kind] += sum(
                            1 for t in column.to_pylist() if t and " ends" not in t[0]
                        )
        found[str(store.recording_id)] = counts
    return found


def _view_names(out: Path) -> set[str]:
    reader = RrdReader(out)
    names: set[str] = set()
    for store in reader.blueprints():
        for chunk in reader.stream(store=store):
            batch = chunk.to_record_batch()
            if "ViewBlueprint:display_name" in batch.schema.names:
                for value in batch.column("ViewBlueprint:display_name").to_pylist():
                    names.update(value or [])
    return names


def test_each_processed_file_streams_its_wagon_timeline_to_the_viewer(
    tmp_path: Path,
    sink: dict[str, Any],
    monkeypatch: pytest.MonkeyPatch,
    rom_cache_dir: Path,
    rom_refinement: float,
) -> None:
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    fleet, db = tmp_path / "fleet", tmp_path / "fleet.duckdb"
    landed = _land_fleet(fleet)
    outcomes = _watch(fleet, db, sink["url"], rom_refinement, {p for p, _ in landed})
    assert sorted(o.path for o in outcomes) == sorted(p for p, _ in landed)
    assert all(o.status == "ingested" for o in outcomes)
    sink["stop"]()

    streamed = _streamed(sink["out"])
    assert set(streamed) == {str(recording_id(w)) for w in WAGONS}  # a recording per wagon
    for wagon in WAGONS:
        got, expected = streamed[str(recording_id(wagon))], _expected(db, wagon)
        assert expected["/wagon/speed_kmh"] > 0 and expected["events"] > 0
        # the virtual sensor's estimate (every logged second) and the unexplained power
        assert expected["/wagon/temperature/estimated_contact_mean_c"] > 0
        for path in ("unexplained_power/estimate_w", "unexplained_power/hi_w"):
            assert got[f"/wagon/{path}"] == expected["/wagon/temperature/estimated_contact_mean_c"]
        for path, n in expected.items():
            assert got[path] == n, (wagon, path, got[path], n)
        # measured and predicted side by side, and the open-loop contact prediction
        assert (
            got["/wagon/temperature/predicted_contact_mean_c"]
            == (expected["/wagon/temperature/predicted_sensor_c"])
        )
    assert sum(_expected(db, w)["flags"] for w in WAGONS) > 0, "no flags: the test shows less"
    names = _view_names(sink["out"])
    assert "Unexplained heat power W (estimate, 95 % band)" in names
    assert "Events, flags, faulty readings" in names


def test_a_viewer_that_is_not_there_does_not_stop_the_service(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    rom_cache_dir: Path,
    rom_refinement: float,
) -> None:
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    fleet, db = tmp_path / "fleet", tmp_path / "fleet.duckdb"
    landed = _land_fleet(fleet, sessions=range(1))
    later: list[tuple[str, str]] = []

    def failed() -> list[str]:
        return [
            r.getMessage()
            for r in caplog.records
            if r.name == "fleetbrake.viz.live" and "did not take" in r.getMessage()
        ]

    def land_after_the_first_failure() -> None:
        deadline = time.monotonic() + 60
        while not failed():
            assert time.monotonic() < deadline, "no warning for the viewer that is not there"
            time.sleep(0.1)
        later.extend(_land_fleet(fleet, sessions=range(1, 2)))

    dead = f"127.0.0.1:{_free_port()}"  # nothing listens there
    with caplog.at_level(logging.WARNING, logger="fleetbrake.viz.live"):
        outcomes = _watch(
            fleet,
            db,
            dead,
            rom_refinement,
            {_relpath(0), _relpath(1)},
            after_first=land_after_the_first_failure,
        )
    assert later, "the second file did not land"
    assert [(o.path, o.status) for o in outcomes] == [(p, "ingested") for p, _ in landed + later]
    warnings = failed()
    # each unit tried the viewer again, and said so
    assert len(warnings) == 2, warnings
    assert all("trying again at the next unit" in w for w in warnings)
    for (path, _), warning in zip(landed + later, warnings, strict=True):
        assert path in warning


def test_viewer_addresses() -> None:
    assert viewer_url("9876") == "rerun+http://127.0.0.1:9876/proxy"
    assert viewer_url("viewer.local:9877") == "rerun+http://viewer.local:9877/proxy"
    url = "rerun+https://viewer.example:443/proxy"
    assert viewer_url(url) == url
    for bad in ("http://h:1/proxy", "h", "rerun+http://h:1/other", "h:port"):
        with pytest.raises(LiveAddressError, match="--rerun"):
            viewer_url(bad)
    assert recording_id("SGG-0001") == recording_id("SGG-0001") != recording_id("SGG-0002")


def test_watch_refuses_an_address_that_is_not_a_viewer(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from fleetbrake.cli.main import app

    fleet = tmp_path / "fleet"
    write_registry(fleet, WAGONS)
    result = CliRunner().invoke(
        app, ["watch", str(fleet), "--db", str(tmp_path / "f.duckdb"), "--rerun", "http://h:1/x"]
    )
    assert result.exit_code == 2, result.output
    assert "--rerun 'http://h:1/x'" in result.output
    assert not (tmp_path / "f.duckdb").exists()
