"""`fleetbrake record`: rerun recordings of a wagon's timeline and of one event, read back."""

from __future__ import annotations

import datetime as dt
from collections import defaultdict
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader
from typer.testing import CliRunner

from fleetbrake.cli.main import app
from fleetbrake.viz.block import FIELD_EVERY_S
from fleetbrake.viz.data import RecordError
from fleetbrake.viz.entities import TIMELINE
from fleetbrake.viz.record import record
from fleetbrake.warehouse.connection import open_warehouse

WAGON = "TW-0001"
BARE_WAGON = "TW-0002"  # samples, no events, no predictions
T0 = dt.datetime(2024, 3, 1, 10, 0, 0)
FIRST_TRIP_S = 600  # samples 10:00:00 .. 10:09:59
T1 = dt.datetime(2024, 3, 1, 12, 0, 0)
SECOND_TRIP_S = 100  # samples 12:00:00 .. 12:01:39 (a gap of ~2 h before)
FAULTY_S = range(400, 405)  # out-of-range readings (a broken wire) in the first trip
MISSING_S = range(450, 453)  # no reading at all
E1 = f"{WAGON}-20240301T100140"  # stop: 10:01:40 .. 10:04:10
E2 = f"{WAGON}-20240301T120020"  # slowdown: 12:00:20 .. 12:00:50
E1_START, E1_END = T0 + dt.timedelta(seconds=100), T0 + dt.timedelta(seconds=250)
E2_START, E2_END = T1 + dt.timedelta(seconds=20), T1 + dt.timedelta(seconds=50)


def _trip(start: dt.datetime, n: int, brake: tuple[int, int], file_id: int) -> pl.DataFrame:
    s = np.arange(n, dtype=float)
    a, b = brake
    braking = (s >= a) & (s < b)
    speed = np.where(s < a, 80.0, np.where(braking, 80.0 * (b - s) / (b - a), 0.0))
    pressure = np.where(braking, 2.5, 0.0)
    temp = 20.0 + 60.0 * np.clip((s - a) / 300.0, 0.0, 1.0) * np.exp(-np.clip(s - b, 0, None) / 900)
    return pl.DataFrame(
        {
            "wagon_id": WAGON,
            "file_id": file_id,
            "time_utc": [start + dt.timedelta(seconds=int(k)) for k in s],
            "speed_kmh": speed,
            "distance_m": np.cumsum(speed / 3.6),
            "elevation_m": 100.0,
            "lat_deg": 50.0,
            "lon_deg": 8.0,
            "brake_pressure_bar": pressure,
            "block_temp_c": temp,
            "block_temp_raw_c": pl.Series([None] * n, dtype=pl.Float64),
            "block_temp_fault": False,
            "ambient_temp_c": 10.0,
        }
    )


def _predictions(samples: pl.DataFrame, event_id: str, start: dt.datetime, n: int) -> pl.DataFrame:
    window = samples.filter(pl.col("time_utc") >= start).head(n)
    s = np.arange(window.height, dtype=float)
    heating = s < 150 if event_id == E1 else s < 30
    return pl.DataFrame(
        {
            "event_id": event_id,
            "wagon_id": WAGON,
            "time_utc": window["time_utc"],
            "model_revision": "declared",
            "phase": np.where(heating, "heating", "cooling"),
            "measured_sensor_c": window["block_temp_c"],
            "predicted_sensor_c": window["block_temp_c"].fill_null(40.0) + 2.0,
            "predicted_contact_mean_c": window["block_temp_c"].fill_null(40.0) + 80.0,
            "predicted_contact_max_c": window["block_temp_c"].fill_null(40.0) + 120.0,
            "speed_kmh": window["speed_kmh"],
            "brake_pressure_bar": window["brake_pressure_bar"],
            "ambient_c": 10.0,
            "flux_w_m2": np.where(heating, 6.0e4, 0.0),
        }
    )


DRAG_S = range(300, 400)  # the first trip: an unexplained 500 W (a dragging brake) in the estimates


