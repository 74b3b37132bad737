"""The close loop's fit data (``fleetbrake.closeloop.fitdata``) and its engines: the cached
arrays evaluated with the chain kernel predict what the simulation stage's ``predict_wagon``
predicts, second for second; a close loop on the local engine's workers chooses what one in
this process chooses."""

from __future__ import annotations

import datetime as dt
import shutil
import threading
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pytest

from conftest import TEST_REFINEMENT
from conftest import RunFleet as Fleet
from fleetbrake.closeloop import fitdata
from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.evidence import event_sets
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.loop import run_close_loop
from fleetbrake.closeloop.terms import speed_noise_kmh, with_speed_debiased
from fleetbrake.model.effects import (
    AmbientOffset,
    ConvectionSpeed,
    EffectSet,
    FrictionTemperature,
    HolderConduction,
    SensorLag,
)
from fleetbrake.simulation.predictions import (
    Revision,
    current_revision,
    load_wagon,
    model_for,
    predict_wagon,
    stored_wagons,
)
from fleetbrake.simulation.series import running_median
from fleetbrake.warehouse.connection import open_warehouse

START = dt.date(2024, 3, 4)
HOLDOUT = START + dt.timedelta(days=1)


@pytest.fixture(scope="module")
def fleet(convection_fleet: Fleet) -> Fleet:
    """``conftest.convection_fleet``: the close loop's small fleet, run."""
    return convection_fleet


EFFECT_SETS = [
    EffectSet(),
    EffectSet((ConvectionSpeed(gain=2.3, exponent=0.75),)),
    EffectSet((SensorLag(tau_s=40.0),)),
    EffectSet((HolderConduction(h_holder_extra_w_m2k=80.0), AmbientOffset(offset_k=1.5))),
    EffectSet((ConvectionSpeed(gain=1.5, exponent=0.9), SensorLag(tau_s=25.0))),
]


def fit_events(fleet: Fleet) -> tuple[Revision, pl.DataFrame, dict[str, Any]]:
    """The fleet's current revision, the close loop's fit events and their wagons loaded as
    the close loop loads them."""
    config = CloseLoopConfig(HOLDOUT, simulation=fleet.simulation)
    with open_warehouse(fleet.db) as wh:
        wagons = stored_wagons(wh)
        base = current_revision(wh, refinement=TEST_REFINEMENT)
        fit, _, _ = event_sets(wh, base.name, config)
        loaded = {w: load_wagon(wh, wagons[w], fleet.simulation) for w in fit["wagon_id"]}
    return base, fit, loaded


@pytest.mark.usefixtures("rom_env")
def test_fit_data_predicts_what_predict_wagon_predicts(fleet: Fleet) -> None:
    """For the fit events, the cached arrays run through the chain kernel give the
    prediction ``predict_wagon`` gives at every second with a measurement (to 1e-9 K), for
    effects acting on the heat input, the convection, the air and the sensor; a
    state-dependent effect (fixed point over the whole chain instead of run by run) to the
    fixed point's tolerance."""
    base, fit, loaded = fit_events(fleet)
    assert fit.height > 10 and len(loaded) == 2
    data = FitData.build(loaded, fit, fleet.simulation, base)
    assert all(w.batched for w in data.wagons)  # the kernel path, not the fallback
    # the blocks are wagon-days: each holds one wagon's seconds of one day
    for block in np.unique(data.blocks):
        days = data.time_utc[data.blocks == block].astype("datetime64[D]")
        assert np.unique(days).size == 1
    calls = fitdata.kernel_calls()
    for effects in [*EFFECT_SETS, EffectSet((FrictionTemperature(fade_per_k=1.5e-3),))]:
        rev = Revision("candidate", effects, base.solver, base.refinement)
        frames = [
            predict_wagon(
                loaded[w.wagon.wagon_id],
                model_for(w.wagon, base.solver, base.refinement),
                rev,
                fleet.simulation,
                event_ids=w.event_ids,
                timeline=False,
            ).predictions
            for w in data.wagons
        ]
        reference = pl.concat(frames).filter(pl.col("measured_sensor_c").is_not_null())
        ours = data.frame(effects)
        assert ours.height == reference.height == data.seconds
        joined = ours.join(
            reference.select("event_id", "time_utc", reference_c="predicted_sensor_c"),
            on=["event_id", "time_utc"],
            how="left",
        )
        difference = (joined["predicted_sensor_c"] - joined["reference_c"]).abs()
        assert difference.null_count() == 0
        tolerance = 5e-3 if effects.state_dependent else 1e-9
        assert float(difference.max()) <= tolerance, (str(effects), difference.max())
        # the drivers are the prediction rows' own
        for name in ("speed_kmh", "brake_pressure_bar", "ambient_c"):
            np.testing.assert_allclose(
                ours[name].to_numpy(),
                ours.join(reference, on=["event_id", "time_utc"])[f"{name}_right"].to_numpy(),
            )
    # one kernel call per span per evaluation (more for the fixed point)
    assert fitdata.kernel_calls() - calls >= len(EFFECT_SETS) * len(data.wagons)


