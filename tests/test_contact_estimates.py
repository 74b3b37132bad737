"""The virtual sensor's stage: ``run`` fills ``v_contact_estimates`` with one row
per wagon and logged second (interface v2), incrementally, the same on any engine; with a
fleet that follows the declared model the estimate is the model's prediction, and a dragging
brake shows as unexplained power."""

from __future__ import annotations

import datetime as dt
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import polars as pl
import pytest

from fleetbrake.app.run import RunReport, run_fleet
from fleetbrake.engine import InlineEngine, LocalEngine
from fleetbrake.model.estimator import Z95, EstimatorNoise
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.simulation.estimates import (
    DEFAULT_POWER_NOISE_W_PER_SQRT_S,
    ESTIMATE_SCHEMA,
    EstimationConfig,
    wagon_estimates,
)
from fleetbrake.warehouse.connection import open_warehouse

VIEW_COLUMNS = [
    ("wagon_id", "VARCHAR"),
    ("time_utc", "TIMESTAMP"),
    ("model_revision", "VARCHAR"),
    ("resolution_s", "INTEGER"),
    ("contact_mean_c", "DOUBLE"),
    ("contact_mean_lo_c", "DOUBLE"),
    ("contact_mean_hi_c", "DOUBLE"),
    ("contact_max_c", "DOUBLE"),
    ("contact_max_hi_c", "DOUBLE"),
    ("smoothed_contact_mean_c", "DOUBLE"),
    ("smoothed_contact_mean_lo_c", "DOUBLE"),
    ("smoothed_contact_mean_hi_c", "DOUBLE"),
    ("unexplained_power_w", "DOUBLE"),
    ("unexplained_power_lo_w", "DOUBLE"),
    ("unexplained_power_hi_w", "DOUBLE"),
    ("innovation_k", "DOUBLE"),
]
"""``v_contact_estimates`` of interface.md v3, in order."""

STAGE_TABLES = ("contact_estimates", "estimated_spans", "estimator_noise")


@pytest.fixture(scope="module")
def fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_cache_dir: Path,
) -> Iterator[Path]:
    """3 wagons x 1 day with the anomalies (seed 1: SGG-0002's dragging brake is logged, with
    no sensor fault at the time)."""
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    root = tmp_path_factory.mktemp("estimates") / "fleet"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        generate_fleet(root, SynthConfig(wagons=3, days=1, seed=1), rom=reduced_model_for)
        yield root


def _run(
    fleet: Path,
    db: Path,
    engine: object,
    refinement: float,
    cache: Path,
    estimation: EstimationConfig | None = None,
) -> RunReport:
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(cache))
        return run_fleet(
            fleet,
            db,
            simulation=SimulationConfig(refinement=refinement),
            progress=False,
            engine=engine,  # type: ignore[arg-type]
            estimation=estimation,
        )


@pytest.fixture(scope="module")
def inline_db(
    fleet: Path,
    tmp_path_factory: pytest.TempPathFactory,
    rom_refinement: float,
    rom_cache_dir: Path,
) -> Path:
    db = tmp_path_factory.mktemp("estimates-db") / "inline.duckdb"
    report = _run(fleet, db, InlineEngine(), rom_refinement, rom_cache_dir)
    assert report.estimation is not None and report.estimation.noise_method == "default"
    assert "estimate" in report.stage_s
    return db


FE_REFINEMENT = 0.2
"""The full model's mesh that writes the full-FE fleets (409 hex20 nodes, as ``test_closeloop``:
another mesh and another integrator than the reduced model the stage estimates with)."""


@pytest.fixture(scope="module")
def full_fleet(
    tmp_path_factory: pytest.TempPathFactory,
    full_model_for: Callable[..., object],
    rom_cache_dir: Path,
) -> Iterator[Path]:
    """``fleet``'s wagons, day and anomalies (seed 1: SGG-0002's dragging brake) written by
    the full FE model (solver ``full``; some 20 s)."""
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    root = tmp_path_factory.mktemp("estimates-full") / "fleet"
    config = SynthConfig(wagons=3, days=1, seed=1, solver="full", refinement=FE_REFINEMENT)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        generate_fleet(root, config, rom=full_model_for)  # type: ignore[arg-type]
        yield root


