"""``fleetbrake bench watch`` on a tiny setting: it runs the service in a process of its own,
drops the files, and prints every figure (no timing is asserted)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from fleetbrake.bench import watch as bench_watch_module


def _child_env(cache_dir: Path) -> dict[str, str]:
    """The environment of a child python that imports this fleetbrake, with the session's
    reduced-model cache."""
    package_root = str(Path(bench_watch_module.__file__).resolve().parents[2])
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([package_root, os.environ.get("PYTHONPATH", "")]),
        "FLEETBRAKE_CACHE_DIR": str(cache_dir),
        "RAYON_NUM_THREADS": "1",
    }


def _bench(tmp_path: Path, cache_dir: Path, *args: str) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "fleetbrake.cli.main", "bench", "watch", "--json"]
    command += ["--workdir", str(tmp_path), *args]
    return subprocess.run(
        command, capture_output=True, text=True, timeout=600, env=_child_env(cache_dir)
    )


def test_bench_watch_prints_each_file_and_its_figures_as_json_last(
    tmp_path: Path, rom_cache_dir: Path, rom_refinement: float
) -> None:
    log, fleet = tmp_path / "service.log", tmp_path / "fleet"
    result = _bench(
        tmp_path,
        rom_cache_dir,
        *("--wagons", "2", "--files", "3", "--rate", "60", "--idle", "0.5", "--fleet", str(fleet)),
        *("--refinement", str(rom_refinement), "--workers", "2", "--service-log", str(log)),
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    figures = json.loads(lines[-1])
    for key in (
        "p50_s",
        "p95_s",
        "max_s",
        "files",
        "rate_per_min",
        "idle_cpu_percent",
        "units",
        "unit_stage_s_mean",
        "queryable",
        "history_files",
        "load_avg_1min_at_start",
    ):
        assert key in figures, key
    assert figures["benchmark"] == "watch"
    assert figures["files"] == figures["files_queryable"] == 3
    assert figures["files_not_reported"] == 0 and figures["complete"] is True
    assert figures["rate_per_min"] == 60.0
    assert figures["service_exit_code"] == 0
    assert figures["idle_cpu_percent"] >= 0
    assert 1 <= figures["units"] <= 3  # units that stored files
    assert figures["units_empty"] >= 0
    assert figures["history_files"] > 0
    per_file = figures["per_file"]
    assert len(per_file) == 3
    for item in per_file:
        assert item["status"] == "ingested"
        assert item["rows"] > 1800  # a one-hour file (at least half an hour of samples)
        assert item["latency_s"] is not None and item["latency_s"] >= 0
        assert item["path"].startswith(f"logs/{item['wagon']}/{item['wagon']}_")
        assert any(line.startswith(f"{item['path']}: ") for line in lines[:-1])
    assert any("p95" in line for line in lines[:-1])
    assert "watching " in log.read_text()  # the service's own log, kept
    assert (fleet / "fleet.toml").is_file() and (fleet / "truth").is_dir()  # kept
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "fleet",
        "service.log",
    ]  # the rest removed


def test_bench_watch_refuses_a_bad_setting_before_any_work(
    tmp_path: Path, rom_cache_dir: Path
) -> None:
    for args, named in ((("--rate", "0"), "rate"), (("--files", "0"), "files")):
        result = _bench(tmp_path, rom_cache_dir, *args)
        assert result.returncode == 2, result.stderr
        assert named in result.stderr
    assert list(tmp_path.iterdir()) == []