def _estimates(samples: pl.DataFrame) -> pl.DataFrame:
    """``v_contact_estimates`` rows (interface v3, per second) for every logged second of ``samples``: the
    contact mean 70 K over the reading with a +-5 K band, the unexplained power 500 W during
    :data:`DRAG_S` of the first trip (else 0) with a +-50 W band."""
    n = samples.height
    temp = samples["block_temp_c"].fill_null(40.0).to_numpy()
    k = np.arange(n)
    power = np.where((k >= DRAG_S.start) & (k < DRAG_S.stop), 500.0, 0.0)
    return pl.DataFrame(
        {
            "wagon_id": samples["wagon_id"],
            "time_utc": samples["time_utc"],
            "model_revision": "declared",
            "contact_mean_c": temp + 70.0,
            "contact_mean_lo_c": temp + 65.0,
            "contact_mean_hi_c": temp + 75.0,
            "contact_max_c": temp + 110.0,
            "contact_max_hi_c": temp + 118.0,
            "smoothed_contact_mean_c": temp + 70.0,
            "smoothed_contact_mean_lo_c": temp + 66.0,
            "smoothed_contact_mean_hi_c": temp + 74.0,
            "unexplained_power_w": power,
            "unexplained_power_lo_w": power - 50.0,
            "unexplained_power_hi_w": power + 50.0,
            "innovation_k": 0.1,
            "resolution_s": 1,
        },
        schema_overrides={"resolution_s": pl.Int32()},
    )