@pytest.fixture(scope="module")
def full_db(
    full_fleet: Path,
    tmp_path_factory: pytest.TempPathFactory,
    rom_refinement: float,
    rom_cache_dir: Path,
) -> Path:
    db = tmp_path_factory.mktemp("estimates-full-db") / "full.duckdb"
    report = _run(full_fleet, db, InlineEngine(), rom_refinement, rom_cache_dir)
    assert report.estimation is not None and report.estimation.wagons_estimated
    return db


def _query(db: Path, text: str, params: dict[str, Any] | None = None) -> pl.DataFrame:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.sql(text, params=params).pl()
    finally:
        con.close()


def _tables(db: Path) -> dict[str, pl.DataFrame]:
    return {
        table: _query(db, f"SELECT * FROM {table} ORDER BY ALL").drop("created_utc", strict=False)
        for table in STAGE_TABLES
    }


def test_run_fills_v_contact_estimates_one_row_per_logged_second(
    fleet: Path, inline_db: Path
) -> None:
    described = _query(inline_db, "DESCRIBE v_contact_estimates")
    assert list(zip(described["column_name"], described["column_type"], strict=True)) == (
        VIEW_COLUMNS
    )
    per_wagon = _query(
        inline_db,
        """
        WITH logged AS (
            SELECT s.wagon_id, count(DISTINCT s.time_utc) AS seconds
            FROM samples AS s JOIN wagon_registry AS r USING (wagon_id)
            GROUP BY ALL
        ),
        estimated AS (
            SELECT wagon_id, count(*) AS rows, count(DISTINCT time_utc) AS seconds
            FROM v_contact_estimates WHERE model_revision = 'declared' GROUP BY ALL
        )
        SELECT l.wagon_id, l.seconds, e.rows, e.seconds AS distinct_seconds
        FROM logged AS l LEFT JOIN estimated AS e USING (wagon_id) ORDER BY ALL
        """,
    )
    assert per_wagon.height >= 3
    assert per_wagon["rows"].to_list() == per_wagon["seconds"].to_list()
    assert per_wagon["distinct_seconds"].to_list() == per_wagon["seconds"].to_list()
    # every logged second at the sample's time; the innovation only with a valid reading, and
    # with every valid reading but a frozen sensor's (the truth's frozen faults)
    ((unmatched, wrong_innovation, nulls),) = _query(
        inline_db,
        """
        SELECT
            count(*) FILTER (WHERE s.time_utc IS NULL),
            count(*) FILTER (WHERE e.innovation_k IS NOT NULL AND s.block_temp_c IS NULL),
            count(*) FILTER (WHERE e.smoothed_contact_mean_c IS NULL OR e.contact_mean_c IS NULL)
        FROM v_contact_estimates AS e
        LEFT JOIN (
            SELECT wagon_id, time_utc, any_value(block_temp_c) AS block_temp_c
            FROM samples GROUP BY ALL
        ) AS s USING (wagon_id, time_utc)
        """,
    ).rows()
    assert (unmatched, wrong_innovation, nulls) == (0, 0, 0)
    skipped = _query(
        inline_db,
        """
        SELECT e.wagon_id, e.time_utc
        FROM v_contact_estimates AS e
        JOIN samples AS s USING (wagon_id, time_utc)
        WHERE e.innovation_k IS NULL AND s.block_temp_c IS NOT NULL
        """,
    )
    from fleetbrake.synth.truth import load_truth

    frozen = [
        a for a in load_truth(fleet).anomalies if a.kind == "sensor_fault" and a.subtype == "frozen"
    ]
    inside = pl.lit(False)
    for a in frozen:
        inside |= (pl.col("wagon_id") == a.wagon_id) & pl.col("time_utc").is_between(
            a.start_utc, a.end_utc
        )
    assert skipped.filter(~inside).height == 0
    ((bad_bounds,),) = _query(
        inline_db,
        """
        SELECT count(*) FROM v_contact_estimates
        WHERE NOT (contact_mean_lo_c <= contact_mean_c AND contact_mean_c <= contact_mean_hi_c
                   AND contact_max_c <= contact_max_hi_c
                   AND smoothed_contact_mean_lo_c <= smoothed_contact_mean_c
                   AND smoothed_contact_mean_c <= smoothed_contact_mean_hi_c
                   AND unexplained_power_lo_w <= unexplained_power_w
                   AND unexplained_power_w <= unexplained_power_hi_w)
        """,
    ).rows()
    assert bad_bounds == 0
    # the noise: sigma_v each wagon's own, from its readings (the generator's: 0.1 K, on every
    # wagon, sensor faults or not); sigma_w the declared revision's default; nothing fitted
    noise = _query(inline_db, "SELECT * FROM estimated_spans ORDER BY wagon_id")
    assert noise.height >= 3
    assert noise["measurement_k"].is_between(0.085, 0.115).all(), noise["measurement_k"]
    assert noise["measurement_k"].n_unique() == noise.height  # each its own
    assert (noise["power_w_per_sqrt_s"] == DEFAULT_POWER_NOISE_W_PER_SQRT_S).all()
    assert _query(inline_db, "SELECT * FROM estimator_noise").height == 0
    # a wagon's rows as a polars frame with the table's columns
    with open_warehouse(inline_db, read_only=True) as wh:
        frame = wagon_estimates(wh, per_wagon["wagon_id"][0], "declared")
        assert frame.schema == ESTIMATE_SCHEMA
        assert frame.height == per_wagon["seconds"][0]
        assert frame["time_utc"].is_sorted()
        assert wagon_estimates(wh, per_wagon["wagon_id"][0], "no-such-revision").height == 0


