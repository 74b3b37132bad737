"""The synthetic fleet generator (fleetbrake.synth.generator, ``fleetbrake synth``).

The default fleet (4 wagons x 2 days, every imperfection and anomaly on) is generated once
per session into a directory the xdist workers share (a file lock decides who writes it);
the reduced model is the session's (tests/conftest.py).
"""

from __future__ import annotations

import datetime as dt
import fcntl
import gzip
import io
import os
import re
import zlib
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from typer.testing import CliRunner

from fleetbrake.cli.main import app
from fleetbrake.fleet import logfile
from fleetbrake.fleet.registry import load_registry
from fleetbrake.model.effects import (
    EFFECT_ORDER,
    ConvectionFlatPlate,
    EffectSet,
    FrictionSpeed,
    SensorLag,
)
from fleetbrake.model.physics import block_force_n
from fleetbrake.synth.block import solar_rise_k
from fleetbrake.synth.config import draw_effect
from fleetbrake.synth.generator import (
    SENSOR_FAULT_SUBTYPES,
    FleetTruth,
    SynthConfig,
    generate_fleet,
    load_truth,
    summary,
)

TIME_RE = re.compile(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ")


@pytest.fixture(scope="session")
def fleet(tmp_path_factory, reduced_model_for) -> FleetTruth:
    """The default fleet, generated once for all workers of the session."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # shared by the workers of this session only
    out = root / "synth-default"
    with open(root / "synth-default.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (out / "truth" / "truth.json").exists():
            return load_truth(out)
        return generate_fleet(out, SynthConfig(), rom=reduced_model_for)


def _read(path: Path) -> bytes:
    data = path.read_bytes()
    return gzip.decompress(data) if path.name.endswith(".gz") else data


def _frame(path: Path) -> pl.DataFrame:
    return pl.read_csv(io.BytesIO(_read(path)), infer_schema=False)


def _good_files(fleet: FleetTruth, *, clean: bool = False):
    faulty = {a.file for a in fleet.anomalies if a.kind == "sensor_fault"}
    for f in fleet.files:
        if f.bad is not None or (clean and (f.path in faulty)):
            continue
        yield f


def _numbers(frame: pl.DataFrame, column: str) -> np.ndarray:
    return frame[column].cast(pl.Float64, strict=True).to_numpy()


def _times(frame: pl.DataFrame) -> pl.Series:
    return frame["time_utc"].str.strptime(pl.Datetime("us"), "%Y-%m-%dT%H:%M:%SZ")


# --------------------------------------------------------------------------------------------
# The contract of fleet-data.md


def test_the_fleet_directory_follows_the_data_contract(fleet):
    root = fleet.out_dir
    assert sorted(p.name for p in root.iterdir()) == ["fleet.toml", "logs", "truth"]
    on_disk = sorted(
        p.relative_to(root).as_posix() for p in (root / "logs").rglob("*") if p.is_file()
    )
    assert on_disk == sorted(f.path for f in fleet.files)
    for rel in on_disk:
        name = logfile.parse_log_path(rel)
        assert logfile.WAGON_ID_PATTERN.fullmatch(name.wagon_id)
    registry = load_registry(root / "fleet.toml")
    good = [w.wagon_id for w in fleet.wagons if w.registry == "ok"]
    assert sorted(registry.wagons) == sorted(good) and len(good) == 4

    checked = 0
    for f in _good_files(fleet):
        path = root / f.path
        name = logfile.parse_log_path(f.path)
        assert name.gzip == f.gzip == path.name.endswith(".gz")
        frame = _frame(path)
        assert set(logfile.REQUIRED_COLUMNS) <= set(frame.columns)
        assert frame.height == f.rows_written > 0
        times = frame["time_utc"].drop_nulls().to_list()
        assert all(TIME_RE.fullmatch(t) for t in times)
        parsed = _times(frame).drop_nulls()
        # the name is the session's first sample (the first row, unless its cell was emptied);
        # samples are whole seconds, 1 Hz
        assert name.start_utc == f.start_utc == parsed.min() or frame["time_utc"][0] is None
        assert frame["time_utc"][0] in (f.start_utc.strftime("%Y-%m-%dT%H:%M:%SZ"), None)
        seconds = ((parsed - parsed.min()).dt.total_seconds()).to_numpy()
        unique = np.unique(seconds)
        assert unique[-1] <= f.session_rows - 1
        missing = f.imperfections.get("missing_rows", 0) + f.imperfections.get("gap", {}).get(
            "seconds", 0
        )
        assert f.session_rows - unique.size <= missing + f.imperfections.get("empty_cells", 0)
        if not f.imperfections:
            np.testing.assert_array_equal(seconds, np.arange(f.session_rows))
        # distance since the session began, non-decreasing in time
        all_seconds = (_times(frame) - parsed.min()).dt.total_seconds().to_numpy()
        distance = _numbers(frame, "distance_m")
        known = np.isfinite(all_seconds) & np.isfinite(distance)
        distance = distance[known][np.argsort(all_seconds[known], kind="stable")]
        assert distance[0] == 0.0 or f.imperfections
        assert np.all(np.diff(distance) >= 0)
        # pressure on the 7 mbar grid, never negative; speeds never negative
        pressure = _numbers(frame, "brake_pressure_bar")
        pressure = pressure[np.isfinite(pressure)]
        assert np.all(pressure >= 0)
        np.testing.assert_allclose(pressure / 0.007, np.round(pressure / 0.007), atol=1e-6)
        speed = _numbers(frame, "speed_kmh")
        assert np.nanmin(speed) >= 0 and np.nanmax(speed) < 160
        checked += 1
    assert checked >= 30


def test_ambient_column_and_registry_ambient(fleet):
    registry = load_registry(fleet.out_dir / "fleet.toml")
    kinds = {w.ambient_column for w in fleet.wagons if w.registry == "ok"}
    assert kinds == {"values", "absent", "empty"}
    for wagon in fleet.wagons:
        files = [f for f in _good_files(fleet) if f.wagon_id == wagon.wagon_id]
        series = fleet.series(wagon.wagon_id)
        for f in files[:3]:
            frame = _frame(fleet.out_dir / f.path)
            if wagon.ambient_column == "absent":
                assert "ambient_temp_c" not in frame.columns
            elif wagon.ambient_column == "empty":
                assert frame["ambient_temp_c"].null_count() == frame.height
            else:
                logged = frame.select(
                    _times(frame).alias("time_utc"), pl.col("ambient_temp_c").cast(pl.Float64)
                ).drop_nulls()
                both = logged.join(series.select("time_utc", "ambient_c"), on="time_utc")
                residual = (both["ambient_temp_c"] - both["ambient_c"]).to_numpy()
                assert abs(residual.mean()) < 0.1 and residual.std() < 0.3
        if wagon.ambient_column != "values":
            # the truth used what the reader will use: the registry's value
            assert wagon.ambient_source == "registry"
            expected = registry.wagons[wagon.wagon_id].ambient_temp_c
            assert np.all(series["ambient_c"].to_numpy() == expected)
        else:
            assert series["ambient_c"].std() > 1.0  # a day's sine and weather


def test_operation_is_realistic(fleet):
    for wagon in (w for w in fleet.wagons if w.registry == "ok"):
        s = fleet.series(wagon.wagon_id)
        assert s.height == 2 * 86_400
        v = s["speed_kmh"].to_numpy()
        p = s["brake_pressure_bar"].to_numpy()
        assert 60.0 <= v.max() <= 100.0 + 1e-9
        accel = np.diff(v) / 3.6
        assert accel.max() <= 0.3 + 1e-9
        assert 0.8 < p.max() <= 3.8 + 1e-9
        assert 0.2 < (v > 0.5).mean() < 0.8  # it runs, and it stands
        # filling: from release to 95 % of the target in about 20 s, release in about 45 s
        events = [e for e in fleet.events if e.wagon_id == wagon.wagon_id]
        kinds = {e.kind for e in events}
        assert kinds == {"stop", "slowdown", "drag"}
        for e in events[:20]:
            i = int((e.command_utc - fleet.start_utc).total_seconds())
            j = int((e.release_command_utc - fleet.start_utc).total_seconds())
            if j - i > 40:
                assert p[i + 19] == pytest.approx(e.p_target_bar, rel=0.06)
            k = int((e.end_utc - fleet.start_utc).total_seconds())
            assert 30 <= k - j <= 80
        drags = [e for e in events if e.kind == "drag"]
        assert drags and all(0.5 <= e.p_target_bar <= 0.85 for e in drags)
        assert all(abs(e.v_end_kmh - e.v_start_kmh) < 1e-6 for e in drags)  # constant speed
        assert all(e.v_end_kmh == 0.0 for e in events if e.kind == "stop")
        # sessions: many per day, and the unit sleeps between them
        files = [f for f in fleet.files if f.wagon_id == wagon.wagon_id and f.bad != "garbage"]
        assert len(files) >= 4
        awake = s["awake"].to_numpy()
        assert 0.2 < awake.mean() < 0.95


def test_truth_events_are_the_pressure_applications(fleet):
    for wagon in (w for w in fleet.wagons if w.registry == "ok"):
        s = fleet.series(wagon.wagon_id)
        p = s["brake_pressure_bar"].to_numpy()
        events = sorted(
            (e for e in fleet.events if e.wagon_id == wagon.wagon_id), key=lambda e: e.start_utc
        )
        spans = [
            (
                int((e.start_utc - fleet.start_utc).total_seconds()),
                int((e.end_utc - fleet.start_utc).total_seconds()),
            )
            for e in events
        ]
        inside = np.zeros(p.size, dtype=bool)
        for (a, b), e in zip(spans, events, strict=True):
            assert p[a] > 0.05 >= p[a - 1]  # activation: the first sample of the rise
            assert p[b] <= 0.05 < p[b - 1]  # release: the first sample back at the baseline
            assert p[a:b].max() >= 0.3
            window = p[a : b + 1]
            assert e.p_mean_bar == pytest.approx(np.trapezoid(window) / (b - a), rel=1e-5)
            inside[a:b] = True
        # every second above the baseline belongs to exactly one event; events do not touch
        np.testing.assert_array_equal(inside, p > 0.05)
        starts = np.array([a for a, _ in spans])
        ends = np.array([b for _, b in spans])
        assert np.all(starts[1:] - ends[:-1] >= 20)


def test_recorded_events_are_in_their_files(fleet):
    by_path = {f.path: f for f in fleet.files}
    recorded = [e for e in fleet.events if e.recorded]
    assert len(recorded) > 100
    assert len(recorded) < len(fleet.events)  # some lie in bad files or while asleep
    for e in recorded[::10]:
        f = by_path[e.file]
        assert f.bad is None and f.start_utc <= e.start_utc and e.end_utc <= f.end_utc
        frame = _frame(fleet.out_dir / f.path)
        frame = frame.with_columns(_times(frame).alias("t"))
        window = frame.filter(pl.col("t").is_between(e.start_utc, e.end_utc))
        assert window["brake_pressure_bar"].cast(pl.Float64).max() >= 0.3 - 0.01


def test_the_projects_reader_takes_the_fleet_as_the_truth_says(fleet, tmp_path):
    """Integration: ``fleetbrake ingest`` quarantines exactly the bad files and the files of
    the wagons without a good registry entry, and finds the recorded braking events."""
    import duckdb

    from fleetbrake.ingest.files import run_ingest

    db = tmp_path / "fleet.duckdb"
    report = run_ingest(fleet.out_dir, db, progress=False)
    status = {r.path: r.status for r in report.results}
    assert set(status) == {f.path for f in fleet.files}
    for f in fleet.files:
        expected = "ingested" if f.bad is None and f.registered else "quarantined"
        if f.bad == "truncated_mid_row" and status[f.path] == "ingested":
            continue  # the reader may keep the complete rows of a cut file
        assert status[f.path] == expected, f
    con = duckdb.connect(str(db), read_only=True)
    try:
        detected = con.execute("SELECT wagon_id, start_utc, end_utc FROM v_events").fetchall()
    finally:
        con.close()
    truth = [
        e
        for e in fleet.events
        if e.recorded and any(f.path == e.file and f.registered for f in fleet.files)
    ]
    assert len(truth) > 100
    found = {(w, s) for w, s, _ in detected}
    near = 0
    for e in truth:
        near += any(
            (e.wagon_id, e.start_utc + dt.timedelta(seconds=d)) in found for d in (-1, 0, 1)
        )
    assert near >= 0.97 * len(truth)
    # more only where the reader kept the complete rows of a file cut mid-row
    cut = {f.path for f in fleet.files if f.bad == "truncated_mid_row"}
    in_cut = sum(e.file in cut for e in fleet.events)
    assert len(truth) - 5 <= len(detected) <= len(truth) + in_cut + 2


# --------------------------------------------------------------------------------------------
# Readings against the truth


def test_sensor_noise_is_the_pt1000s(fleet):
    residuals = []
    for f in _good_files(fleet, clean=True):
        frame = _frame(fleet.out_dir / f.path)
        logged = frame.select(
            _times(frame).alias("time_utc"), pl.col("block_temp_c").cast(pl.Float64)
        ).drop_nulls()
        reading = logged["block_temp_c"].to_numpy()
        np.testing.assert_allclose(reading * 100, np.round(reading * 100), atol=1e-6)  # 0.01 K
        truth = fleet.series(f.wagon_id).select("time_utc", "sensor_c")
        both = logged.join(truth, on="time_utc")
        residuals.append((both["block_temp_c"] - both["sensor_c"]).to_numpy())
    r = np.concatenate(residuals)
    assert r.size > 100_000
    assert abs(r.mean()) < 0.003
    assert r.std() == pytest.approx(0.1, rel=0.03)
    assert np.abs(r).max() < 0.7  # Gaussian, no outlier: faults are elsewhere


def test_the_block_keeps_cooling_while_the_unit_sleeps(fleet):
    wagon = fleet.wagons[0].wagon_id
    s = fleet.series(wagon)
    awake = s["awake"].to_numpy()
    sensor = s["sensor_c"].to_numpy()
    ambient = s["ambient_c"].to_numpy()
    edges = np.flatnonzero(np.diff(awake.astype(int)) == -1) + 1  # first sleeping second
    cooled = 0
    for e in edges:
        nxt = np.flatnonzero(awake[e:])
        if nxt.size == 0 or nxt[0] < 1800:
            continue
        # asleep: no heat, and the excess over the air decays
        assert s["heat_flux_w_m2"][e : e + int(nxt[0])].max() == 0.0
        before, after = sensor[e] - ambient[e], sensor[e + nxt[0]] - ambient[e + nxt[0]]
        if before > 20:
            assert after < before * 0.9
            cooled += 1
    assert cooled >= 1
    # and the next session's first readings start where the truth is
    files = [f for f in _good_files(fleet, clean=True) if f.wagon_id == wagon]
    for f in files[1:4]:
        frame = _frame(fleet.out_dir / f.path).head(20)
        logged = frame["block_temp_c"].cast(pl.Float64).drop_nulls().to_numpy()
        i = int((f.start_utc - fleet.start_utc).total_seconds())
        assert abs(np.median(logged) - np.median(sensor[i : i + 20])) < 0.15


def test_pressure_and_speed_readings(fleet):
    clean = [x for x in _good_files(fleet, clean=True) if "frozen_speed" not in x.imperfections]
    clean = [x for x in clean if "speed_jumps" not in x.imperfections]
    for f in clean[:5]:
        frame = _frame(fleet.out_dir / f.path)
        logged = frame.select(
            _times(frame).alias("time_utc"),
            pl.col("brake_pressure_bar", "speed_kmh").cast(pl.Float64).name.suffix("_log"),
        ).drop_nulls()
        both = logged.join(fleet.series(f.wagon_id), on="time_utc")
        dp = (both["brake_pressure_bar_log"] - both["brake_pressure_bar"]).to_numpy()
        assert np.abs(dp).max() < 0.0035 + 5 * 0.003  # half the 7 mbar step, and the noise
        assert abs(dp.mean()) < 0.002
        moving = both.filter(pl.col("speed_kmh") > 10)
        dv = (moving["speed_kmh_log"] - moving["speed_kmh"]).to_numpy()
        assert 0.25 < dv.std() < 0.35


# --------------------------------------------------------------------------------------------
# Imperfections and anomalies


def test_configured_imperfections_are_in_the_files(fleet):
    root = fleet.out_dir
    kinds = {k for f in fleet.files for k in f.imperfections}
    for kind in (
        "missing_rows",
        "duplicated_rows",
        "swapped_pairs",
        "empty_cells",
        "gap",
        "frozen_speed",
        "speed_jumps",
        "odd_columns",
    ):
        assert kind in kinds, kind
    for f in _good_files(fleet):
        imp = f.imperfections
        if not imp:
            continue
        frame = _frame(root / f.path)
        times = _times(frame)
        if "duplicated_rows" in imp:
            assert times.drop_nulls().is_duplicated().sum() >= 2
        if "swapped_pairs" in imp:
            t = times.drop_nulls().to_numpy()
            assert np.sum(np.diff(t) < np.timedelta64(0)) >= 1
        if "empty_cells" in imp:
            cells = frame.drop("ambient_temp_c", strict=False)
            assert cells.null_count().sum_horizontal().item() > 0
        if "gap" in imp:
            start = imp["gap"]["start_utc"]
            hole = times.filter(
                times.is_between(start, start + dt.timedelta(seconds=imp["gap"]["seconds"] - 1))
            )
            assert hole.len() == 0
        if "frozen_speed" in imp:
            start, seconds = imp["frozen_speed"]["start_utc"], imp["frozen_speed"]["seconds"]
            frozen = frame.filter(
                times.is_between(start, start + dt.timedelta(seconds=seconds - 1))
            )
            assert frozen["speed_kmh"].drop_nulls().n_unique() == 1
        if "odd_columns" in imp:
            assert list(frame.columns) == imp["odd_columns"]
            assert "battery_v" in frame.columns
            assert list(frame.columns)[:8] != list(logfile.REQUIRED_COLUMNS)


def test_bad_files_are_bad_as_recorded(fleet):
    bad = {f.bad: f for f in fleet.bad_files()}
    assert set(bad) == {"truncated_mid_row", "truncated_gzip", "garbage"}
    cut = (fleet.out_dir / bad["truncated_mid_row"].path).read_bytes()
    assert not cut.endswith(b"\n") and cut.startswith(b"time_utc,")
    assert logfile.complete_rows(cut) == bad["truncated_mid_row"].rows_written
    assert bad["truncated_mid_row"].rows_written < bad["truncated_mid_row"].session_rows
    packed = (fleet.out_dir / bad["truncated_gzip"].path).read_bytes()
    with pytest.raises(EOFError):
        gzip.decompress(packed)
    assert (
        logfile.complete_rows(zlib.decompressobj(wbits=31).decompress(packed))
        == bad["truncated_gzip"].rows_written
    )
    garbage = (fleet.out_dir / bad["garbage"].path).read_bytes()
    assert not garbage.startswith(b"time_utc") and bad["garbage"].reason
    # registry: one wagon with logs and no entry, one with a bad value
    registry = load_registry(fleet.out_dir / "fleet.toml")
    missing = [w for w in fleet.wagons if w.registry == "missing"]
    broken = [w for w in fleet.wagons if w.registry == "bad"]
    assert len(missing) == len(broken) == 1
    assert missing[0].wagon_id not in registry and broken[0].wagon_id not in registry
    assert any(f.wagon_id == missing[0].wagon_id for f in fleet.files)
    assert any(f.wagon_id == broken[0].wagon_id for f in fleet.files)
    [problem] = registry.problems
    assert (problem.wagon_id, problem.key) == (broken[0].wagon_id, "cylinder_diameter_m")
    assert fleet.registry_problems[0]["wagon_id"] == broken[0].wagon_id


def test_anomalies_are_in_the_truth_and_act(fleet):
    kinds = sorted((a.kind, a.subtype or "") for a in fleet.anomalies)
    assert kinds == sorted(
        [("dragging_brake", ""), ("weak_brake", "")]
        + [("sensor_fault", s) for s in SENSOR_FAULT_SUBTYPES]
    )
    registry = load_registry(fleet.out_dir / "fleet.toml")
    clean = fleet.wagons[0].wagon_id
    assert all(a.wagon_id != clean for a in fleet.anomalies)
    for a in fleet.anomalies:
        s = fleet.series(a.wagon_id)
        i = int((a.start_utc - fleet.start_utc).total_seconds())
        j = int((a.end_utc - fleet.start_utc).total_seconds())
        force = s["block_force_n"].to_numpy()
        p = s["brake_pressure_bar"].to_numpy()
        declared = np.asarray(block_force_n(registry.wagons[a.wagon_id], p))
        if a.kind == "dragging_brake":
            assert 15 * 60 <= j - i <= 40 * 60 or j == s.height
            assert np.all(force[i:j] >= a.parameters["drag_force_n"] - 1e-3)
            released = p[i:j] < 0.01
            assert released.mean() > 0.5
            heating = s["heat_flux_w_m2"].to_numpy()[i:j][
                released & (s["speed_kmh"][i:j] > 10).to_numpy()
            ]
            assert heating.size and heating.min() > 0
            assert s["sensor_c"][j] - s["sensor_c"][i] > 5.0
            np.testing.assert_allclose(force[:i], declared[:i], rtol=0, atol=2e-3)
        elif a.kind == "weak_brake":
            assert j - i == 86_400
            share = a.parameters["brake_efficiency"]
            assert 0.4 <= share <= 0.6
            np.testing.assert_allclose(force[i:j], share * declared[i:j], rtol=0, atol=2e-3)
            np.testing.assert_allclose(force[:i], declared[:i], rtol=0, atol=2e-3)
        else:
            f = next(x for x in fleet.files if x.path == a.file)
            assert f.bad is None and f.wagon_id == a.wagon_id
            frame = _frame(fleet.out_dir / f.path)
            frame = frame.with_columns(_times(frame).alias("t")).join(
                s.select(pl.col("time_utc").alias("t"), "sensor_c", "ambient_c"), on="t"
            )
            during = frame.filter(pl.col("t").is_between(a.start_utc, a.end_utc, closed="left"))
            before = frame.filter(pl.col("t") < a.start_utc)
            reading = during["block_temp_c"].cast(pl.Float64)
            if a.subtype == "open":
                assert reading.drop_nulls().is_between(-60.0, 600.0).sum() == 0
                assert (
                    before["block_temp_c"].cast(pl.Float64).drop_nulls().is_between(-60, 600).all()
                )
            elif a.subtype == "frozen":
                assert reading.drop_nulls().n_unique() == 1
            elif a.subtype == "loose":
                tail = during.tail(60)
                to_air = (tail["block_temp_c"].cast(pl.Float64) - tail["ambient_c"]).abs().mean()
                truth_to_air = (tail["sensor_c"] - tail["ambient_c"]).abs().mean()
                assert to_air < truth_to_air
            else:
                off = (reading - during["sensor_c"]).to_numpy()
                hours = (during["t"] - during["t"][0]).dt.total_seconds().to_numpy() / 3600
                ok = np.isfinite(off)
                rate = np.polyfit(hours[ok], off[ok], 1)[0]
                assert rate == pytest.approx(a.parameters["rate_k_per_h"], abs=0.2)


# --------------------------------------------------------------------------------------------
# Reproducibility, effects, configuration, command line


def _tree(root: Path) -> dict[str, bytes]:
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_the_same_seed_writes_the_same_bytes(tmp_path, reduced_model_for):
    # every imperfection and anomaly on, the extra wagons off (time)
    config = SynthConfig(
        wagons=2,
        days=1,
        seed=11,
        effects=EffectSet((SensorLag(tau_s=30.0),)),
        unregistered_wagon=False,
        bad_registry_entry=False,
    )
    one = generate_fleet(tmp_path / "one", config, rom=reduced_model_for)
    generate_fleet(tmp_path / "two", config, rom=reduced_model_for)
    a, b = _tree(tmp_path / "one"), _tree(tmp_path / "two")
    assert a.keys() == b.keys() and len(a) > 10
    assert [k for k in a if a[k] != b[k]] == []
    assert one.anomalies and one.bad_files()
    # the truth reads back as it was returned
    back = load_truth(tmp_path / "one")
    assert back.to_dict() == one.to_dict()
    assert back.files == one.files and back.events == one.events
    # another seed, another fleet
    other = generate_fleet(
        tmp_path / "three", SynthConfig.clean(wagons=1, days=1, seed=12), rom=reduced_model_for
    )
    assert {f.path for f in other.files}.isdisjoint(f.path for f in one.files)
    assert (
        other.series("SGG-0001")["brake_pressure_bar"].to_list()
        != one.series("SGG-0001")["brake_pressure_bar"].to_list()
    )


def dataclass_replace(config: SynthConfig, **changes):
    import dataclasses

    return dataclasses.replace(config, **changes)


def test_an_effect_changes_the_block_not_the_operation(tmp_path, reduced_model_for):
    base = SynthConfig.clean(wagons=1, days=1, seed=5)
    plain = generate_fleet(tmp_path / "plain", base, rom=reduced_model_for)
    lag = SensorLag(tau_s=90.0)
    lagged = generate_fleet(
        tmp_path / "lagged",
        dataclass_replace(base, effects=EffectSet((lag,))),
        rom=reduced_model_for,
    )
    assert plain.bad_files() == [] and plain.anomalies == [] and plain.registry_problems == []
    assert all(not f.imperfections for f in plain.files)
    assert lagged.effects == EffectSet((lag,))
    assert load_truth(tmp_path / "lagged").effects.get("sensor_lag") == lag
    a, b = plain.series("SGG-0001"), lagged.series("SGG-0001")
    np.testing.assert_array_equal(a["brake_pressure_bar"], b["brake_pressure_bar"])
    np.testing.assert_array_equal(a["seat_c"], b["seat_c"])
    assert plain.events == lagged.events
    peak_a, peak_b = int(a["sensor_c"].arg_max()), int(b["sensor_c"].arg_max())
    assert peak_b > peak_a and b["sensor_c"].max() < a["sensor_c"].max()


def test_config_checks_and_round_trips():
    config = SynthConfig(effects=(SensorLag(),), start=dt.date(2025, 1, 2))
    assert isinstance(config.effects, EffectSet)
    assert SynthConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="wagons"):
        SynthConfig(wagons=0)
    with pytest.raises(ValueError, match="gzip_fraction"):
        SynthConfig(gzip_fraction=1.5)
    with pytest.raises(ValueError, match="start"):
        SynthConfig(start=dt.datetime(2024, 1, 1))


def test_generate_refuses_a_directory_in_use(tmp_path):
    (tmp_path / "x.txt").write_text("mine")
    with pytest.raises(FileExistsError):
        generate_fleet(tmp_path, SynthConfig.clean(wagons=1, days=1))
    assert (tmp_path / "x.txt").read_text() == "mine"


def test_command_line(tmp_path, monkeypatch, rom_cache_dir, rom_refinement, default_rom):
    # default_rom: the model is built (under the lock) before the command looks for it
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    # the command sets it (setdefault) for its process; keep this one's environment as it was
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", os.environ.get("OPENBLAS_NUM_THREADS", "1"))
    runner = CliRunner()
    out = tmp_path / "fleet"
    result = runner.invoke(
        app,
        [
            "synth",
            str(out),
            "--wagons",
            "1",
            "--days",
            "1",
            "--seed",
            "4",
            "--no-anomalies",
            "--no-imperfections",
            "--effect",
            "heat_partition:alpha=0.8",
            "--gzip-fraction",
            "1",
            "--start",
            "2024-06-01",
            "--refinement",
            str(rom_refinement),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "heat_partition:alpha=0.8" in result.output
    truth = load_truth(out)
    assert truth.start_utc == dt.datetime(2024, 6, 1)
    assert truth.anomalies == []
    assert truth.effects.get("heat_partition").alpha == 0.8
    assert truth.files and all(f.gzip and f.path.endswith(".gz") for f in truth.files)
    assert [w.wagon_id for w in truth.wagons] == ["SGG-0001"]
    again = runner.invoke(app, ["synth", str(out)])
    assert again.exit_code == 1 and "not empty" in again.output
    wrong = runner.invoke(app, ["synth", str(tmp_path / "w"), "--effect", "sensor_lag:tau=1"])
    assert wrong.exit_code == 2 and "unknown parameter" in wrong.output  # a bad --effect: usage


# --------------------------------------------------------------------------------------------
# The block made by the full finite-element model

FE_REFINEMENT = 0.2
"""A coarse mesh for the full model (409 hex20 nodes): affordable over whole days."""


def test_a_fleet_made_by_the_full_model(tmp_path, reduced_model_for, monkeypatch):
    """``solver="full"``: the same operation and readings' randomness as the reduced model's
    fleet of the same seed, a block that differs from it by the model error of a coarse mesh
    only (well below the sensor's noise), and the truth says which model made it. While the
    unit sleeps the full model takes ``ASLEEP_STEP_S`` steps: what is logged is as a 1 Hz
    run gives it."""
    import fleetbrake.synth.block as block

    base = SynthConfig.clean(wagons=1, days=1, seed=6, effects=EffectSet((SensorLag(tau_s=60.0),)))
    reduced = generate_fleet(tmp_path / "rom", base, rom=reduced_model_for)
    full_config = dataclass_replace(base, solver="full", refinement=FE_REFINEMENT)
    full = generate_fleet(tmp_path / "full", full_config)
    assert reduced.rom["solver"] == "rom" and reduced.rom["order"] > 10
    assert full.rom == {"solver": "full", "refinement": FE_REFINEMENT, "nodes": 409}
    assert load_truth(tmp_path / "full").config.solver == "full"
    a, b = reduced.series("SGG-0001"), full.series("SGG-0001")
    np.testing.assert_array_equal(a["brake_pressure_bar"], b["brake_pressure_bar"])
    assert [f.path for f in reduced.files] == [f.path for f in full.files]
    difference = (a["sensor_c"] - b["sensor_c"]).to_numpy()
    assert 1e-3 < float(np.sqrt(np.mean(difference**2))) < 0.05
    assert float(np.abs(difference).max()) < 0.3
    # the sleeping steps: against the full model at 1 Hz throughout
    monkeypatch.setattr(block, "ASLEEP_MIN_S", 10**9)
    every_second = generate_fleet(tmp_path / "full-1hz", full_config).series("SGG-0001")
    awake = b["awake"].to_numpy()
    assert 0.2 < awake.mean() < 0.9
    off = np.abs((b["sensor_c"] - every_second["sensor_c"]).to_numpy())
    assert off[awake].max() < 0.005 and off.max() < 0.01


def test_a_model_of_the_other_solver_is_refused(tmp_path, reduced_model_for):
    config = SynthConfig.clean(wagons=1, days=1, solver="full", refinement=FE_REFINEMENT)
    with pytest.raises(ValueError, match="rom model, but the configuration's solver is 'full'"):
        generate_fleet(tmp_path, config, rom=reduced_model_for)
    with pytest.raises(ValueError, match="solver"):
        SynthConfig(solver="fem")  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# The laws drawn, and an effect outside the vocabulary


def test_drawn_effects_are_the_close_loops_laws_within_their_ranges():
    physical = [cls for cls in EFFECT_ORDER if not cls.fallback]
    for cls in physical:
        text = f"{cls.name}:law={cls.law}"
        draws = [draw_effect(text, seed) for seed in range(40)]
        assert all(type(e) is cls for e in draws), text
        assert draw_effect(text, 3) == draws[3]  # the seed decides
        for key, (low, high) in cls.PARAMETER_RANGES.items():
            values = np.array([e.parameters[key] for e in draws])
            assert np.all((values >= low) & (values <= high)), (text, key)
            # the draws cover the range, every parameter of the law (level, scales, ...)
            assert values.max() - values.min() > 0.6 * (high - low), (text, key)
    # the name alone: the family's first law; another index, another draw
    assert type(draw_effect("friction_speed", 0)) is FrictionSpeed
    assert set(draw_effect("friction_speed", 0).parameters) == {
        "level",
        "speed_scale_kmh",
        "force_scale_kn",
    }
    assert draw_effect("sensor_lag", 0, 0) != draw_effect("sensor_lag", 0, 1)
    with pytest.raises(ValueError, match="not drawn"):
        draw_effect("empirical", 0)
    with pytest.raises(ValueError, match="unknown law"):
        draw_effect("convection_speed:law=cylinder", 0)
    with pytest.raises(ValueError, match="only law"):
        draw_effect("convection_speed:gain=2", 0)


def test_solar_rise_follows_the_hour_of_day():
    hours = np.array([0.0, 5.0, 6.0, 9.0, 12.0, 15.0, 18.0, 21.0, 36.0])
    rise = solar_rise_k(150.0, hours)
    expected = 150.0 / 10.0 * np.array([0, 0, 0, np.sin(np.pi / 4), 1, np.sin(np.pi / 4), 0, 0, 1])
    np.testing.assert_allclose(rise, expected, atol=1e-12)
    config = SynthConfig(solar_heating_w_m2=150.0)
    assert SynthConfig.from_dict(config.to_dict()) == config
    assert SynthConfig.from_dict({"wagons": 2}).solar_heating_w_m2 == 0.0  # written before it
    with pytest.raises(ValueError, match="solar_heating_w_m2"):
        SynthConfig(solar_heating_w_m2=-1.0)


def test_solar_heating_warms_the_block_by_day_only(tmp_path, reduced_model_for):
    base = SynthConfig.clean(wagons=1, days=1, seed=5)
    plain = generate_fleet(tmp_path / "plain", base, rom=reduced_model_for)
    sunny = generate_fleet(
        tmp_path / "sunny",
        dataclass_replace(base, solar_heating_w_m2=100.0),
        rom=reduced_model_for,
    )
    a, b = plain.series("SGG-0001"), sunny.series("SGG-0001")
    # the operation and the logged air are the same; the effects of the vocabulary are none
    np.testing.assert_array_equal(a["brake_pressure_bar"], b["brake_pressure_bar"])
    np.testing.assert_array_equal(a["ambient_c"], b["ambient_c"])
    assert sunny.effects == EffectSet() and sunny.events == plain.events
    assert load_truth(tmp_path / "sunny").config.solar_heating_w_m2 == 100.0
    warmer = (b["seat_c"] - a["seat_c"]).to_numpy()
    hour = np.arange(warmer.size) / 3600.0
    peak_rise = 100.0 / 10.0
    # nothing before sunrise; by the afternoon a good part of the sol-air rise, never more
    assert np.abs(warmer[hour < 6.0]).max() < 1e-3
    afternoon = warmer[(hour >= 13.0) & (hour < 16.0)]
    assert afternoon.min() > 0.3 * peak_rise
    assert warmer.max() < peak_rise + 0.01
    assert 12.0 <= hour[int(np.argmax(warmer))] <= 20.0
    assert "solar heating" in summary(sunny)


def test_command_line_draws_laws_and_adds_the_sun(
    tmp_path, monkeypatch, rom_cache_dir, rom_refinement, default_rom
):
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", os.environ.get("OPENBLAS_NUM_THREADS", "1"))
    runner = CliRunner()
    shown = runner.invoke(app, ["synth", "--help"], terminal_width=200)
    assert "--random-effect" in shown.output and "--solar-heating" in shown.output
    out = tmp_path / "fleet"
    args = ["synth", str(out), "--wagons", "1", "--days", "1", "--seed", "8"]
    args += ["--no-anomalies", "--no-imperfections", "--refinement", str(rom_refinement)]
    args += ["--random-effect", "convection_speed:law=flat_plate", "--solar-heating", "60"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    truth = load_truth(out)
    assert truth.effects == EffectSet((draw_effect("convection_speed:law=flat_plate", 8, 0),))
    assert isinstance(truth.effects.get("convection_speed"), ConvectionFlatPlate)
    assert truth.config.solar_heating_w_m2 == 60.0
    refused = runner.invoke(app, ["synth", str(tmp_path / "e"), "--random-effect", "empirical"])
    assert refused.exit_code == 2 and "not drawn" in refused.output