@pytest.mark.usefixtures("rom_env")
def test_fit_data_on_threads_predicts_bit_for_bit_what_one_thread_does(
    fleet: Fleet, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Inside ``fitdata.parallel(2)`` an evaluation runs its spans on two threads (the chain
    kernel releases the GIL): the same predictions, bit for bit, as one thread, a
    state-dependent effect's warm-started fixed points included (each span's effect sets in
    order on one thread), and the kernel calls counted alike."""
    base, fit, loaded = fit_events(fleet)
    serial = FitData.build(loaded, fit, fleet.simulation, base)
    threaded = FitData.build(loaded, fit, fleet.simulation, base)
    assert sum(len(w.spans) for w in threaded.wagons) >= 2
    fade = [EffectSet((FrictionTemperature(fade_per_k=f),)) for f in (1.5e-3, 1.6e-3)]
    sets = [*EFFECT_SETS, *fade]
    calls = fitdata.kernel_calls()
    expected = serial.predict_many(sets) + serial.predict_many(fade)
    serial_calls = fitdata.kernel_calls() - calls
    threads: set[str] = set()
    run_span = FitData._run_span

    def recorded(self: FitData, *args: Any) -> Any:
        threads.add(threading.current_thread().name)
        return run_span(self, *args)

    monkeypatch.setattr(FitData, "_run_span", recorded)
    calls = fitdata.kernel_calls()
    with fitdata.parallel(2):
        got = threaded.predict_many(sets) + threaded.predict_many(fade)
    assert fitdata.kernel_calls() - calls == serial_calls
    assert len(threads) == 2 and threading.current_thread().name not in threads
    for a, b in zip(expected, got, strict=True):
        np.testing.assert_array_equal(a, b)
    # outside it, one thread again
    threads.clear()
    threaded.predict(EFFECT_SETS[1])
    assert threads == {threading.current_thread().name}


@pytest.fixture
def rom_env(monkeypatch: pytest.MonkeyPatch, rom_cache_dir: Path) -> None:
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))


@pytest.mark.usefixtures("rom_env")
def test_local_and_inline_engines_close_the_loop_alike(fleet: Fleet, tmp_path: Path) -> None:
    """The candidates fitted on two worker processes (the data read by each once, from the
    file the run writes) give the revision, effect and parameters of a close loop run in
    this process."""
    config = CloseLoopConfig(
        HOLDOUT,
        simulation=fleet.simulation,
        candidates=("convection_speed", "sensor_lag", "ambient_offset"),
        max_nfev=6,
        reflag=False,
    )
    reports = {}
    for engine in ("inline", "local"):
        db = tmp_path / f"{engine}.duckdb"
        shutil.copy(fleet.db, db)
        reports[engine] = run_close_loop(
            db, HOLDOUT, tmp_path / f"{engine}.json", config=config, engine=engine, workers=2
        )
    inline, local = reports["inline"], reports["local"]
    assert inline["effect"] == local["effect"] == "convection_speed", inline["candidates"]
    assert inline["new_revision"] == local["new_revision"]
    assert inline["parameters"].keys() == local["parameters"].keys()
    for name, value in inline["parameters"].items():
        assert local["parameters"][name] == pytest.approx(value, rel=1e-6), name
    assert [c["effect"] for c in inline["candidates"]] == [c["effect"] for c in local["candidates"]]
    assert inline["cost"]["candidates_fitted"] == local["cost"]["candidates_fitted"]
    assert inline["cost"]["kernel_calls"] == local["cost"]["kernel_calls"] > 0
    # the evaluations per phase are counted where they run (workers' fits from their results)
    assert inline["cost"]["evaluations"] == local["cost"]["evaluations"]
    assert local["cost"]["evaluations"]["screen"] >= 3 * 2  # 3 candidates, start + Jacobian
    # the Markdown report and its plots (drawn on a worker by the local engine) for both
    for engine in ("inline", "local"):
        text = (tmp_path / f"{engine}.md").read_text(encoding="utf-8")
        for plot in ("by-wagon", "by-phase"):
            assert f"]({engine}-{plot}.png)" in text
            assert (tmp_path / f"{engine}-{plot}.png").read_bytes().startswith(b"\x89PNG")


def report_differences(
    a: Any, b: Any, rel: float = 1e-12, path: str = "", skip: tuple[str, ...] = ("cost/seconds",)
) -> list[str]:
    """Where two close-loop reports differ: every number to ``rel`` (relative, 1e-300 K
    absolute), every other value exactly, the same keys and lengths; the paths in ``skip``
    (the seconds spent) not compared."""
    if path.lstrip("/") in skip:
        return []
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{path}: keys {sorted(a.keys() ^ b.keys())}"]
        return [d for k in a for d in report_differences(a[k], b[k], rel, f"{path}/{k}", skip)]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} against {len(b)} items"]
        return [
            d
            for i, (u, v) in enumerate(zip(a, b, strict=True))
            for d in report_differences(u, v, rel, f"{path}[{i}]", skip)
        ]
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool):
        same = a == b or abs(a - b) <= rel * max(abs(a), abs(b), 1e-300)
        return [] if same else [f"{path}: {a!r} against {b!r}"]
    return [] if a == b else [f"{path}: {a!r} against {b!r}"]


def test_report_differences_sees_a_change_in_any_number() -> None:
    a = {"x": [1.0, {"y": 0.5}], "cost": {"seconds": {"total_s": 1.0}}, "s": "a"}
    assert report_differences(a, a) == []
    assert report_differences(a, {**a, "cost": {"seconds": {"total_s": 9.0}}}) == []
    assert report_differences(a, {**a, "x": [1.0, {"y": 0.5 + 1e-9}]}) == [
        "/x[1]/y: 0.5 against 0.500000001"
    ]
    assert report_differences(a, {**a, "s": "b"}) == ["/s: 'a' against 'b'"]
    assert report_differences(a, {**a, "x": [1.0]}) == ["/x: 2 against 1 items"]


@pytest.mark.usefixtures("rom_env")
def test_the_same_fleet_gives_the_same_report(fleet: Fleet, tmp_path: Path) -> None:
    """Two close loops on copies of one database (the default method: screening, outliers,
    choice, intervals with the numerical and input terms, revision, re-flagging) give the same
    report, every number to 1e-12 (only the seconds spent differ): nothing in the loop
    depends on an unseeded draw, a set's order, or the order rows come back in."""
    config = CloseLoopConfig(
        HOLDOUT,
        simulation=fleet.simulation,
        candidates=("convection_speed", "sensor_lag", "ambient_offset"),
    )
    reports = []
    for run in ("first", "second"):
        db = tmp_path / f"{run}.duckdb"
        shutil.copy(fleet.db, db)
        reports.append(run_close_loop(db, HOLDOUT, tmp_path / f"{run}.json", config=config))
    first, second = reports
    assert first["new_revision"] is not None, first.get("evidence")
    assert "input" in first["interval_methods"], first["interval_methods"].keys()
    assert report_differences(first, second) == []