def test_local_engine_equals_inline_and_a_second_run_adds_nothing(
    fleet: Path, inline_db: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    db = tmp_path / "local.duckdb"
    with LocalEngine(2) as engine:
        _run(fleet, db, engine, rom_refinement, rom_cache_dir)
        local, inline = _tables(db), _tables(inline_db)
        for table in STAGE_TABLES:
            assert local[table].columns == inline[table].columns
            assert local[table].height == inline[table].height
            assert local[table].height > 0 or table == "estimator_noise"  # none fitted
            for name, dtype in local[table].schema.items():
                a, b = local[table][name], inline[table][name]
                if dtype == pl.Float64:
                    assert np.allclose(
                        a.to_numpy(), b.to_numpy(), rtol=0, atol=1e-9, equal_nan=True
                    ), f"{table}.{name}"
                    assert a.is_null().to_list() == b.is_null().to_list()
                else:
                    assert a.to_list() == b.to_list(), f"{table}.{name}"
        stamps = _query(db, "SELECT * FROM estimated_spans ORDER BY ALL")
        again = _run(fleet, db, engine, rom_refinement, rom_cache_dir)
    assert again.estimation is not None
    assert again.estimation.wagons_estimated == [] and again.estimation.rows == 0
    assert _query(db, "SELECT * FROM estimated_spans ORDER BY ALL").equals(stamps)
    assert _tables(db)["contact_estimates"].equals(local["contact_estimates"])


def test_a_late_file_reestimates_only_its_wagon(
    fleet: Path, inline_db: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    """A late file re-estimates its wagon only, and the estimates end where one run over all
    the files ends (what ``watch`` then ``run`` does, file by file)."""
    copy = tmp_path / "fleet"
    shutil.copytree(fleet, copy)
    logs = sorted((copy / "logs").glob("SGG-0003/*.csv*"))
    late = logs[len(logs) // 2]  # a file from the middle of a wagon's day, landing late
    held = tmp_path / late.name
    late.rename(held)
    db = tmp_path / "fleet.duckdb"
    engine = InlineEngine()
    _run(copy, db, engine, rom_refinement, rom_cache_dir)
    before = _tables(db)
    before_stamps = _query(db, "SELECT * FROM estimated_spans ORDER BY ALL")
    held.rename(late)
    report = _run(copy, db, engine, rom_refinement, rom_cache_dir)
    assert report.estimation is not None
    assert report.estimation.wagons_estimated == ["SGG-0003"]
    after = _tables(db)
    for table in ("contact_estimates", "estimated_spans"):
        mine = pl.col("wagon_id") == "SGG-0003"
        assert after[table].filter(~mine).equals(before[table].filter(~mine)), table
    stamps = _query(db, "SELECT * FROM estimated_spans ORDER BY ALL")
    others = pl.col("wagon_id") != "SGG-0003"
    assert stamps.filter(others).equals(before_stamps.filter(others))  # not rewritten
    # the late file's seconds are estimated now
    grown = after["contact_estimates"].filter(pl.col("wagon_id") == "SGG-0003").height
    assert grown > before["contact_estimates"].filter(pl.col("wagon_id") == "SGG-0003").height
    assert after["contact_estimates"].equals(_tables(inline_db)["contact_estimates"])


def test_a_dragging_brake_shows_as_unexplained_power(fleet: Path, inline_db: Path) -> None:
    _assert_drag_found(fleet, inline_db)


def _assert_drag_found(fleet: Path, inline_db: Path) -> None:
    """The fleet's dragging brake as unexplained power: its smoothed mean near the true
    power, its lower bound above 0, none the hours before."""
    from fleetbrake.fleet.registry import WagonConfig
    from fleetbrake.synth.truth import load_truth

    truth = load_truth(fleet)
    (drag,) = [a for a in truth.anomalies if a.kind == "dragging_brake"]
    series = truth.series(drag.wagon_id)
    area = WagonConfig(wagon_id=drag.wagon_id).geometry.contact_area_m2
    during = (pl.col("time_utc") >= drag.start_utc) & (pl.col("time_utc") <= drag.end_utc)
    true_power = float(
        series.filter(during & (pl.col("brake_pressure_bar") < 0.01))
        .select((pl.col("heat_flux_w_m2") * area).mean())
        .item()
    )
    assert true_power > 100  # the truth has a drag to find
    est = _query(
        inline_db,
        "SELECT * FROM contact_estimates WHERE wagon_id = $w AND model_revision = 'declared' "
        "ORDER BY time_utc",
        {"w": drag.wagon_id},
    )
    inside = est.filter(
        pl.col("time_utc").is_between(drag.start_utc + dt.timedelta(minutes=5), drag.end_utc)
    )
    assert inside.height > 600
    smoothed = inside["smoothed_unexplained_power_w"].to_numpy()
    live = inside["unexplained_power_w"].to_numpy()
    # well above 0: the smoothed power's lower bound above 0 nearly throughout, its mean near
    # the truth's, the live estimate there in the second half of the drag
    assert np.mean(inside["smoothed_unexplained_power_lo_w"].to_numpy() > 0) > 0.9
    assert abs(np.mean(smoothed) - true_power) < 0.3 * true_power
    assert np.mean(live[live.size // 2 :]) > 0.7 * true_power
    # and no such power the hours before it
    quiet = est.filter(pl.col("time_utc") < drag.start_utc - dt.timedelta(hours=1))
    assert quiet.height > 600
    assert abs(float(quiet["smoothed_unexplained_power_w"].mean())) < 0.2 * true_power


@pytest.fixture(scope="module")
def declared_fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_cache_dir: Path,
) -> Iterator[Path]:
    """One wagon-day following the declared model: no anomaly, noise-free readings and
    inputs, no damaged or missing data."""
    root = tmp_path_factory.mktemp("declared") / "fleet"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        _generate_declared(root, reduced_model_for, "rom")
        yield root


def _generate_declared(
    root: Path, model: Callable[..., object], solver: str, refinement: float = FE_REFINEMENT
) -> None:
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    config = SynthConfig(
        wagons=1,
        days=1,
        seed=5,
        anomalies=False,
        sensor_noise_k=0.0,
        pressure_noise_bar=0.0,
        speed_noise_kmh=0.0,
        missing_row_fraction=0.0,
        gap_probability=0.0,
        duplicate_fraction=0.0,
        swap_fraction=0.0,
        empty_cell_fraction=0.0,
        frozen_speed_probability=0.0,
        speed_jump_probability=0.0,
        truncated_files=0,
        truncated_gzip_files=0,
        garbage_files=0,
        unregistered_wagon=False,
        bad_registry_entry=False,
        odd_columns=False,
        solver=solver,  # type: ignore[arg-type]
        **({"refinement": refinement} if solver == "full" else {}),  # type: ignore[arg-type]
    )
    generate_fleet(root, config, rom=model)  # type: ignore[arg-type]


def test_identity_noise_free_declared_readings_give_the_models_prediction(
    declared_fleet: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    _assert_identity(declared_fleet, tmp_path, rom_refinement, rom_cache_dir, model_error_k=0.0)


def _assert_identity(
    declared_fleet: Path,
    tmp_path: Path,
    rom_refinement: float,
    rom_cache_dir: Path,
    *,
    model_error_k: float,
) -> None:
    """With noise-free readings of a fleet following the declared model, the estimate is
    the model's prediction within its band (plus ``model_error_k``: how far the model that
    wrote the fleet is from the estimator's reduced one) and the unexplained power within
    its bounds of zero."""
    db = tmp_path / "declared.duckdb"
    given = EstimationConfig(noise=EstimatorNoise(measurement_k=0.1, power_w_per_sqrt_s=3.0))
    _run(declared_fleet, db, InlineEngine(), rom_refinement, rom_cache_dir, given)
    noise = _query(db, "SELECT measurement_k, power_w_per_sqrt_s FROM estimated_spans")
    assert noise.rows() == [(0.1, 3.0)]
    both = _query(
        db,
        """
        SELECT e.*, t.predicted_contact_mean_c
        FROM contact_estimates AS e
        JOIN timeline AS t USING (wagon_id, model_revision, time_utc)
        ORDER BY time_utc
        """,
    )
    # the declared model's prediction from the true inputs: what the readings came from
    from fleetbrake.synth.truth import load_truth

    truth = load_truth(declared_fleet).series("SGG-0001")
    both = both.join(
        truth.select("time_utc", pl.col("contact_mean_c").alias("model_c")), on="time_utc"
    )
    assert both.height > 10_000
    model = both["model_c"].to_numpy()
    assert model.max() - model.min() > 30  # brakings heat the block
    timeline = both["predicted_contact_mean_c"].to_numpy()
    for prefix in ("", "smoothed_"):
        mean = both[f"{prefix}contact_mean_c"].to_numpy()
        half = (both[f"{prefix}contact_mean_hi_c"] - both[f"{prefix}contact_mean_lo_c"]).to_numpy()
        # inside the band around the model's prediction (0.02 K: the log's rounding of the
        # readings), and a band that says something. Not necessarily at every second: the
        # logged pressure has the sensor's 7 mbar resolution (fleet-data.md), an input error
        # of a few W in a long braking that the declared model does not have, which the
        # braking's power P_b resolves after a while: a few seconds of long brakings leave the
        # band, by less than 1.5x the sensor's noise (measured with the defaults: 0.12 % of
        # the seconds, by 0.024 K filtered; 0.06 %, by 0.11 K smoothed; with sigma_q 0.3 and
        # no P_b: 0.05 %, by 0.006 K and 0.10 K)
        excess = np.abs(mean - model) - (0.5 * half + 0.02 + model_error_k)
        outside = float(np.mean(excess > 0))
        print(f"{prefix}outside the band: {outside:.5f}, by at most {excess.max():.4f} K")
        assert outside <= 0.002, prefix
        assert excess.max() <= 0.15, prefix
        assert np.mean(half / 2 / Z95) < 1.0, prefix
        # the stored open-loop timeline (re-anchored by uniform shifts) is within ~1 K of it
        assert np.all(np.abs(mean - timeline) <= 0.5 * half + 1.5), prefix
    # (98 % of the seconds for the model itself: the pressure's 7 mbar resolution is a real
    # -8 W in long brakings, which P_b resolves (measured 0.993 filtered, 0.988 smoothed);
    # the FE model's error on the full-FE fleet: 95 %, measured 0.993 and 0.988 there too)
    least = 0.98 if model_error_k == 0 else 0.95
    for prefix in ("", "smoothed_"):
        lo = both[f"{prefix}unexplained_power_lo_w"].to_numpy()
        hi = both[f"{prefix}unexplained_power_hi_w"].to_numpy()
        share = float(np.mean((lo <= 0) & (hi >= 0)))
        print(f"{prefix}unexplained power within its bounds of 0: {share:.4f}")
        assert share >= least, prefix


def test_a_wagons_results_do_not_depend_on_when_the_others_arrived(
    fleet: Path, inline_db: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    """A wagon's estimates are a function of its data and the revision only: estimating the
    fleet with one wagon's files arriving after the others' gives the rows of estimating
    them all together (the noise is not fitted on whichever wagons came first)."""
    copy = tmp_path / "fleet"
    shutil.copytree(fleet, copy)
    late = copy / "logs" / "SGG-0001"  # the first id: the old fleet fit always took it
    held = tmp_path / "SGG-0001"
    late.rename(held)
    db = tmp_path / "fleet.duckdb"
    first = _run(copy, db, InlineEngine(), rom_refinement, rom_cache_dir)
    assert first.estimation is not None
    assert "SGG-0001" not in first.estimation.wagons_estimated
    held.rename(late)
    then = _run(copy, db, InlineEngine(), rom_refinement, rom_cache_dir)
    assert then.estimation is not None and then.estimation.wagons_estimated == ["SGG-0001"]
    order = ["wagon_id", "time_utc"]
    together = _query(inline_db, "SELECT * FROM contact_estimates ORDER BY wagon_id, time_utc")
    one_by_one = _query(db, "SELECT * FROM contact_estimates ORDER BY wagon_id, time_utc")
    assert together.height == one_by_one.height > 0
    assert together.sort(order).equals(one_by_one.sort(order))
    columns = "wagon_id, seconds, measurement_k, power_w_per_sqrt_s"
    assert _query(db, f"SELECT {columns} FROM estimated_spans ORDER BY ALL").equals(
        _query(inline_db, f"SELECT {columns} FROM estimated_spans ORDER BY ALL")
    )


def test_the_estimate_beats_the_open_loop_prediction_over_normal_operation(
    fleet: Path, inline_db: Path
) -> None:
    """On a normal noisy generated fleet, the filtered and smoothed contact mean's
    RMSE against the truth over normal operation (every wagon's seconds outside its
    anomalies) is at most the open-loop prediction's (the stored timeline); and the estimate
    follows the prediction within its band, not the sensor reading."""
    from fleetbrake.synth.truth import load_truth

    truth = load_truth(fleet)
    both = _query(
        inline_db,
        """
        SELECT e.wagon_id, e.time_utc, e.contact_mean_c, e.contact_mean_lo_c,
               e.contact_mean_hi_c, e.smoothed_contact_mean_c, t.predicted_contact_mean_c
        FROM contact_estimates AS e
        JOIN timeline AS t USING (wagon_id, model_revision, time_utc)
        WHERE e.model_revision = 'declared'
        """,
    )
    frames = []
    for wagon_id in sorted(set(both["wagon_id"].to_list())):
        normal = pl.col("wagon_id") == wagon_id
        for a in truth.anomalies:
            if a.wagon_id == wagon_id:
                normal &= ~pl.col("time_utc").is_between(a.start_utc, a.end_utc)
        true = truth.series(wagon_id).select(
            pl.col("time_utc").cast(pl.Datetime("us")), pl.col("contact_mean_c").alias("true_c")
        )
        frames.append(both.filter(normal).join(true, on="time_utc"))
    normal_seconds = pl.concat(frames)
    assert normal_seconds.height > 20_000
    assert normal_seconds["wagon_id"].n_unique() >= 2
    true = normal_seconds["true_c"].to_numpy()

    def rmse(column: str) -> float:
        return float(np.sqrt(np.mean((normal_seconds[column].to_numpy() - true) ** 2)))

    open_loop = rmse("predicted_contact_mean_c")
    assert rmse("contact_mean_c") <= open_loop
    assert rmse("smoothed_contact_mean_c") <= open_loop
    # a band that says something (RR saw +-17 K with the old fleet fit) and holds the truth
    half = (
        (normal_seconds["contact_mean_hi_c"] - normal_seconds["contact_mean_lo_c"]) / 2
    ).to_numpy()
    assert float(np.median(half)) < 2.0
    assert 0.9 <= float(np.mean(np.abs(normal_seconds["contact_mean_c"].to_numpy() - true) <= half))


def test_measurement_noise_from_second_differences_ignores_gaps_and_missing() -> None:
    from fleetbrake.model.estimator import measurement_noise

    rng = np.random.default_rng(3)
    t = np.arange(20_000.0)
    smooth = 20 + 30 * np.sin(t / 900.0) ** 2  # a block heating and cooling
    y = smooth + rng.normal(0.0, 0.1, t.size)
    y[rng.random(t.size) < 0.01] = np.nan  # missing readings
    t[10_000:] += 3_600.0  # an unlogged hour (a jump is not a step)
    y[10_000:] += 15.0
    found = measurement_noise(t, y)
    assert found is not None and abs(found - 0.1) < 0.01
    assert measurement_noise(t[:5], y[:5]) is None
    # a different sensor noise gives a different sigma_v (the wagon's own)
    other = measurement_noise(t, smooth + rng.normal(0.0, 0.3, t.size))
    assert other is not None and abs(other - 0.3) < 0.03


def test_the_close_loops_revision_gets_its_own_sigma_w_by_maximum_likelihood(
    fleet: Path, inline_db: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    """``fit_revision_noise``: σ_w fitted on the fit days' innovations (each wagon with its own
    σ_v held), stored for the revision, the same twice, and then used for every wagon."""
    from fleetbrake.ingest.files import load_fleet_registry
    from fleetbrake.simulation.estimates import estimate_wagons, fit_revision_noise, stored_noise
    from fleetbrake.simulation.predictions import current_revision

    db = tmp_path / "copy.duckdb"
    shutil.copy(inline_db, db)
    registry = load_fleet_registry(fleet)
    with pytest.MonkeyPatch.context() as mp, open_warehouse(db) as wh:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        rev = current_revision(wh, "rom", rom_refinement)
        events = wh.con.sql("SELECT wagon_id, start_utc FROM events").pl()
        config = EstimationConfig(noise_fit_s=7_200.0)
        fitted = fit_revision_noise(wh, registry, rev, events, config)
        assert fitted is not None and fitted.method == "ml"
        assert fitted.noise.power_w_per_sqrt_s >= config.min_power_noise_w_per_sqrt_s
        assert 0.085 < fitted.noise.measurement_k < 0.115
        again = fit_revision_noise(wh, registry, rev, events, config)
        assert again == fitted  # deterministic, replaced in place
        stored = stored_noise(wh, rev.name)
        assert stored is not None and stored.noise == fitted.noise
        report = estimate_wagons(wh, registry, rev, config)
        assert report.noise_method == "ml"
        assert report.power_noise_w_per_sqrt_s == fitted.noise.power_w_per_sqrt_s
        powers = wh.con.sql("SELECT DISTINCT power_w_per_sqrt_s FROM estimated_spans").fetchall()
    assert powers == [(fitted.noise.power_w_per_sqrt_s,)]
    # the default's wagons are all estimated again with it (their model key changed)
    assert sorted(report.wagons_estimated) == sorted(
        _query(inline_db, "SELECT wagon_id FROM estimated_spans")["wagon_id"].to_list()
    )


def _freeze_reading(root: Path, wagon_id: str, start: dt.datetime, end: dt.datetime) -> float:
    """Rewrite ``wagon_id``'s log files so that its reading holds, from ``start`` to ``end``,
    the value it had at ``start`` (a stuck thermistor); returns that value."""
    import csv
    import gzip
    import io

    def stamp(t: dt.datetime) -> str:
        return t.strftime("%Y-%m-%dT%H:%M:%SZ")

    first, last = stamp(start), stamp(end)
    value: str | None = None
    for path in sorted((root / "logs" / wagon_id).glob("*.csv*")):
        zipped = path.suffix == ".gz"
        text = (gzip.decompress(path.read_bytes()) if zipped else path.read_bytes()).decode()
        rows = list(csv.reader(io.StringIO(text)))
        column = rows[0].index("block_temp_c")
        touched = False
        for row in sorted(rows[1:], key=lambda r: r[0]):
            if len(row) > column and first <= row[0] <= last:
                if value is None:
                    value = row[column]
                row[column], touched = value, True
        if touched:
            out = io.StringIO()
            csv.writer(out, lineterminator="\n").writerows(rows)
            data = out.getvalue().encode()
            path.write_bytes(gzip.compress(data) if zipped else data)
    assert value is not None
    return float(value)


def test_a_frozen_thermistor_skips_the_update_and_is_still_flagged(
    fleet: Path, inline_db: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    """A thermistor stuck for an hour around the wagon's hottest braking (SGG-0001, healthy):
    its readings are masked out of the estimator's updates (no innovation), so the contact
    estimate follows the model, its band widening while it runs blind, instead of diving
    towards the stuck value; the flags still report the frozen sensor (one run detector,
    ``constant_runs``, for both)."""
    from fleetbrake.synth.truth import load_truth

    wagon = "SGG-0001"
    truth = (
        load_truth(fleet)
        .series(wagon)
        .select(
            pl.col("time_utc").cast(pl.Datetime("us")), pl.col("contact_mean_c").alias("true_c")
        )
    )
    assert not [a for a in load_truth(fleet).anomalies if a.wagon_id == wagon]
    peak = truth.sort("true_c", descending=True)["time_utc"][0]
    start, end = peak - dt.timedelta(minutes=30), peak + dt.timedelta(minutes=30)
    copy = tmp_path / "fleet"
    shutil.copytree(fleet, copy)
    stuck_c = _freeze_reading(copy, wagon, start, end)
    db = tmp_path / "fleet.duckdb"
    _run(copy, db, InlineEngine(), rom_refinement, rom_cache_dir)
    query = "SELECT * FROM contact_estimates WHERE wagon_id = $w ORDER BY time_utc"
    est = _query(db, query, {"w": wagon}).join(truth, on="time_utc")
    normal = _query(inline_db, query, {"w": wagon}).join(truth, on="time_utc")
    window = pl.col("time_utc").is_between(start + dt.timedelta(seconds=1), end)
    frozen = est.filter(window)
    assert frozen.height > 1500
    assert frozen["true_c"].max() > stuck_c + 30  # the block heats while the reading sticks
    # the stuck readings skipped the update
    assert frozen["innovation_k"].null_count() == frozen.height
    # no dip: the smoothed and the live estimates hold the truth within their bands
    true = frozen["true_c"].to_numpy()
    for prefix in ("", "smoothed_"):
        mean = frozen[f"{prefix}contact_mean_c"].to_numpy()
        half = (
            (frozen[f"{prefix}contact_mean_hi_c"] - frozen[f"{prefix}contact_mean_lo_c"]) / 2
        ).to_numpy()
        assert float(np.mean(np.abs(mean - true) <= half + 0.5)) > 0.95, prefix
        assert float(mean.min()) > float(true.min()) - 5.0, prefix

    # the band widens while blind: wider than before it and than with the readings
    def half_width(frame: pl.DataFrame) -> float:
        return float(((frame["contact_mean_hi_c"] - frame["contact_mean_lo_c"]) / 2).median())

    before = est.filter(pl.col("time_utc").is_between(start - dt.timedelta(hours=1), start))
    assert half_width(frozen) > 1.5 * half_width(before)
    assert half_width(frozen) > 1.5 * half_width(normal.filter(window))
    # and the flag still fires, on the same readings
    flags = _query(
        db,
        "SELECT * FROM flags WHERE wagon_id = $w AND kind = 'sensor_fault' "
        "AND start_utc < $end AND end_utc > $start",
        {"w": wagon, "start": start, "end": end},
    )
    assert flags.height >= 1 and any("frozen" in e for e in flags["evidence"]), flags


def test_a_full_fe_fleets_dragging_brake_shows_as_unexplained_power(
    full_fleet: Path, full_db: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    """The drag check on a fleet the full FE model wrote (the stage estimates with the reduced
    one), and a second run adds nothing there either."""
    _assert_drag_found(full_fleet, full_db)
    before = _tables(full_db)
    again = _run(full_fleet, full_db, InlineEngine(), rom_refinement, rom_cache_dir)
    assert again.estimation is not None and again.estimation.wagons_estimated == []
    assert _tables(full_db)["contact_estimates"].equals(before["contact_estimates"])


def test_identity_on_a_full_fe_fleet_following_the_declared_model(
    tmp_path: Path,
    rom_refinement: float,
    rom_cache_dir: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The identity check with the readings of the full FE model on the reduced model's own
    mesh (not reduced, integrated in time): the estimate is its contact temperature within
    the band and the FE model's distance from the reduced one (up to 0.3 K at a hard
    braking's peak on the face, within 0.01 K at the seat).

    Written at the model's mesh because the defaults have σ_q 0.03 W/√s and the braking's power
    ``P_b`` (docs/estimator.md, "How each noise is set"): the 409-node mesh of
    ``FE_REFINEMENT`` (0.2) puts its own error of 0.1-0.2 K at the seat in hard brakings,
    which the tight quiet noise then follows into the face (with the defaults there: 48 s
    outside the band + 0.5 K, by up to 0.37 K; the power band holding 0 for 0.948 / 0.900 of
    the seconds; at 0.6: 0 s, 0.993 / 0.988), as the acceptance fleets and the drag day of
    ``test_estimator`` are written at the model's mesh for the same reason."""
    from fleetbrake.model.fullmodel import FullModelRunner

    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    root = tmp_path / "fleet"

    def writer(wagon: Any) -> FullModelRunner:
        return FullModelRunner.for_wagon(wagon, refinement=rom_refinement)

    _generate_declared(root, writer, "full", refinement=rom_refinement)
    _assert_identity(root, tmp_path, rom_refinement, rom_cache_dir, model_error_k=0.5)