@pytest.fixture(scope="module")
def fleet_db(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """The warehouse of :func:`build_fleet_db`."""
    return build_fleet_db(tmp_path_factory.mktemp("record") / "fleet.duckdb")


def build_fleet_db(db: Path) -> dict[str, object]:
    """A small warehouse at ``db``: two trips of one wagon (700 samples, 5 faulty and 3
    missing readings), two events with predictions of revision `declared`, contact estimates
    at every logged second, two flags; and a wagon with samples only."""
    s1 = _trip(T0, FIRST_TRIP_S, (100, 250), 1)
    faulty = pl.Series("k", np.arange(FIRST_TRIP_S)).is_in(list(FAULTY_S))
    missing = pl.Series("k", np.arange(FIRST_TRIP_S)).is_in(list(MISSING_S))
    s1 = s1.with_columns(
        block_temp_c=pl.when(faulty | missing).then(None).otherwise(pl.col("block_temp_c")),
        block_temp_raw_c=pl.when(faulty).then(850.0).otherwise(None),
        block_temp_fault=faulty,
    )
    s2 = _trip(T1, SECOND_TRIP_S, (20, 50), 2)
    bare = _trip(T0, 50, (10, 20), 3).with_columns(wagon_id=pl.lit(BARE_WAGON))
    samples = pl.concat([s1, s2, bare])
    # Predictions: from activation until the end of the trip (the next event is later).
    p1 = _predictions(s1, E1, E1_START, FIRST_TRIP_S - 100)
    p2 = _predictions(s2, E2, E2_START, SECOND_TRIP_S - 20)
    predictions = pl.concat([p1, p2])
    estimates = pl.concat([_estimates(s1), _estimates(s2)])
    now = dt.datetime(2024, 3, 2)
    with open_warehouse(db) as wh, wh.transaction() as con:
        # the public view the recording reads, over a table of this test's rows
        con.register("new_estimates", estimates.to_arrow())
        con.execute("CREATE TABLE test_contact_estimates AS SELECT * FROM new_estimates")
        con.execute(
            "CREATE OR REPLACE VIEW v_contact_estimates AS SELECT * FROM test_contact_estimates"
        )
        con.register("new_samples", samples.to_arrow())
        con.execute("INSERT INTO samples SELECT * FROM new_samples")
        con.register("new_predictions", predictions.to_arrow())
        con.execute("INSERT INTO predictions SELECT * FROM new_predictions")
        for event_id, kind, start, end, v0, v1 in (
            (E1, "stop", E1_START, E1_END, 80.0, 0.0),
            (E2, "slowdown", E2_START, E2_END, 80.0, 0.0),
        ):
            con.execute(
                "INSERT INTO events VALUES ($id, $w, $a, $b, $d, 1700.0, $v0, $v1, 2.5, 2.5, "
                "20.0, $kind, true, $now)",
                {
                    "id": event_id,
                    "w": WAGON,
                    "a": start,
                    "b": end,
                    "d": (end - start).total_seconds(),
                    "v0": v0,
                    "v1": v1,
                    "kind": kind,
                    "now": now,
                },
            )
        con.execute(
            "INSERT INTO model_revisions VALUES ('declared', NULL, NULL, '{}', NULL, NULL, "
            "'rom', true, $now, NULL)",
            {"now": now},
        )
        con.execute(
            "INSERT INTO flags VALUES "
            "('F1', $w, $e, 'overheating', 'alarm', $a, $b, "
            "'contact temperature 420 °C over the 400 °C limit: inspect the block', $now), "
            "('F2', $w, NULL, 'sensor_fault', 'warning', $fa, $fb, "
            "'5 readings out of range: check the thermistor wiring', $now)",
            {
                "w": WAGON,
                "e": E1,
                "a": T0 + dt.timedelta(seconds=150),
                "b": T0 + dt.timedelta(seconds=210),
                "fa": T0 + dt.timedelta(seconds=400),
                "fb": T0 + dt.timedelta(seconds=405),
                "now": now,
            },
        )
    return {
        "db": db,
        "samples_1": FIRST_TRIP_S + SECOND_TRIP_S,
        "valid_temps": FIRST_TRIP_S + SECOND_TRIP_S - len(FAULTY_S) - len(MISSING_S),
        "predictions": predictions.height,
        "residuals": predictions["measured_sensor_c"].is_not_null().sum(),
        "p1": p1,
        "estimates": estimates.height,
        "estimates_frame": estimates,
    }


def _read(path: Path) -> dict[str, dict[str, object]]:
    """Per entity path: rows per component (non-null, temporal), static components, and the
    type of every timeline column seen."""
    entities: dict[str, dict[str, object]] = defaultdict(
        lambda: {"rows": defaultdict(int), "static": set(), "timelines": {}, "values": {}}
    )
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        entity = entities[chunk.entity_path]
        for name in chunk.timeline_names:
            entity["timelines"][name] = batch.schema.field(name).type  # type: ignore[index]
        for f in batch.schema:
            if f.name in chunk.timeline_names or f.name.startswith("rerun.controls"):
                continue
            column = batch.column(f.name)
            if chunk.is_static:
                entity["static"].add(f.name)  # type: ignore[attr-defined]
            else:
                entity["rows"][f.name] += len(column) - column.null_count  # type: ignore[index]
            entity["values"].setdefault(f.name, []).extend(column.to_pylist())  # type: ignore[union-attr]
    return entities


def _assert_utc_timeline(entities: dict[str, dict[str, object]]) -> None:
    for path, entity in entities.items():
        for name, kind in entity["timelines"].items():  # type: ignore[union-attr]
            assert name == TIMELINE, (path, name)
            assert pa.types.is_timestamp(kind), (path, kind)


def test_timeline_recording(fleet_db: dict[str, object], tmp_path: Path) -> None:
    out = tmp_path / "timeline.rrd"
    summary = record(fleet_db["db"], WAGON, out)  # type: ignore[arg-type]
    assert out.exists() and summary.revision == "declared"
    e = _read(out)
    _assert_utc_timeline(e)

    n = fleet_db["samples_1"]
    assert e["/wagon/speed_kmh"]["rows"]["Scalars:scalars"] == n
    assert e["/wagon/brake_pressure_bar"]["rows"]["Scalars:scalars"] == n
    measured = e["/wagon/temperature/measured_sensor_c"]
    assert measured["rows"]["Scalars:scalars"] == fleet_db["valid_temps"]
    assert max(v[0] for v in measured["values"]["Scalars:scalars"]) < 100.0  # no 850 °C
    for path in (
        "predicted_sensor_c",
        "predicted_contact_mean_c",
        "predicted_contact_max_c",
    ):
        rows = e[f"/wagon/temperature/{path}"]["rows"]["Scalars:scalars"]
        assert rows == fleet_db["predictions"]
    assert e["/wagon/residual_k"]["rows"]["Scalars:scalars"] == fleet_db["residuals"]
    # The virtual sensor: the contact estimate with its band, and the unexplained power.
    for path in (
        "temperature/estimated_contact_mean_c",
        "temperature/estimated_contact_mean_lo_c",
        "temperature/estimated_contact_mean_hi_c",
        "unexplained_power/estimate_w",
        "unexplained_power/lo_w",
        "unexplained_power/hi_w",
    ):
        assert e[f"/wagon/{path}"]["rows"]["Scalars:scalars"] == fleet_db["estimates"], path
        assert e[f"/wagon/{path}"]["rows"]["Clear:is_recursive"] == 1, path  # the 2-h gap
    power = [v[0] for v in e["/wagon/unexplained_power/estimate_w"]["values"]["Scalars:scalars"]]
    assert sum(p == 500.0 for p in power) == len(DRAG_S) and max(power) == 500.0
    high = e["/wagon/unexplained_power/hi_w"]["values"]["Scalars:scalars"]
    assert max(v[0] for v in high) == 550.0
    mean = e["/wagon/temperature/estimated_contact_mean_c"]["values"]["Scalars:scalars"]
    low = e["/wagon/temperature/estimated_contact_mean_lo_c"]["values"]["Scalars:scalars"]
    assert all(m[0] - lo[0] == pytest.approx(5.0) for m, lo in zip(mean, low, strict=True))
    assert summary.counts["wagon/unexplained_power/estimate_w"] == fleet_db["estimates"]
    # The two-hour gap between the trips is a hole in the lines, not a straight line.
    assert e["/wagon/speed_kmh"]["rows"]["Clear:is_recursive"] == 1
    assert "SeriesLines:names" in e["/wagon/speed_kmh"]["static"]

    flags = e["/log/flags"]["values"]
    assert flags["TextLog:level"] == [["ERROR"], ["ERROR"], ["WARN"], ["WARN"]]
    texts = [t[0] for t in flags["TextLog:text"]]
    assert texts[0].startswith("overheating [alarm] F1") and "inspect the block" in texts[0]
    assert "ends" in texts[1] and texts[2].startswith("sensor_fault [warning] F2")
    events = [t[0] for t in e["/log/events"]["values"]["TextLog:text"]]
    assert len(events) == 4 and E1 in events[0] and "stop" in events[0] and "ends" in events[1]
    states = [s[0] if s else "" for s in e["/state/events"]["values"]["StateChange:state"]]
    assert states == ["stop", "", "slowdown", ""]
    assert e["/state/flags/overheating"]["rows"]["StateChange:state"] == 2
    assert e["/log/faulty_readings"]["rows"]["TextLog:text"] == 1
    assert "/block/mesh" not in e

    blueprints = RrdReader(out).blueprints()
    assert len(blueprints) == 1
    assert len(list(RrdReader(out).stream(store=blueprints[0]))) > 0


def test_event_recording_has_the_block_field(fleet_db: dict[str, object], tmp_path: Path) -> None:
    out = tmp_path / "event.rrd"
    summary = record(fleet_db["db"], WAGON, out, event_id=E1)  # type: ignore[arg-type]
    e = _read(out)
    _assert_utc_timeline(e)

    # Window: 60 s before activation to the last prediction (the end of the first trip).
    assert e["/wagon/speed_kmh"]["rows"]["Scalars:scalars"] == FIRST_TRIP_S - 100 + 60
    p1 = fleet_db["p1"]
    assert e["/wagon/temperature/predicted_sensor_c"]["rows"]["Scalars:scalars"] == p1.height
    # the estimates of the window (every logged second of it), not the other trip's
    window_s = FIRST_TRIP_S - 100 + 60
    assert e["/wagon/temperature/estimated_contact_mean_c"]["rows"]["Scalars:scalars"] == window_s
    assert e["/wagon/unexplained_power/estimate_w"]["rows"]["Scalars:scalars"] == window_s

    n_steps = p1.height - 1  # one-second steps between the predicted seconds
    every = round(FIELD_EVERY_S)
    frames = n_steps // every + 1 + (1 if n_steps % every else 0)
    mesh = e["/block/mesh"]
    assert mesh["rows"]["Mesh3D:vertex_colors"] == frames == summary.counts["block/mesh"]
    assert {"Mesh3D:vertex_positions", "Mesh3D:triangle_indices"} <= mesh["static"]
    assert "Points3D:positions" in e["/block/sensor"]["static"]
    colours = mesh["values"]["Mesh3D:vertex_colors"]
    assert colours[0] != colours[-1]  # the block heated up
    assert len(set(map(len, colours))) == 1

    # The event's flag and the wagon's sensor fault inside the window; not the other event.
    levels = [lv[0] for lv in e["/log/flags"]["values"]["TextLog:level"]]
    assert levels == ["ERROR", "ERROR", "WARN", "WARN"]
    assert all(E2 not in t[0] for t in e["/log/events"]["values"]["TextLog:text"])
    assert any("inferno" in t[0] for t in e["/log/notes"]["values"]["TextLog:text"])


def test_wagon_without_predictions_still_records_samples(
    fleet_db: dict[str, object], tmp_path: Path
) -> None:
    out = tmp_path / "bare.rrd"
    summary = record(fleet_db["db"], BARE_WAGON, out)  # type: ignore[arg-type]
    assert any("no predictions" in n for n in summary.notes)
    e = _read(out)
    assert e["/wagon/speed_kmh"]["rows"]["Scalars:scalars"] == 50
    assert e["/wagon/temperature/measured_sensor_c"]["rows"]["Scalars:scalars"] == 50
    assert (
        "/wagon/temperature/predicted_sensor_c" not in e
        or not e["/wagon/temperature/predicted_sensor_c"]["rows"]
    )
    notes = [t[0] for t in e["/log/notes"]["values"]["TextLog:text"]]
    assert any("no predictions" in n for n in notes)
    assert (
        "/wagon/unexplained_power/estimate_w" not in e
        or not (e["/wagon/unexplained_power/estimate_w"]["rows"])
    )


def test_bad_input_names_what_is_wrong(fleet_db: dict[str, object], tmp_path: Path) -> None:
    db = fleet_db["db"]
    with pytest.raises(RecordError, match="unknown wagon NOPE-1"):
        record(db, "NOPE-1", tmp_path / "x.rrd")  # type: ignore[arg-type]
    with pytest.raises(RecordError, match="unknown event NOPE-EVENT"):
        record(db, WAGON, tmp_path / "x.rrd", event_id="NOPE-EVENT")  # type: ignore[arg-type]
    with pytest.raises(RecordError, match=f"event {E1} is of wagon {WAGON}, not of wagon"):
        record(db, BARE_WAGON, tmp_path / "x.rrd", event_id=E1)  # type: ignore[arg-type]
    with pytest.raises(RecordError, match="unknown model revision 'r9'"):
        record(db, WAGON, tmp_path / "x.rrd", revision="r9")  # type: ignore[arg-type]
    with pytest.raises(RecordError, match=r"nowhere\.duckdb"):
        record(tmp_path / "nowhere.duckdb", WAGON, tmp_path / "x.rrd")
    assert not list(tmp_path.iterdir())  # nothing written, not even a partial file
    (tmp_path / "adir").mkdir()
    with pytest.raises(RecordError, match="adir: cannot write the recording"):
        record(db, WAGON, tmp_path / "adir")  # type: ignore[arg-type]
    assert [p.name for p in tmp_path.iterdir()] == ["adir"]


def test_cli(fleet_db: dict[str, object], tmp_path: Path) -> None:
    runner = CliRunner()
    db = str(fleet_db["db"])
    out = tmp_path / "cli.rrd"
    result = runner.invoke(
        app, ["record", "--db", db, "--wagon", WAGON, "--event", E2, "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    assert out.exists() and E2 in result.output

    result = runner.invoke(app, ["record", "--db", db, "--wagon", "NOPE-1", "--out", str(out)])
    assert result.exit_code == 1
    assert "NOPE-1" in result.output

    result = runner.invoke(
        app, ["record", "--db", db, "--wagon", WAGON, "--event", "NOPE-E", "--out", str(out)]
    )
    assert result.exit_code == 1
    assert "NOPE-E" in result.output

    missing = tmp_path / "missing.duckdb"
    result = runner.invoke(app, ["record", "--db", str(missing), "--wagon", WAGON, "--out", "x"])
    assert result.exit_code == 1
    assert str(missing) in result.output

    result = runner.invoke(app, ["record", "--help"])
    assert result.exit_code == 0 and "--wagon" in result.output


def test_database_being_written_is_reported(fleet_db: dict[str, object], tmp_path: Path) -> None:
    import shutil
    import subprocess
    import sys

    db = tmp_path / "busy.duckdb"
    shutil.copy(fleet_db["db"], db)  # type: ignore[arg-type]
    holder = "import duckdb, sys; c = duckdb.connect(sys.argv[1]); print('ready', flush=True); sys.stdin.read()"
    writer = subprocess.Popen(
        [sys.executable, "-c", holder, str(db)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert writer.stdout is not None and writer.stdout.readline().strip() == "ready"
        result = CliRunner().invoke(
            app, ["record", "--db", str(db), "--wagon", WAGON, "--out", str(tmp_path / "b.rrd")]
        )
    finally:
        writer.communicate(input="", timeout=30)
    assert result.exit_code == 75, result.output
    assert str(db) in result.output and "another process" in result.output
    assert not (tmp_path / "b.rrd").exists()


def _blueprint_names(path: Path) -> set[str]:
    (store,) = RrdReader(path).blueprints()
    names: set[str] = set()
    for chunk in RrdReader(path).stream(store=store):
        batch = chunk.to_record_batch()
        if "ViewBlueprint:display_name" in batch.schema.names:
            for value in batch.column("ViewBlueprint:display_name").to_pylist():
                names.update(value or [])
    return names


def test_blueprint_lays_out_the_review(fleet_db: dict[str, object], tmp_path: Path) -> None:
    record(fleet_db["db"], WAGON, tmp_path / "t.rrd")  # type: ignore[arg-type]
    record(fleet_db["db"], WAGON, tmp_path / "e.rrd", event_id=E2)  # type: ignore[arg-type]
    timeline, event = _blueprint_names(tmp_path / "t.rrd"), _blueprint_names(tmp_path / "e.rrd")
    plots = {
        "Block temperature °C: measured vs predicted, contact estimate (95 % band)",
        "Unexplained heat power W (estimate, 95 % band)",
        "Speed km/h",
        "Brake pressure bar",
        "Residual K (measured - predicted sensor)",
        "Events, flags, faulty readings",
        "Flags, events, notes",
    }
    assert plots <= timeline and plots <= event
    assert not any(n.startswith("Block temperature field") for n in timeline)
    assert any(n.startswith("Block temperature field (inferno") for n in event)


def test_registry_gives_the_block(fleet_db: dict[str, object], tmp_path: Path) -> None:
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    (fleet / "fleet.toml").write_text(
        f'[defaults]\nwheel_radius_m = 0.5\n\n[[wagon]]\nid = "{WAGON}"\n', encoding="utf-8"
    )
    runner = CliRunner()
    args = ["record", "--db", str(fleet_db["db"]), "--event", E2, "--registry", str(fleet)]
    result = runner.invoke(app, [*args, "--wagon", WAGON, "--out", str(tmp_path / "r.rrd")])
    assert result.exit_code == 0, result.output
    assert "spec's defaults" not in result.output
    e = _read(tmp_path / "r.rrd")
    ((sensor,),) = e["/block/sensor"]["values"]["Points3D:positions"]
    assert sensor[1] == pytest.approx(0.5 + 0.055)  # the registry's wheel, the default seat
    ys = [p[1] for p in e["/block/mesh"]["values"]["Mesh3D:vertex_positions"][0]]
    assert min(ys) == pytest.approx(0.5 * np.cos(np.radians(29.4 / 2)), rel=1e-3)

    result = runner.invoke(app, [*args, "--wagon", BARE_WAGON, "--out", str(tmp_path / "x.rrd")])
    assert result.exit_code == 1
    assert BARE_WAGON in result.output and "fleet.toml" in result.output


def test_flags_of_one_kind_overlapping_show_the_highest_severity() -> None:
    from fleetbrake.viz.timeline import _flag_lane

    t = [dt.datetime(2024, 3, 1, 10, 0, s) for s in range(6)]
    lane = _flag_lane(
        [
            {"severity": "warning", "start_utc": t[0], "end_utc": t[4]},
            {"severity": "alarm", "start_utc": t[1], "end_utc": t[2]},
            {"severity": "info", "start_utc": t[3], "end_utc": t[5]},
        ]
    )
    assert [(c[0], c[2]) for c in lane] == [
        (np.datetime64(t[0], "ns"), "warning"),
        (np.datetime64(t[1], "ns"), "alarm"),
        (np.datetime64(t[2], "ns"), "warning"),
        (np.datetime64(t[4], "ns"), "info"),
        (np.datetime64(t[5], "ns"), ""),
    ]


def test_block_of_the_registry_run_stored(fleet_db: dict[str, object], tmp_path: Path) -> None:
    import dataclasses
    import json
    import shutil

    from fleetbrake.fleet.registry import WagonConfig

    db = tmp_path / "stored.duckdb"
    shutil.copy(fleet_db["db"], db)  # type: ignore[arg-type]
    config = WagonConfig(wagon_id=WAGON, wheel_radius_m=0.5)
    with open_warehouse(db) as wh:
        wh.con.execute(
            "INSERT INTO wagon_registry VALUES ($w, $c, 'fleet/fleet.toml', now())",
            {"w": WAGON, "c": json.dumps(dataclasses.asdict(config))},
        )
    summary = record(db, WAGON, tmp_path / "s.rrd", event_id=E2)
    assert any("fleet/fleet.toml" in n for n in summary.notes)
    ((sensor,),) = _read(tmp_path / "s.rrd")["/block/sensor"]["values"]["Points3D:positions"]
    assert sensor[1] == pytest.approx(0.5 + 0.055)


def test_event_flags_and_quarantined_wagons(fleet_db: dict[str, object], tmp_path: Path) -> None:
    """An event's recording shows the flags tied to it even outside its window, and no other
    flag from outside it; a wagon whose every file was quarantined is named with the reason."""
    import shutil

    db = tmp_path / "more.duckdb"
    shutil.copy(fleet_db["db"], db)  # type: ignore[arg-type]
    late = T1 + dt.timedelta(hours=3)
    with open_warehouse(db) as wh:
        wh.con.execute(
            "INSERT INTO flags VALUES ('F3', $w, $e, 'dragging_brake', 'info', $a, $b, "
            "'heating long after the stop', $a)",
            {"w": WAGON, "e": E1, "a": late, "b": late + dt.timedelta(seconds=60)},
        )
        wh.con.execute(
            "INSERT INTO files (file_id, path, wagon_id, sha256, size_bytes, mtime_ns, status, "
            "reason, rows, ingested_utc) VALUES (9, 'logs/TW-0003_20240301T000000Z.csv', "
            "'TW-0003', 'x', 10, 0, 'quarantined', 'TW-0003_20240301T000000Z.csv: no header', "
            "0, $a)",
            {"a": late},
        )

    def flag_texts(event_id: str) -> list[str]:
        out = tmp_path / f"{event_id}.rrd"
        record(db, WAGON, out, event_id=event_id)
        flags = _read(out).get("/log/flags")
        return [t[0] for t in flags["values"]["TextLog:text"]] if flags else []  # type: ignore[index]

    assert any(t.startswith("dragging_brake [info] F3") for t in flag_texts(E1))
    assert not any("F3" in t for t in flag_texts(E2))
    with pytest.raises(RecordError, match="TW-0003 has no samples: all its files were quarantined"):
        record(db, "TW-0003", tmp_path / "q.rrd")
