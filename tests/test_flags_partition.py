"""The flags are partition-local: a wagon's flags are a function of its own data and the
model revision only, so another wagon's data (a late file, a bad fit) cannot move them."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import polars as pl
import pytest

from fleetbrake.flags import raise_flags, wagon_residual_spread
from fleetbrake.flags.wagon import RESIDUAL_MIN_READINGS


def _windows(rms_by_event: dict[int, float], readings: int) -> pl.DataFrame:
    rows = []
    for event_id, rms in rms_by_event.items():
        for k in range(readings):
            sign = 1.0 if k % 2 else -1.0
            rows.append(
                {
                    "event_id": event_id,
                    "measured_sensor_c": 50.0 + sign * rms,
                    "predicted_sensor_c": 50.0,
                }
            )
    return pl.DataFrame(rows)


def test_the_wagon_spread_is_a_median_of_its_brakings() -> None:
    n = RESIDUAL_MIN_READINGS
    # one weak braking far off its prediction does not raise the spread
    assert wagon_residual_spread(_windows({1: 0.1, 2: 0.1, 3: 5.0}, n)) == pytest.approx(0.1)
    # brakings with too few readings do not count; none left: no spread
    assert wagon_residual_spread(_windows({1: 0.2}, n - 1)) is None
    assert wagon_residual_spread(_windows({}, n)) is None


def test_another_wagons_residual_leaves_a_wagons_flags_byte_identical(
    tmp_path: Path,
    reduced_model_for: Callable[..., object],
    rom_cache_dir: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from conftest import TEST_REFINEMENT
    from fleetbrake.ingest.files import load_fleet_registry, run_ingest
    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.simulation.predictions import (
        current_revision,
        simulate_events,
    )
    from fleetbrake.synth.generator import SynthConfig, generate_fleet
    from fleetbrake.warehouse.connection import open_warehouse

    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    generate_fleet(
        tmp_path / "fleet",
        SynthConfig(wagons=2, days=1, seed=11, anomalies=True),
        rom=reduced_model_for,
    )
    run_ingest(tmp_path / "fleet", tmp_path / "fleet.duckdb", progress=False)
    registry = load_fleet_registry(tmp_path / "fleet")
    query = (
        "SELECT flag_id, kind, severity, start_utc, end_utc, evidence, detected_utc "
        "FROM flags WHERE wagon_id = $w ORDER BY flag_id"
    )
    with open_warehouse(tmp_path / "fleet.duckdb") as wh:
        simulate_events(
            wh,
            registry,
            current_revision(wh, refinement=TEST_REFINEMENT),
            SimulationConfig(refinement=TEST_REFINEMENT),
            progress=False,
        )
        a, b = sorted(registry.wagons)[:2]
        raise_flags(wh, registry, "declared")
        before = wh.con.execute(query, {"w": a}).fetchall()
        spread_a = raise_flags(wh, registry, "declared", wagons=[a]).residual_spread_k
        assert spread_a is not None
        # wagon B's data now far from the revision's predictions (as a late file of a
        # wagon the model fits badly would make it): the fleet's median residual moves
        wh.con.execute(
            "UPDATE predictions SET measured_sensor_c = measured_sensor_c + 8.0 "
            "WHERE wagon_id = $w",
            {"w": b},
        )
        raise_flags(wh, registry, "declared")
        assert wh.con.execute(query, {"w": a}).fetchall() == before
        assert raise_flags(wh, registry, "declared", wagons=[a]).residual_spread_k == spread_a
        assert raise_flags(wh, registry, "declared", wagons=[b]).residual_spread_k > spread_a
