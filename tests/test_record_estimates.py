"""`fleetbrake record` over compacted contact estimates (interface v3): the recording shows
per-second estimates over the whole range, recomputed where the warehouse holds minute rows,
equal to the per-second rows the estimation stage stored (the estimator is deterministic)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from rerun.chunk import RrdReader

from conftest import TEST_REFINEMENT
from fleetbrake.fleet.registry import load_registry
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import run_ingest
from fleetbrake.simulation.estimates import EstimationConfig, estimate_wagons
from fleetbrake.simulation.predictions import ensure_declared, revision, store_registry
from fleetbrake.viz.entities import ESTIMATE_HI, ESTIMATE_MEAN, POWER, TIMELINE
from fleetbrake.viz.record import record
from fleetbrake.warehouse.connection import open_warehouse
from fleetbrake.warehouse.estimate_windows import compact_estimates
from fleetgen import T0_UTC, simple_session, write_registry, write_session

WAGON = "SGG-0001"
ROWS = 2 * 3600
FLAG = (T0_UTC + dt.timedelta(minutes=50), T0_UTC + dt.timedelta(minutes=55))
SERIES = {
    ESTIMATE_MEAN: "contact_mean_c",
    ESTIMATE_HI: "contact_mean_hi_c",
    POWER: "unexplained_power_w",
}


@pytest.fixture(scope="module")
def compacted(tmp_path_factory: pytest.TempPathFactory, rom_cache_dir: Path) -> dict[str, object]:
    """Two quiet hours of one wagon (no braking, the block at the air's temperature) estimated per second, a
    flag of five minutes in the middle, then compacted: the per-second rows as stored before
    the compaction, and the database."""
    root = tmp_path_factory.mktemp("record_estimates")
    fleet = root / "fleet"
    write_registry(fleet, [WAGON])
    rng = np.random.default_rng(3)
    quiet = simple_session(rows=ROWS).with_columns(
        brake_pressure_bar=pl.lit(0.0),
        block_temp_c=pl.Series(np.round(10.0 + rng.normal(0.0, 0.1, ROWS), 1)),
    )
    write_session(fleet, WAGON, quiet, T0_UTC)
    db = root / "fleet.duckdb"
    run_ingest(fleet, db, config=IngestConfig(), progress=False)
    registry = load_registry(fleet / "fleet.toml")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        with open_warehouse(db) as wh:
            ensure_declared(wh, refinement=TEST_REFINEMENT)
            store_registry(wh, registry)
            estimate_wagons(wh, registry, revision(wh, "declared"), EstimationConfig())
            seconds = wh.con.sql("SELECT * FROM v_contact_estimates ORDER BY time_utc").pl()
            wh.con.execute(
                "INSERT INTO flags VALUES ('F1', $w, NULL, 'sensor_fault', 'warning', $a, $b, "
                "'a test flag', $a)",
                {"w": WAGON, "a": FLAG[0], "b": FLAG[1]},
            )
            done = compact_estimates(wh.con, [(WAGON, None, None)], "declared")
            stored = wh.con.sql("SELECT * FROM v_contact_estimates ORDER BY time_utc").pl()
    return {"db": db, "seconds": seconds, "stored": stored, "done": done}


def _series(path: Path, entity: str) -> tuple[np.ndarray, np.ndarray]:
    times: list[np.ndarray] = []
    values: list[np.ndarray] = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path != f"/{entity}" or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        scalars = batch.column("Scalars:scalars").to_pylist()
        keep = np.array([v is not None for v in scalars], dtype=bool)
        times.append(batch.column(TIMELINE).to_numpy()[keep].astype("datetime64[us]"))
        values.append(np.array([v[0] for v in scalars if v is not None], dtype=np.float64))
    order = np.argsort(np.concatenate(times), kind="stable")
    return np.concatenate(times)[order], np.concatenate(values)[order]


def test_the_compaction_left_minute_rows_and_the_flags_seconds(
    compacted: dict[str, object],
) -> None:
    stored = compacted["stored"]
    assert isinstance(stored, pl.DataFrame)
    per_second = stored.filter(pl.col("resolution_s") == 1)
    assert per_second.height > 0 and stored.filter(pl.col("resolution_s") == 60).height > 60
    assert per_second["time_utc"].min() <= FLAG[0] - dt.timedelta(seconds=60)
    assert per_second["time_utc"].max() >= FLAG[1] + dt.timedelta(seconds=60)


def test_record_shows_every_second_as_the_stage_estimated_it(
    compacted: dict[str, object], tmp_path: Path
) -> None:
    out = tmp_path / "wagon.rrd"
    summary = record(compacted["db"], WAGON, out)  # type: ignore[arg-type]
    assert any("recomputed per second" in note for note in summary.notes)
    seconds, stored = compacted["seconds"], compacted["stored"]
    assert isinstance(seconds, pl.DataFrame) and isinstance(stored, pl.DataFrame)
    expected_times = seconds["time_utc"].to_numpy().astype("datetime64[us]")
    kept = stored.filter(pl.col("resolution_s") == 1)
    for entity, column in SERIES.items():
        times, values = _series(out, entity)
        assert times.size == seconds.height, entity
        np.testing.assert_array_equal(times, expected_times)
        np.testing.assert_allclose(values, seconds[column].to_numpy(), rtol=0, atol=1e-9)
        # the rows stored per second, inside the windows, are the recording's there
        inside = np.isin(times, kept["time_utc"].to_numpy().astype("datetime64[us]"))
        np.testing.assert_allclose(values[inside], kept[column].to_numpy(), rtol=0, atol=1e-9)
