"""Tests of fleetbrake.simulation: the one chain/re-anchor algorithm on hand-made series, and the
simulation stage on a small generated fleet: what it stores, that it is incremental, that the
flags read it without simulating, and that the close loop's candidates are simulated exactly
as the stage stores predictions."""

from __future__ import annotations

import dataclasses
import datetime as dt
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pytest

from fleetbrake.errors import ConfigError, UnknownKeyError
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import (
    AmbientOffset,
    ConvectionSpeed,
    EffectSet,
    HeatPartition,
    HolderConduction,
    SensorLag,
)
from fleetbrake.model.timeline import simulate_timeline
from fleetbrake.simulation.chains import (
    ChainParams,
    ChainParamsError,
    event_windows,
    segment_bounds,
    simulate_span,
    trusted_readings,
)
from fleetbrake.simulation.series import WagonSeries

T0 = dt.datetime(2024, 3, 4, 8, 0, 0)


def make_series(
    measured: np.ndarray,
    *,
    pressure: np.ndarray | float = 0.0,
    speed: np.ndarray | float = 60.0,
    events: list[tuple[str, int, int]] = (),  # type: ignore[assignment]
    drop: np.ndarray | None = None,
    fault: np.ndarray | None = None,
) -> WagonSeries:
    """A 1 Hz series from ``T0``; rows where ``drop`` is set are not written at all."""
    n = measured.size
    frame = pl.DataFrame(
        {
            "time_utc": pl.Series([T0 + dt.timedelta(seconds=k) for k in range(n)]),
            "speed_kmh": np.broadcast_to(np.asarray(speed, dtype=float), n).copy(),
            "brake_pressure_bar": np.broadcast_to(np.asarray(pressure, dtype=float), n).copy(),
            "block_temp_c": measured,
            "block_temp_fault": np.zeros(n, dtype=bool) if fault is None else fault,
            "ambient_temp_c": np.full(n, 8.0),
        }
    ).with_columns(pl.col("block_temp_c").fill_nan(None))
    if drop is not None:
        frame = frame.filter(pl.Series(~drop))
    event_frame = pl.DataFrame(
        {
            "event_id": [e[0] for e in events],
            "start_utc": [T0 + dt.timedelta(seconds=e[1]) for e in events],
            "end_utc": [T0 + dt.timedelta(seconds=e[2]) for e in events],
        },
        schema={
            "event_id": pl.String,
            "start_utc": pl.Datetime("us"),
            "end_utc": pl.Datetime("us"),
        },
    )
    return WagonSeries.from_frame("TEST-0001", frame, ambient_default_c=8.0, events=event_frame)


# --------------------------------------------------------------------------------------------
# The parameters


def test_chain_params_name_a_bad_key() -> None:
    with pytest.raises(ChainParamsError, match=r"ChainParams: anchor_s must be > 0") as caught:
        ChainParams(anchor_s=0)
    assert isinstance(caught.value, ConfigError) and caught.value.exit_code == 2
    with pytest.raises(ChainParamsError, match="anchor_min_readings must not exceed anchor_s"):
        ChainParams(anchor_s=4)
    with pytest.raises(ChainParamsError, match="window_s must be an integer"):
        ChainParams(window_s=600.5)  # type: ignore[arg-type]


def test_the_gap_that_cuts_a_simulation_is_the_one_that_ends_an_event() -> None:
    """One gap rule for events and simulation: a 12 s hole (too short to end an event) does
    not cut an event's window, nor start a ``gap`` segment; a 20 s one does both."""
    from fleetbrake.ingest.config import EventConfig

    assert ChainParams().max_gap_s == EventConfig().max_gap_s
    n = 1500
    pressure = np.zeros(n)
    pressure[100:160] = 1.0
    for hole_s, cut in ((12, False), (20, True)):
        drop = np.zeros(n, dtype=bool)
        drop[300 : 300 + hole_s] = True
        series = make_series(
            np.full(n, 20.0), pressure=pressure, events=[("E1", 100, 160)], drop=drop
        )
        (window,) = event_windows(series, ChainParams())
        assert window.stop == (299 if cut else 160 + 600), hole_s
        _, kinds = segment_bounds(series, ChainParams())
        assert ("gap" in kinds) == cut, hole_s


def test_spans_are_cut_at_long_gaps_whatever_the_order_of_the_rows() -> None:
    """``spans_from_frame`` cuts the samples where a gap exceeds ``bridge_max_s`` (rows as the
    warehouse hands them, in time order, are cut as they are; shuffled rows with a repeated
    time are sorted, the first of each time kept, and give the same spans)."""
    n = 900
    times = [T0 + dt.timedelta(seconds=k + (400 if k >= 500 else 0)) for k in range(n)]
    frame = pl.DataFrame(
        {
            "time_utc": pl.Series(times, dtype=pl.Datetime("us")),
            "speed_kmh": np.full(n, 50.0),
            "brake_pressure_bar": np.zeros(n),
            "block_temp_c": np.linspace(20.0, 30.0, n),
            "ambient_temp_c": np.full(n, 8.0),
        }
    )
    spans = WagonSeries.spans_from_frame("W1", frame, ambient_default_c=8.0, bridge_max_s=300.0)
    assert [(s.t0, s.n) for s in spans] == [(times[0], 500), (times[500], 400)]
    shuffled = pl.concat([frame[::-1], frame[10:11].with_columns(block_temp_c=pl.lit(99.0))])
    again = WagonSeries.spans_from_frame("W1", shuffled, ambient_default_c=8.0, bridge_max_s=300.0)
    assert [(s.t0, s.n) for s in again] == [(s.t0, s.n) for s in spans]
    for a, b in zip(spans, again, strict=True):
        assert np.array_equal(a.measured_c, b.measured_c)
    one = WagonSeries.spans_from_frame("W1", frame, ambient_default_c=8.0, bridge_max_s=401.0)
    assert [(s.t0, s.n) for s in one] == [(times[0], 900 + 400)]  # a 401 s gap is bridged


