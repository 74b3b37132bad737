"""``fleetbrake bench fleet`` on 2 wagon-days: the figures of a run, the fleet generated in a
process of its own (its memory is not the writer's) and reused when given again."""

from __future__ import annotations

import resource
from pathlib import Path

import pytest

from fleetbrake.bench.fleet import bench_fleet


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def test_bench_fleet_generates_the_fleet_in_a_child_then_reuses_it(
    tmp_path: Path, rom_cache_dir: Path, rom_refinement: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("psutil")
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    fleet = tmp_path / "fleet"
    # one worker: the run is inline, so the only child this process waits for is the generator
    before = _children_cpu_s()
    first = bench_fleet(
        2, 1, fleet_dir=fleet, workdir=tmp_path, refinement=rom_refinement, workers=1
    )
    generated_cpu_s = _children_cpu_s() - before
    assert (fleet / "fleet.toml").is_file()
    assert generated_cpu_s > 0.5  # the generator ran (imports and all) in a child
    assert first["wagon_days"] == 2 and first["rows"] > 0 and first["events_simulated"] > 0
    assert first["peak_rss_mb"] >= max(w for w, _ in first["peak_rss_by_stage_mb"].values()) - 1

    before = _children_cpu_s()
    again = bench_fleet(
        2, 1, fleet_dir=fleet, workdir=tmp_path, refinement=rom_refinement, workers=1
    )
    assert _children_cpu_s() - before < 0.5 * generated_cpu_s  # reused, not generated again
    for key in ("rows", "events", "events_simulated", "prediction_rows", "flags"):
        assert again[key] == first[key], key