def test_the_speed_noise_is_read_from_the_logged_speed_and_its_bias_taken_out(
    fleet: Fleet,
) -> None:
    """The input term's two pieces on a generated fleet (GPS speed ``|v + e|``, noise 0.3
    km/h, ``SynthConfig.speed_noise_kmh``): the noise estimated from the logged speed where
    the wagon moves, within 10 %; the speed debiased, ``sqrt(max(v^2 - noise^2, 0))``: 0
    where the wagon stands (it logs about its noise there), unchanged to 1e-3 at running
    speeds, the driving running median debiased alike."""
    _, _, loaded = fit_events(fleet)
    noise = speed_noise_kmh(loaded)
    assert noise == pytest.approx(0.3, rel=0.1)
    debiased = with_speed_debiased(loaded, noise)
    width = fleet.simulation.chain.speed_median_samples
    for wagon_id, data in loaded.items():
        for before, after in zip(data.spans, debiased[wagon_id].spans, strict=True):
            raw = np.isfinite(before.speed_raw_kmh)
            assert np.array_equal(raw, np.isfinite(after.speed_raw_kmh))
            v = before.speed_raw_kmh[raw]
            assert np.all(after.speed_raw_kmh[raw][v <= noise] == 0.0)
            running = v > 30.0
            np.testing.assert_allclose(after.speed_raw_kmh[raw][running], v[running], rtol=1e-4)
            np.testing.assert_allclose(
                running_median(after.speed_kmh, width),
                np.sqrt(np.maximum(running_median(before.speed_kmh, width) ** 2 - noise**2, 0)),
                atol=1e-12,
            )
        assert data.spans[0].speed_kmh is not debiased[wagon_id].spans[0].speed_kmh  # a copy