def test_readings_a_broken_or_frozen_sensor_gave_never_anchor() -> None:
    n = 3000
    rng = np.random.default_rng(0)
    measured = np.round(20.0 + rng.normal(0.0, 0.1, n), 2)
    measured[1000:1200] = 21.37  # frozen for 200 s
    fault = np.zeros(n, dtype=bool)
    fault[2000:2010] = fault[2300:2310] = True  # an intermittent circuit
    measured[fault] = np.nan
    trusted = trusted_readings(make_series(measured, fault=fault), ChainParams())
    assert np.isnan(trusted[1000:1200]).all() and np.isnan(trusted[2000:2310]).all()
    assert np.isfinite(trusted[:1000]).all() and np.isfinite(trusted[2310:]).all()


# --------------------------------------------------------------------------------------------
# The algorithm


@pytest.fixture(scope="module")
def rom(reduced_model_for: Callable[..., Any]) -> Any:
    return reduced_model_for(WagonConfig(wagon_id="TEST-0001"))


def test_an_event_window_is_the_chain_carried_on_from_its_anchored_activation(rom: Any) -> None:
    """The timeline and the event's window share the braking segment exactly; after it the
    timeline is re-anchored at every quiet window, the window is not (it keeps the model's
    error for the braking)."""
    wagon = WagonConfig(wagon_id="TEST-0001")
    n = 2400
    pressure = np.zeros(n)
    pressure[600:660] = 1.5
    speed = np.clip(80.0 - np.clip(np.arange(n) - 600, 0, 60) * 1.0, 0.0, None)
    # the data: a block heated more than the declared model says (a larger share of the heat)
    truth = simulate_timeline(
        rom,
        wagon,
        dt_s=1.0,
        p_bar=pressure,
        speed_kmh=speed,
        ambient_c=8.0,
        initial_c=30.0,
        effects=EffectSet((HeatPartition(alpha=0.6),)),
    )
    noise = np.random.default_rng(1).normal(0.0, 0.05, n)  # noise-free readings look frozen
    measured = np.round(truth.sensor_c + noise, 2)
    series = make_series(measured, pressure=pressure, speed=speed, events=[("E1", 600, 660)])
    chain = ChainParams()
    result = simulate_span(series, wagon, rom, EffectSet(), chain)
    (window,) = result.windows
    assert (window.start, window.stop) == (600, 660 + chain.event_after_release_s)
    assert window.sensor_c is not None
    braking = next(s for s in result.segments if s.kind == "braking")
    assert (braking.start, braking.stop, braking.event_id, braking.anchor) == (
        600,
        660 + chain.quiet_after_release_s,
        "E1",
        "before",
    )
    inside = slice(0, braking.stop - 600)  # [start, stop): the next segment starts at stop
    np.testing.assert_allclose(
        window.sensor_c[inside], result.sensor_c[600 : braking.stop], rtol=0, atol=1e-12
    )
    after = [s for s in result.segments if s.start >= braking.stop]
    assert after and all(s.kind == "quiet" and s.anchor == "before" for s in after)
    # the window misses the extra heat the whole way; the timeline is back on the data after
    # each anchor
    k = after[0].start + chain.anchor_s
    window_error = truth.sensor_c[k] - window.sensor_c[k - 600]
    timeline_error = truth.sensor_c[k] - result.sensor_c[k]
    assert window_error > 1.0 and abs(timeline_error) < 0.2 * window_error


# --------------------------------------------------------------------------------------------
# The stage on a generated fleet


@dataclasses.dataclass
class Fleet:
    path: Path
    db: Path
    registry: Any
    config: Any


@pytest.fixture(scope="module")
def fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., Any],
    rom_cache_dir: Path,
) -> Iterator[Fleet]:
    """Two wagons (plus the generator's unregistered one) x 1 day with anomalies, ingested and
    events detected; the simulation stage not yet run."""
    from conftest import TEST_REFINEMENT
    from fleetbrake.ingest.files import load_fleet_registry, run_ingest
    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        out = tmp_path_factory.mktemp("simfleet")
        generate_fleet(out / "fleet", SynthConfig(wagons=2, days=1, seed=1), rom=reduced_model_for)
        run_ingest(out / "fleet", out / "fleet.duckdb", progress=False)
        yield Fleet(
            out / "fleet",
            out / "fleet.duckdb",
            load_fleet_registry(out / "fleet"),
            SimulationConfig(refinement=TEST_REFINEMENT),
        )


