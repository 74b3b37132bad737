"""The close loop's making of a revision (``closeloop.revision.make_revision``): the
simulation on a second connection in a thread of its own while σ_w is fitted and the wagons
are estimated stores what the three steps one after the other store, table for table (the
revision's predictions, timeline, segments, stamps, σ_w and every row of
``contact_estimates``), in this process and on the local engine's workers; an error of either
side is raised, the other side having finished."""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import polars as pl
import pytest

from conftest import TEST_REFINEMENT
from conftest import RunFleet as Fleet
from fleetbrake.closeloop import revision
from fleetbrake.closeloop.candidates import Candidate
from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.evidence import event_sets
from fleetbrake.closeloop.revision import record_revision
from fleetbrake.engine import LocalEngine
from fleetbrake.model.effects import ConvectionSpeed, EffectSet
from fleetbrake.simulation.estimates import EstimationConfig, estimate_wagons, fit_revision_noise
from fleetbrake.simulation.predictions import (
    Revision,
    current_revision,
    simulate_events,
    stored_wagons,
)
from fleetbrake.warehouse.connection import open_warehouse, sql

START = dt.date(2024, 3, 4)
HOLDOUT = START + dt.timedelta(days=1)
EFFECTS = EffectSet((ConvectionSpeed(gain=2.0, exponent=0.8),))


@pytest.fixture(scope="module")
def fleet(convection_fleet: Fleet) -> Fleet:
    """``conftest.convection_fleet``: the close loop's small fleet, run."""
    return convection_fleet


@pytest.fixture
def rom_env(monkeypatch: pytest.MonkeyPatch, rom_cache_dir: Path) -> None:
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))


TABLES = {
    "predictions": "SELECT * FROM predictions WHERE model_revision = $r "
    "ORDER BY event_id, time_utc",
    "timeline": "SELECT * FROM timeline WHERE model_revision = $r ORDER BY wagon_id, time_utc",
    "simulated_spans": "SELECT * EXCLUDE (simulated_utc) FROM simulated_spans "
    "WHERE model_revision = $r ORDER BY wagon_id, span_start_utc",
    "contact_estimates": "SELECT * FROM contact_estimates WHERE model_revision = $r "
    "ORDER BY wagon_id, time_utc",
    "estimated_spans": "SELECT * EXCLUDE (created_utc) FROM estimated_spans "
    "WHERE model_revision = $r ORDER BY wagon_id, span_start_utc",
    "estimator_noise": "SELECT * EXCLUDE (created_utc) FROM estimator_noise "
    "WHERE model_revision = $r",
}


def _stored(db: Path, revision: str) -> dict[str, pl.DataFrame]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return {name: con.sql(q, params={"r": revision}).pl() for name, q in TABLES.items()}
    finally:
        con.close()


def _make(fleet: Fleet, db: Path, engine: Any, *, together: bool) -> str:
    """A copy of the fleet's database given a convection revision, made by ``make_revision``
    (``together``) or by its three steps one after the other."""
    shutil.copy(fleet.db, db)
    sim = fleet.simulation
    config = CloseLoopConfig(HOLDOUT, simulation=sim)
    with open_warehouse(db) as wh:
        wagons = stored_wagons(wh)
        base = current_revision(wh, refinement=TEST_REFINEMENT)
        fit, _, _ = event_sets(wh, base.name, config)
        events = wh.con.sql(sql("q_closeloop_events")).pl()["event_id"].to_list()
        name = "r1-convection_speed"
        record_revision(wh, name, base, Candidate(EFFECTS, 0.0, 0.0, 2))
        rev = Revision(name, EFFECTS, base.solver, base.refinement)
        assert fit.height > 5 and len(events) > fit.height
        if together:
            revision.make_revision(wh, wagons, rev, sim, events, fit, engine)
        else:
            estimation = EstimationConfig(chain=sim.chain)
            simulate_events(wh, wagons, rev, sim, event_ids=events, engine=engine)
            fit_revision_noise(wh, wagons, rev, fit, estimation, engine=engine)
            estimate_wagons(wh, wagons, rev, estimation, engine=engine)
    return name


@pytest.mark.usefixtures("rom_env")
@pytest.mark.parametrize("engine_name", ["inline", "local"])
def test_the_revision_made_together_is_the_three_steps_one_after_the_other(
    fleet: Fleet, tmp_path: Path, engine_name: str
) -> None:
    engine = LocalEngine(2) if engine_name == "local" else None
    try:
        name = _make(fleet, tmp_path / "apart.duckdb", engine, together=False)
        _make(fleet, tmp_path / "together.duckdb", engine, together=True)
    finally:
        if engine is not None:
            engine.close()
    apart = _stored(tmp_path / "apart.duckdb", name)
    together = _stored(tmp_path / "together.duckdb", name)
    for table in TABLES:
        assert apart[table].height > 0, table
        assert together[table].columns == apart[table].columns, table
        assert together[table].height == apart[table].height, table
    # the estimator's rows: every column to 1e-9 (K, W), nulls where they were
    want, got = apart["contact_estimates"], together["contact_estimates"]
    for column, kind in want.schema.items():
        if kind == pl.Float64:
            a, b = want[column].to_numpy(), got[column].to_numpy()
            assert np.array_equal(np.isnan(a), np.isnan(b)), column
            ok = ~np.isnan(a)
            assert np.max(np.abs(a[ok] - b[ok]), initial=0.0) <= 1e-9, column
        else:
            assert got[column].equals(want[column]), column
    # the rest the same rows exactly (the same pure functions of the same partitions)
    for table in TABLES:
        assert together[table].equals(apart[table]), table


@pytest.mark.usefixtures("rom_env")
@pytest.mark.parametrize("failing", ["simulate_events", "estimate_wagons"])
def test_an_error_on_either_side_is_raised_after_the_other_ended(
    fleet: Fleet, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failing: str
) -> None:
    """The side that fails raises its error from ``make_revision``; the other ran to its
    end first (its rows are stored: no thread left writing)."""
    real = getattr(revision, failing)

    def fails(*args: Any, **kwargs: Any) -> None:
        raise RuntimeError(f"{failing} failed")

    monkeypatch.setattr(revision, failing, fails)
    with pytest.raises(RuntimeError, match=f"{failing} failed"):
        _make(fleet, tmp_path / "fails.duckdb", None, together=True)
    monkeypatch.setattr(revision, failing, real)
    stored = _stored(tmp_path / "fails.duckdb", "r1-convection_speed")
    other = "contact_estimates" if failing == "simulate_events" else "timeline"
    assert stored[other].height > 0
