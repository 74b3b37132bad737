"""``fleetbrake bench incremental`` on 2 wagons x 3 days: each day landed and run into one
warehouse, which ends as a single run of all three days makes it (no timing is asserted)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import duckdb
import pytest
from typer.testing import CliRunner

from fleetbrake.cli.main import app

_VIEWS = ("v_files", "v_events", "v_predictions", "v_flags")


def _counts(db: Path) -> dict[str, int]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return {view: con.sql(f"SELECT count(*) FROM {view}").fetchall()[0][0] for view in _VIEWS}
    finally:
        con.close()


def test_bench_incremental_ends_with_the_warehouse_of_a_single_run(
    tmp_path: Path, rom_cache_dir: Path, rom_refinement: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("psutil")
    from fleetbrake.app.run import run_fleet
    from fleetbrake.simulation.config import SimulationConfig

    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    fleet, db = tmp_path / "fleet", tmp_path / "incremental.duckdb"
    args = ["-q", "bench", "incremental", "--json", "--wagons", "2", "--days", "3"]
    args += ["--refinement", str(rom_refinement), "--workers", "1", "--workdir", str(tmp_path)]
    result = CliRunner().invoke(app, [*args, "--fleet", str(fleet), "--db", str(db)])
    assert result.exit_code == 0, result.output
    lines = result.stdout.strip().splitlines()
    figures = json.loads(lines[-1])
    assert figures["benchmark"] == "incremental"
    assert len(figures["day_s"]) == 3 and all(s > 0 for s in figures["day_s"])
    assert math.isfinite(figures["last_over_first"])
    assert figures["last_over_first"] == round(figures["day_s"][2] / figures["day_s"][0], 3)
    assert figures["limit_last_over_first"] == 1.2
    for key in ("day_cpu_s", "day_rows", "day_files", "day_warehouse_mb"):
        assert len(figures[key]) == 3, key
    assert all(rows > 0 for rows in figures["day_rows"])
    assert all(files > 0 for files in figures["day_files"])  # landed that day
    assert figures["warehouse_mb"] > 0 and len(figures["load_avg_at_start"]) == 3
    assert any(line.startswith("day 3/3: ") for line in lines)
    assert any("day 3 / day 1" in line and "limit 1.2" in line for line in lines)
    assert {p.name for p in tmp_path.iterdir()} <= {"fleet", db.name, f"{db.name}.lock"}

    once = tmp_path / "once.duckdb"
    report = run_fleet(
        fleet,
        once,
        simulation=SimulationConfig(refinement=rom_refinement),
        progress=False,
        workers=1,
    )
    assert report.ingest.rows == figures["rows"] == sum(figures["day_rows"])
    assert _counts(db) == _counts(once)
    assert _counts(db)["v_files"] == sum(figures["day_files"])


def test_bench_incremental_refuses_a_bad_setting_before_any_work(tmp_path: Path) -> None:
    pytest.importorskip("psutil")
    taken = tmp_path / "taken.duckdb"
    taken.write_bytes(b"")
    for args, named in (
        (("--days", "0"), "days"),
        (("--wagons", "0"), "wagons"),
        (("--db", str(taken)), str(taken)),
    ):
        command = ["bench", "incremental", "--workdir", str(tmp_path), *args]
        result = CliRunner().invoke(app, command)
        assert result.exit_code == 2, result.output
        assert named in result.output
    assert [p.name for p in tmp_path.iterdir()] == ["taken.duckdb"]