def _counts(wh: Any, revision: str = "declared") -> dict[str, int]:
    return {
        table: wh.con.execute(
            f"SELECT count(*) FROM {table} WHERE model_revision = $r", {"r": revision}
        ).fetchall()[0][0]
        for table in ("predictions", "timeline", "timeline_segments", "simulated_spans")
    }


def test_the_stage_stores_timeline_and_predictions_once(fleet: Fleet) -> None:
    from fleetbrake.simulation.predictions import current_revision, simulate_events
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db) as wh:
        first = simulate_events(
            wh,
            fleet.registry,
            current_revision(wh, refinement=fleet.config.refinement),
            fleet.config,
        )
        registered = sorted(fleet.registry.wagons)
        with_samples = [
            w
            for (w,) in wh.con.execute("SELECT DISTINCT wagon_id FROM samples").fetchall()
            if w in fleet.registry.wagons
        ]
        assert sorted(first.wagons_simulated) == sorted(with_samples) and with_samples
        assert first.events_simulated > 10 and first.timeline_rows > first.prediction_rows
        assert any("has no valid registry entry" in s for s in first.skipped) or set(
            with_samples
        ) == set(registered)
        counts = _counts(wh)
        # one timeline row per logged second of every simulated wagon
        ((logged,),) = wh.con.execute(
            "SELECT count(DISTINCT (wagon_id, time_utc)) FROM samples "
            "WHERE list_contains($w, wagon_id)",
            {"w": with_samples},
        ).fetchall()
        assert counts["timeline"] == logged
        # every event window starts at its braking segment, anchored there
        ((unanchored,),) = wh.con.execute(
            "SELECT count(*) FROM (SELECT event_id, min(time_utc) AS t0 FROM predictions "
            "GROUP BY event_id) p LEFT JOIN timeline_segments s "
            "ON s.event_id = p.event_id AND s.start_utc = p.t0 AND s.kind = 'braking' "
            "WHERE s.event_id IS NULL"
        ).fetchall()
        assert unanchored == 0
        # again: nothing to do, nothing changed
        again = simulate_events(
            wh,
            fleet.registry,
            current_revision(wh, refinement=fleet.config.refinement),
            fleet.config,
        )
        assert (again.wagons_simulated, again.events_simulated) == ([], 0)
        assert _counts(wh) == counts


def test_a_wagon_whose_data_changed_is_simulated_again_alone(fleet: Fleet) -> None:
    from fleetbrake.flags import raise_flags
    from fleetbrake.ingest.spans import update_spans
    from fleetbrake.simulation.predictions import current_revision, simulate_events
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db) as wh:
        rev = current_revision(wh, refinement=fleet.config.refinement)
        simulate_events(wh, fleet.registry, rev, fleet.config)
        first, second = sorted(fleet.registry.wagons)[:2]
        ((last,),) = wh.con.execute(
            "SELECT max(time_utc) FROM samples WHERE wagon_id = $w", {"w": second}
        ).fetchall()
        cut = last - dt.timedelta(hours=1)
        wh.con.execute(
            "DELETE FROM samples WHERE wagon_id = $w AND time_utc > $t", {"w": second, "t": cut}
        )
        # the flags see that its timeline does not hold its samples and do not use it
        report = raise_flags(wh, fleet.registry, rev.name, wagons=[second])
        assert any(f"wagon {second}: its data changed" in note for note in report.notes)
        # as a replaced file does: its row changed, the spans cut again where it lies
        wh.con.execute(
            "UPDATE files SET sha256 = 'replaced', last_utc = $t, rows = rows - 1 "
            "WHERE file_id = (SELECT max(file_id) FROM samples WHERE wagon_id = $w)",
            {"w": second, "t": cut},
        )
        update_spans(wh)
        report = raise_flags(wh, fleet.registry, rev.name, wagons=[second])
        assert any(f"wagon {second}: its data changed" in note for note in report.notes)
        again = simulate_events(wh, fleet.registry, rev, fleet.config)
        assert again.wagons_simulated == [second]
        ((after,),) = wh.con.execute(
            "SELECT max(time_utc) FROM timeline WHERE wagon_id = $w", {"w": second}
        ).fetchall()
        assert after <= cut
        report = raise_flags(wh, fleet.registry, rev.name, wagons=[first, second])
        assert not any("changed" in note or "simulated" in note for note in report.notes)


def test_the_flags_read_the_timeline_and_never_simulate(
    fleet: Fleet, monkeypatch: pytest.MonkeyPatch
) -> None:
    import fleetbrake.model.timeline
    import fleetbrake.simulation.chains
    from fleetbrake.flags import raise_flags
    from fleetbrake.simulation.predictions import current_revision, simulate_events
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db) as wh:
        rev = current_revision(wh, refinement=fleet.config.refinement)
        simulate_events(wh, fleet.registry, rev, fleet.config)
        expected = raise_flags(wh, fleet.registry, rev.name)

        def refuse(*args: object, **kwargs: object) -> None:
            raise AssertionError("the flags simulated")

        monkeypatch.setattr(fleetbrake.model.timeline, "simulate_timeline", refuse)
        monkeypatch.setattr(fleetbrake.simulation.chains, "simulate_timeline", refuse)
        report = raise_flags(wh, fleet.registry, rev.name)
        assert [f.flag_id for f in report.flags] == [f.flag_id for f in expected.flags]
        assert report.flags, "the fleet has anomalies: some flags expected"
        assert not any("only its readings" in n for n in report.notes if "registry" not in n)
        with pytest.raises(UnknownKeyError, match=r"no model revision 'nope'"):
            raise_flags(wh, fleet.registry, "nope")