WALL_CLOCK_COLUMNS = {"created_utc", "detected_utc", "updated_utc", "simulated_utc", "applied_utc"}
"""Columns that say when a row was written, not what it holds."""


def stored_tables(db: Path) -> dict[str, pl.DataFrame]:
    """Every table of a warehouse, less the wall-clock columns, in a fixed row order."""
    import duckdb

    con = duckdb.connect(str(db), read_only=True)
    try:
        out = {}
        tables = con.sql(
            "SELECT table_name FROM information_schema.tables WHERE table_type = 'BASE TABLE'"
        ).fetchall()
        for (table,) in tables:
            frame = con.sql(f"SELECT * FROM {table}").pl()
            frame = frame.drop([c for c in frame.columns if c in WALL_CLOCK_COLUMNS])
            out[table] = frame.sort(frame.columns, nulls_last=True)
        return out
    finally:
        con.close()


@pytest.mark.usefixtures("rom_env")
def test_the_interval_terms_beside_the_reflag_refit_change_nothing(
    fleet: Fleet, tmp_path: Path
) -> None:
    """On the local engine, the interval terms computed while the revision is re-flagged
    and refitted (``overlap``, the default) give the report and every stored value of the
    close loop that computes them after the refit (``overlap=False``), every number to 1e-12
    (only the seconds spent differ); the terms computed ahead were the ones used."""
    import dataclasses

    config = CloseLoopConfig(
        HOLDOUT,
        simulation=fleet.simulation,
        candidates=("convection_speed", "sensor_lag", "ambient_offset"),
    )
    reports, tables = {}, {}
    for overlap in (False, True):
        db = tmp_path / f"overlap-{overlap}.duckdb"
        shutil.copy(fleet.db, db)
        reports[overlap] = run_close_loop(
            db,
            HOLDOUT,
            tmp_path / f"overlap-{overlap}.json",
            config=dataclasses.replace(config, overlap=overlap),
            engine="local",
            workers=2,
        )
        tables[overlap] = stored_tables(db)
    after, before = reports[True], reports[False]
    assert before["new_revision"] is not None, before.get("evidence")
    methods = before["interval_methods"]
    assert "input" in methods and "numerical" in methods, methods.keys()
    assert "terms_wait_s" in after["cost"]["seconds"]
    assert "terms_wait_s" not in before["cost"]["seconds"]
    assert report_differences(before, after) == []
    assert tables[True].keys() == tables[False].keys()
    assert tables[True]["estimator_noise"].height == 1
    for name, frame in tables[False].items():
        assert frame.equals(tables[True][name]), name
