"""Estimates are kept for `declared` and for the revision the last close-loop recorded (the
current one): storing a newer revision's estimates of a wagon deletes the wagon's estimates of
the older closed-loop revisions (interface v3); the migration to schema version 3 keeps the
same."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pyarrow as pa

from fleetbrake.model.estimator import EstimatorNoise
from fleetbrake.simulation.estimates import EstimateResult, replace_estimates
from fleetbrake.simulation.estimates.rows import ROWS_SCHEMA
from fleetbrake.warehouse.connection import Warehouse, open_warehouse

T0 = dt.datetime(2024, 3, 1, 8, 0, 0)
WAGONS = ("RW-0001", "RW-0002")


def _rows(wagon_id: str, revision: str, n: int = 30) -> pa.Table:
    values = {
        name: pa.array(np.full(n, 20.0), pa.float64())
        for name in ROWS_SCHEMA.names
        if name not in ("wagon_id", "time_utc", "model_revision")
    }
    values["wagon_id"] = pa.array([wagon_id] * n, pa.large_string())
    values["model_revision"] = pa.array([revision] * n, pa.large_string())
    values["time_utc"] = pa.array(
        [T0 + dt.timedelta(seconds=k) for k in range(n)], pa.timestamp("us")
    )
    return pa.table([values[name] for name in ROWS_SCHEMA.names], schema=ROWS_SCHEMA)


def _result(wagon_id: str, revision: str) -> EstimateResult:
    return EstimateResult(
        wagon_id, revision, "data", "model", _rows(wagon_id, revision), 0.0, EstimatorNoise()
    )


def _record_revision(wh: Warehouse, name: str, parent: str | None) -> None:
    """``name`` recorded as the current revision, as the close loop records one."""
    with wh.transaction() as con:
        con.execute("UPDATE model_revisions SET is_current = FALSE")
        con.execute(
            "INSERT INTO model_revisions VALUES ($n, $p, NULL, '{}', NULL, NULL, 'rom', TRUE, "
            "$t, NULL)",
            {"n": name, "p": parent, "t": T0},
        )


def stored(wh: Warehouse) -> dict[tuple[str, str], int]:
    rows = wh.con.execute(
        "SELECT wagon_id, model_revision, count(*) FROM contact_estimates GROUP BY ALL"
    ).fetchall()
    return {(w, r): int(n) for w, r, n in rows}


def test_a_newer_revisions_estimates_replace_the_olders(tmp_path: Path) -> None:
    with open_warehouse(tmp_path / "fleet.duckdb") as wh:
        _record_revision(wh, "declared", None)
        replace_estimates(wh, "declared", [_result(w, "declared") for w in WAGONS], delete=False)
        _record_revision(wh, "r1-a", "declared")
        replace_estimates(wh, "r1-a", [_result(w, "r1-a") for w in WAGONS], delete=False)
        assert set(stored(wh)) == {(w, r) for w in WAGONS for r in ("declared", "r1-a")}

        _record_revision(wh, "r2-b", "r1-a")
        replace_estimates(wh, "r2-b", [_result(WAGONS[0], "r2-b")], delete=False)
        assert set(stored(wh)) == {
            (WAGONS[0], "declared"),
            (WAGONS[0], "r2-b"),
            (WAGONS[1], "declared"),
            (WAGONS[1], "r1-a"),  # not estimated with r2-b yet: kept until it is
        }
        replace_estimates(wh, "r2-b", [_result(WAGONS[1], "r2-b")], delete=False)
        assert set(stored(wh)) == {(w, r) for w in WAGONS for r in ("declared", "r2-b")}

        # estimating `declared` again leaves the current revision's estimates
        replace_estimates(wh, "declared", [_result(w, "declared") for w in WAGONS])
        assert set(stored(wh)) == {(w, r) for w in WAGONS for r in ("declared", "r2-b")}
        assert all(n == 30 for n in stored(wh).values())