def test_close_loop_candidates_are_simulated_as_the_stage_stores_predictions(
    fleet: Fleet,
) -> None:
    """A candidate with the revision's own effects predicts what the stage stored, to 1e-9 K,
    for any subset of events (each span simulated from its start, up to the last one)."""
    from fleetbrake.simulation.predictions import (
        current_revision,
        load_wagon,
        model_for,
        predict_wagon,
        simulate_events,
    )
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db) as wh:
        rev = current_revision(wh, refinement=fleet.config.refinement)
        simulate_events(wh, fleet.registry, rev, fleet.config)
        wagon = fleet.registry.wagons[sorted(fleet.registry.wagons)[0]]
        stored = wh.con.sql(
            "SELECT * FROM predictions WHERE wagon_id = $w AND model_revision = $r "
            "ORDER BY event_id, time_utc",
            params={"w": wagon.wagon_id, "r": rev.name},
        ).pl()
        ids = stored["event_id"].unique(maintain_order=True).to_list()
        some = ids[1 : len(ids) // 2 : 3]
        data = load_wagon(wh, wagon, fleet.config)
        model = model_for(wagon, rev.solver, fleet.config.refinement)
        got = predict_wagon(data, model, rev, fleet.config, event_ids=some, timeline=False)
        assert got.timeline.height == 0 and sorted(set(got.predictions["event_id"])) == some
        want = stored.filter(pl.col("event_id").is_in(some))
        got_frame = got.predictions.sort("event_id", "time_utc")
        assert got_frame["time_utc"].to_list() == want["time_utc"].to_list()
        np.testing.assert_allclose(
            got_frame["predicted_sensor_c"].to_numpy(),
            want["predicted_sensor_c"].to_numpy(),
            rtol=0,
            atol=1e-9,
        )


def test_reflag_simulates_the_new_revision_then_judges_from_it(fleet: Fleet) -> None:
    from fleetbrake.closeloop.revision import reflag
    from fleetbrake.simulation.predictions import (
        Revision,
        current_revision,
        store_registry,
        stored_wagons,
    )
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db) as wh:
        base = current_revision(wh, refinement=fleet.config.refinement)
        store_registry(wh, fleet.registry)
        effects = EffectSet((HeatPartition(alpha=0.8),))
        wh.con.execute(
            "INSERT INTO model_revisions VALUES ('r1-test', $p, 'heat_partition', $j, NULL, "
            "NULL, 'rom', FALSE, $t, $r)",
            {
                "p": base.name,
                "j": f'{{"effects": {effects.to_json()}}}',
                "t": T0,
                "r": base.refinement,
            },
        )
        new = Revision("r1-test", effects, base.solver, base.refinement)
        wh.con.execute("DELETE FROM flags")
        reflag(wh, stored_wagons(wh), new, fleet.config)
        counts = _counts(wh, "r1-test")
        assert counts["timeline"] > 0 and counts["predictions"] > 0
        ((flags,),) = wh.con.execute("SELECT count(*) FROM flags").fetchall()
        assert flags > 0


# --------------------------------------------------------------------------------------------
# The batched path (one kernel call per span) against the per-segment reference


@pytest.mark.parametrize(
    "effects",
    [
        EffectSet(),
        EffectSet((SensorLag(tau_s=40.0),)),
        EffectSet(
            (
                HeatPartition(alpha=0.8),
                ConvectionSpeed(gain=2.0, exponent=0.8),
                HolderConduction(h_holder_extra_w_m2k=60.0),
                AmbientOffset(offset_k=3.0),
                SensorLag(tau_s=30.0),
            )
        ),
    ],
    ids=["declared", "sensor_lag", "five_effects"],
)
def test_the_batched_chain_predicts_what_the_per_segment_reference_does(
    fleet: Fleet, effects: EffectSet
) -> None:
    """Every wagon of a generated fleet (gaps, faults, frozen readings and all): the event
    windows, the timeline and the segments' anchoring of the one-call kernel equal the
    segment-by-segment reference's to 1e-9 K, for any subset of events too."""
    from fleetbrake.simulation.predictions import Revision, load_wagon, model_for, predict_wagon
    from fleetbrake.warehouse.connection import open_warehouse

    rev = Revision("batched-test", effects)
    numbers = [
        "predicted_sensor_c",
        "predicted_contact_mean_c",
        "predicted_contact_max_c",
        "flux_w_m2",
    ]
    compared = 0
    with open_warehouse(fleet.db) as wh:
        for wagon in fleet.registry.wagons.values():
            data = load_wagon(wh, wagon, fleet.config)
            if not data.spans:
                continue
            model = model_for(wagon, rev.solver, fleet.config.refinement)
            ids = data.event_ids
            for event_ids, timeline in ((None, True), (ids[1 : len(ids) // 2 : 3], False)):
                got = predict_wagon(
                    data, model, rev, fleet.config, event_ids=event_ids, timeline=timeline
                )
                want = predict_wagon(
                    data,
                    model,
                    rev,
                    fleet.config,
                    event_ids=event_ids,
                    timeline=timeline,
                    reference=True,
                )
                assert got.skipped == want.skipped and got.events == want.events
                assert got.predictions.drop(numbers).equals(want.predictions.drop(numbers))
                for name in numbers:
                    np.testing.assert_allclose(
                        got.predictions[name].to_numpy(),
                        want.predictions[name].to_numpy(),
                        rtol=0,
                        atol=1e-9,
                        err_msg=f"{wagon.wagon_id} {name}",
                    )
                assert got.timeline["time_utc"].equals(want.timeline["time_utc"])
                for name in numbers[:3]:
                    np.testing.assert_allclose(
                        got.timeline[name].to_numpy(),
                        want.timeline[name].to_numpy(),
                        rtol=0,
                        atol=1e-9,
                        err_msg=f"{wagon.wagon_id} timeline {name}",
                    )
                anchoring = ["shift_k", "reference_c"]
                assert got.segments.drop(anchoring).equals(want.segments.drop(anchoring))
                for name in anchoring:
                    np.testing.assert_allclose(
                        got.segments[name].to_numpy(),
                        want.segments[name].to_numpy(),
                        rtol=0,
                        atol=1e-9,
                    )
                compared += got.events
    assert compared > 20


def test_the_stage_runs_its_wagons_on_an_engine_and_stores_the_reference_rows(
    fleet: Fleet, rom_cache_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``simulate_events(engine=...)``: each wagon's pure function run in a worker process
    (its partition read and its rows written by the parent), the rows those of the
    reference path."""
    from fleetbrake.engine import LocalEngine
    from fleetbrake.simulation.predictions import current_revision, simulate_events
    from fleetbrake.warehouse.connection import open_warehouse

    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))  # the workers' model cache

    def stored(wh: Any) -> pl.DataFrame:
        return wh.con.sql(
            "SELECT event_id, time_utc, predicted_sensor_c FROM predictions "
            "WHERE model_revision = 'declared' ORDER BY event_id, time_utc"
        ).pl()

    with open_warehouse(fleet.db) as wh:
        rev = current_revision(wh, refinement=fleet.config.refinement)
        wagons = sorted(fleet.registry.wagons)
        want = simulate_events(
            wh, fleet.registry, rev, fleet.config, wagons=wagons, reference=True, progress=False
        )
        reference = stored(wh)
        with LocalEngine(1) as engine:
            got = simulate_events(
                wh, fleet.registry, rev, fleet.config, wagons=wagons, engine=engine, progress=False
            )
        batched = stored(wh)
    assert got.wagons_simulated == want.wagons_simulated and got.events_simulated > 10
    assert (got.prediction_rows, got.timeline_rows) == (want.prediction_rows, want.timeline_rows)
    assert batched.drop("predicted_sensor_c").equals(reference.drop("predicted_sensor_c"))
    np.testing.assert_allclose(
        batched["predicted_sensor_c"].to_numpy(),
        reference["predicted_sensor_c"].to_numpy(),
        rtol=0,
        atol=1e-9,
    )


def _stored_rows(wh: Any) -> dict[str, pl.DataFrame]:
    """Every row the stage stored for ``declared`` (the time it was written left out)."""
    order = {
        "predictions": "event_id, time_utc",
        "timeline": "wagon_id, time_utc",
        "timeline_segments": "wagon_id, start_utc, kind",
        "simulated_spans": "wagon_id, span_start_utc",
    }
    return {
        table: wh.con.sql(
            f"SELECT {'* EXCLUDE (simulated_utc)' if table == 'simulated_spans' else '*'} "
            f"FROM {table} WHERE model_revision = 'declared' ORDER BY {keys}"
        ).pl()
        for table, keys in order.items()
    }


def test_several_wagons_per_transaction_store_what_one_per_transaction_does(
    fleet: Fleet, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``SimulationConfig.batch_rows``: whole wagons written together, fewer commits, the same
    rows as one wagon per transaction; a second run adds nothing."""
    from fleetbrake.simulation.predictions import current_revision, simulate_events
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db) as wh:
        rev = current_revision(wh, refinement=fleet.config.refinement)
        wagons = sorted(fleet.registry.wagons)
        commits: list[int] = []
        real = wh.transaction

        def counted() -> Any:
            commits.append(1)
            return real()

        monkeypatch.setattr(wh, "transaction", counted)
        one = dataclasses.replace(fleet.config, batch_rows=1)
        first = simulate_events(wh, fleet.registry, rev, one, wagons=wagons, progress=False)
        assert len(first.wagons_simulated) >= 2
        assert len(commits) == len(first.spans_simulated)  # one span per transaction
        alone = _stored_rows(wh)
        commits.clear()
        again = simulate_events(wh, fleet.registry, rev, fleet.config, wagons=wagons)
        assert again.wagons_simulated == first.wagons_simulated
        assert len(commits) == 1  # the fleet's rows fit in one batch
        together = _stored_rows(wh)
        for table, frame in alone.items():
            assert frame.height > 0, table
            assert together[table].equals(frame), table
        commits.clear()
        nothing = simulate_events(wh, fleet.registry, rev, fleet.config)
        assert (nothing.wagons_simulated, nothing.events_simulated, commits) == ([], 0, [])
        for table, frame in _stored_rows(wh).items():
            assert frame.equals(alone[table]), table


def test_the_flags_judge_their_wagons_on_an_engine_as_inline(
    fleet: Fleet, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``raise_flags(engine=...)``: each wagon's findings computed in a worker process from
    the partition the parent read, the flags (ids, evidence, notes, stored rows) those of the
    inline path."""
    from fleetbrake.engine import LocalEngine
    from fleetbrake.flags import raise_flags
    from fleetbrake.simulation.predictions import current_revision, simulate_events
    from fleetbrake.warehouse.connection import open_warehouse

    def stored(wh: Any) -> list[tuple[Any, ...]]:
        return wh.con.execute(
            "SELECT flag_id, wagon_id, event_id, kind, severity, start_utc, end_utc, evidence "
            "FROM flags ORDER BY flag_id"
        ).fetchall()

    with open_warehouse(fleet.db) as wh:
        rev = current_revision(wh, refinement=fleet.config.refinement)
        simulate_events(wh, fleet.registry, rev, fleet.config, progress=False)
        inline = raise_flags(wh, fleet.registry, rev.name)
        rows = stored(wh)
        with LocalEngine(2) as engine:
            spread = raise_flags(wh, fleet.registry, rev.name, engine=engine)
        assert stored(wh) == rows
    assert inline.flags, "the fleet has anomalies: some flags expected"
    assert spread.flags == inline.flags
    assert spread.notes == inline.notes and spread.wagons == inline.wagons


def test_rows_of_a_span_without_a_ledger_row_are_replaced_and_orphans_removed(
    fleet: Fleet,
) -> None:
    """A span with rows but no ``simulated_spans`` row has them replaced, not doubled; the
    rows of a span the ledger holds but the spans no longer do (merged, cut again) are
    deleted."""
    import datetime as dt

    from fleetbrake.simulation.predictions import current_revision, simulate_events
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db) as wh:
        rev = current_revision(wh, refinement=fleet.config.refinement)
        wagons = sorted(fleet.registry.wagons)
        simulate_events(wh, fleet.registry, rev, fleet.config, wagons=wagons, progress=False)
        replaced = _stored_rows(wh)
        wh.con.execute("DELETE FROM simulated_spans WHERE model_revision = 'declared'")
        again = simulate_events(wh, fleet.registry, rev, fleet.config, progress=False)
        assert again.spans_simulated
        for table, frame in _stored_rows(wh).items():
            assert frame.height > 0 and frame.equals(replaced[table]), table
        ((wagon, start, end),) = wh.con.execute(
            "SELECT wagon_id, span_start_utc, span_end_utc FROM simulated_spans "
            "ORDER BY ALL LIMIT 1"
        ).fetchall()
        later = end + dt.timedelta(days=30)  # a span the data no longer hold
        wh.con.execute(
            "INSERT INTO simulated_spans SELECT wagon_id, model_revision, $a, $b, data_key, "
            "model_key, events, simulated_utc FROM simulated_spans WHERE wagon_id = $w "
            "AND span_start_utc = $s",
            {"a": later, "b": later, "w": wagon, "s": start},
        )
        wh.con.execute(
            "INSERT INTO timeline SELECT wagon_id, model_revision, $a, predicted_sensor_c, "
            "predicted_contact_mean_c, predicted_contact_max_c FROM timeline "
            "WHERE wagon_id = $w AND time_utc = $s",
            {"a": later, "w": wagon, "s": start},
        )
        nothing = simulate_events(wh, fleet.registry, rev, fleet.config, progress=False)
        assert nothing.spans_simulated == []
        for table, frame in _stored_rows(wh).items():  # the orphan's rows are gone
            assert frame.equals(replaced[table]), table


def test_the_prediction_rows_are_built_as_one_row_per_window_second(fleet: Fleet) -> None:
    """The predictions' frame (built column by column, its strings gathered once per window)
    equals the rows written out one by one from the event windows: every column, every
    value, the nulls where a reading is missing."""
    from fleetbrake.simulation.batched import simulate_span_batched
    from fleetbrake.simulation.frames import PREDICTION_SCHEMA, prediction_frame
    from fleetbrake.simulation.predictions import Revision, load_wagon, model_for
    from fleetbrake.warehouse.connection import open_warehouse

    rev = Revision("rows-test")
    compared = 0
    with open_warehouse(fleet.db) as wh:
        for wagon in fleet.registry.wagons.values():
            data = load_wagon(wh, wagon, fleet.config)
            model = model_for(wagon, rev.solver, fleet.config.refinement)
            windows = []
            for series in data.spans:
                result = simulate_span_batched(
                    series, wagon, model, rev.effects, fleet.config.chain
                )
                windows += [(series, w, result.speed_kmh) for w in result.windows]
            if not windows:
                continue
            rows = []
            for series, w, speed in windows:
                for i, k in enumerate(range(w.start, w.stop + 1)):
                    measured = float(series.measured_c[k])
                    rows.append(
                        {
                            "event_id": w.event_id,
                            "wagon_id": wagon.wagon_id,
                            "time_utc": series.utc(k),
                            "model_revision": rev.name,
                            "phase": "heating" if k <= w.release else "cooling",
                            "measured_sensor_c": None if np.isnan(measured) else measured,
                            "predicted_sensor_c": float(w.sensor_c[i]),
                            "predicted_contact_mean_c": float(w.contact_mean_c[i]),
                            "predicted_contact_max_c": float(w.contact_max_c[i]),
                            "speed_kmh": float(speed[k]),
                            "brake_pressure_bar": float(series.pressure_bar[k]),
                            "ambient_c": float(series.ambient_c[k]),
                            "flux_w_m2": float(w.flux_w_m2[i]),
                        }
                    )
            want = pl.DataFrame(rows, schema=PREDICTION_SCHEMA)
            got = prediction_frame(wagon.wagon_id, rev.name, windows)
            assert got.schema == want.schema
            assert got.equals(want)
            assert got["measured_sensor_c"].null_count() == want["measured_sensor_c"].null_count()
            compared += got.height
    assert compared > 10_000


def test_a_chunk_is_cut_into_each_wagons_rows_sorted_as_its_own_query_sorts_them() -> None:
    """``store.wagon_parts``: rows of several wagons in any stored order (a wagon's rows in
    several runs, a late file's among another wagon's) come out per wagon, sorted by the keys
    with ties kept in stored order, without the cut columns; a wagon without rows gets an
    empty table of the same columns."""
    import pyarrow as pa

    from fleetbrake.simulation.store import wagon_part, wagon_parts

    rng = np.random.default_rng(3)
    n = 400
    wagon = rng.choice(["A", "B", "C"], size=n)
    time = rng.integers(0, 50, size=n)  # ties: the file_id and then the stored order decide
    file_id = rng.integers(0, 3, size=n)
    table = pa.table({"wagon_id": wagon, "time": time, "file_id": file_id, "row": np.arange(n)})
    parts = wagon_parts(table, ["A", "B", "C", "D"], ["time", "file_id"], ["file_id"])
    for w in ("A", "B", "C"):
        mine = np.flatnonzero(wagon == w)
        order = mine[np.lexsort((mine, file_id[mine], time[mine]))]  # stable by stored order
        assert parts[w].column_names == ["time", "row"]
        assert parts[w].column("row").to_pylist() == order.tolist()
        assert wagon_part(table, w, ["time", "file_id"], ["file_id"]).equals(parts[w])
    assert parts["D"].num_rows == 0 and parts["D"].column_names == ["time", "row"]
    # a wagon's rows stored in order (most are) come out as they are, in one run or several
    ordered = table.take(np.lexsort((np.arange(n), file_id, time, wagon)))
    for pieces in (1, 7):
        cut = pa.concat_tables(
            [ordered.slice(k, -(-n // pieces)) for k in range(0, n, -(-n // pieces))]
        )
        again = wagon_parts(cut, ["A", "B", "C"], ["time", "file_id"], ["file_id"])
        for w in ("A", "B", "C"):
            assert again[w].equals(parts[w])
    # read with positions instead of names (``wagon_ix``, 1-based in the list the query was
    # given, here in another order than the wagons asked for): the same parts, ``wagon_ix``
    # dropped instead of ``wagon_id``
    given = ["C", "A", "B"]
    ix = np.array([given.index(w) + 1 for w in wagon], dtype=np.int32)
    positions = table.drop_columns(["wagon_id"]).add_column(0, "wagon_ix", pa.array(ix))
    by_ix = wagon_parts(
        positions, ["A", "B", "C", "D"], ["time", "file_id"], ["file_id"], positions_of=given
    )
    for w in ("A", "B", "C", "D"):
        assert by_ix[w].equals(parts[w])


def test_the_stages_chunks_hold_the_partitions_the_per_wagon_queries_read(
    fleet: Fleet,
) -> None:
    """The simulation's and the flags' chunks (one query per table for several spans, their
    time ranges only) cut into the very tables the per-span queries read (``wagon_task``,
    ``flag_task``), and the flags judged by chunks of one span or of all are the same."""
    from fleetbrake.flags import judge, partition
    from fleetbrake.flags.config import FlagConfig
    from fleetbrake.ingest.spans import stored_spans
    from fleetbrake.simulation import predictions as p
    from fleetbrake.simulation.store import simulated_spans
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db) as wh:
        rev = p.current_revision(wh, refinement=fleet.config.refinement)
        p.simulate_events(wh, fleet.registry, rev, fleet.config, progress=False)
        spans, done = stored_spans(wh), simulated_spans(wh, rev.name)
        registered = [s for s in spans if s.wagon_id in fleet.registry.wagons]
        assert len(registered) >= 2
        todo = [(fleet.registry.wagons[s.wagon_id], s, "model") for s in registered]
        chunk = p.wagon_chunk(wh, todo, rev, fleet.config)
        assert str(chunk).startswith("spans ")
        for task, (w, span, model) in zip(p.chunk_tasks(chunk), todo, strict=True):
            alone = p.wagon_task(wh, w, span, rev, fleet.config, model_key=model)
            assert task.samples.num_rows > 0 and task.events.num_rows > 0
            assert task.samples.equals(alone.samples) and task.events.equals(alone.events)
        heads = [  # the unregistered wagon's spans too: their readings alone
            partition.FlagHead(
                s,
                7.0,
                None,
                done[s.key].data_key if s.key in done else None,
                fleet.registry.wagons.get(s.wagon_id),
                False,
            )
            for s in spans
        ]
        config = FlagConfig()
        flag_chunk = partition.flag_chunk(wh, heads, rev.name, config, rev)
        for task, head in zip(partition.chunk_tasks(flag_chunk), heads, strict=True):
            alone = partition.flag_task(
                wh,
                head.span,
                rev.name,
                config,
                ambient_c=head.ambient_c,
                note=None,
                data_key=head.data_key,
                wagon=head.wagon,
                rev=rev,
            )
            for name in ("samples", "events", "segments", "timeline", "predictions"):
                mine, theirs = getattr(task, name), getattr(alone, name)
                assert (mine is None) == (theirs is None), name
                assert mine is None or mine.equals(theirs), (head.span, name)
        by_one = judge.raise_flags(wh, fleet.registry, rev.name, chunk_rows=1)
        by_all = judge.raise_flags(wh, fleet.registry, rev.name)
    assert by_one.flags == by_all.flags and by_one.notes == by_all.notes
    assert by_all.flags


def test_the_chunk_pipeline_yields_in_order_and_writes_whole_wagons_in_row_batches(
    fleet: Fleet,
) -> None:
    """``store.chunk_pipeline`` (the simulation's and the estimate's one pipeline): chunks
    of about ``chunk_rows`` samples read on a second connection, results yielded in the
    wagons' order, written in batches of whole wagons of at most ``batch_rows`` rows (one
    batch per call, the last committed before the generator ends); a failing partition is
    raised, and the batch still being gathered is not written."""
    from fleetbrake.simulation.store import chunk_pipeline
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db) as wh:
        counts = dict(
            wh.con.execute("SELECT wagon_id, count(*) FROM samples GROUP BY ALL").fetchall()
        )
        ids = sorted(counts)
        assert len(ids) == 2
        read: list[list[str]] = []
        written: list[list[tuple[str, int]]] = []

        def reading(source: Any, chunk: list[str]) -> list[str]:
            assert source.con is not wh.con  # the reader's own connection
            read.append(chunk)
            return chunk

        def run(chunk_rows: int, batch_rows: int, fail: str = "") -> list[str]:
            read.clear()
            written.clear()

            def compute(chunk: list[str]) -> list[tuple[str, int]]:
                if fail in chunk:
                    raise RuntimeError(f"wagon {fail}")
                return [(w, 10) for w in chunk]

            results = chunk_pipeline(
                wh,
                ids,
                unit_rows=counts.__getitem__,
                read=reading,
                compute=compute,
                write=written.append,
                result_rows=lambda result: result[1],
                chunk_rows=chunk_rows,
                batch_rows=batch_rows,
            )
            return [w for w, _ in results]

        assert run(sum(counts.values()), 20) == ids
        assert (read, written) == ([ids], [[(w, 10) for w in ids]])  # one chunk, one batch
        assert run(1, 15) == ids
        assert read == [[w] for w in ids]  # a wagon's samples exceed a chunk: alone
        assert written == [[(w, 10)] for w in ids]  # 20 rows > 15: a batch each
        with pytest.raises(RuntimeError, match=ids[1]):
            run(1, 20, fail=ids[1])
        assert written == []  # the first wagon's batch was still being gathered


def test_a_wagons_samples_are_totally_ordered_by_time_then_file(fleet: Fleet) -> None:
    """``store.sample_parts`` sorts a wagon's samples by (time_utc, file_id), a stable sort of
    rows read in no fixed order: that is deterministic only because ingest keeps one row per
    time in a file (the first of repeated times, ``files.rows_duplicate``) and a file holds one
    wagon, so no two stored samples of a wagon tie on both. The generated fleet's files do
    repeat times."""
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db) as wh:
        repeated = wh.con.execute("SELECT sum(rows_duplicate) FROM files").fetchone()
        ties = wh.con.execute(
            "SELECT count(*) FROM (SELECT wagon_id, time_utc, file_id FROM samples "
            "GROUP BY ALL HAVING count(*) > 1)"
        ).fetchone()
        wagons_per_file = wh.con.execute(
            "SELECT max(n) FROM (SELECT count(DISTINCT wagon_id) AS n FROM samples "
            "GROUP BY file_id)"
        ).fetchone()
    assert repeated is not None and repeated[0] > 0
    assert ties == (0,) and wagons_per_file == (1,)
