"""``bench flags``: fleets generated with and without anomalies, run and scored per class."""

from __future__ import annotations

import json

import pytest

from fleetbrake.bench import BenchConfigError
from fleetbrake.bench.flags import bench_flags, print_figures
from fleetbrake.synth.scoring import SCORED_KINDS


def test_bench_flags_scores_fleets_with_and_without_anomalies(
    tmp_path, rom_cache_dir, rom_refinement, monkeypatch
):
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    figures = bench_flags(
        1, 1, wagons=4, days=1, seed=3, refinement=rom_refinement, workdir=tmp_path, workers=1
    )
    assert json.loads(json.dumps(figures)) == figures
    assert [f["anomalies"] for f in figures["per_fleet"]] == [True, False]
    dirty, clean = figures["per_fleet"]
    assert sum(k["anomalies"] for k in dirty["by_kind"].values()) > 0
    assert sum(k["anomalies"] for k in clean["by_kind"].values()) == 0
    assert set(figures["classes"]) == set(SCORED_KINDS)
    for kind, c in figures["classes"].items():
        found = dirty["by_kind"][kind]
        assert c["recall"] == (
            round(found["found"] / found["anomalies"], 3) if found["anomalies"] else 1.0
        )
        assert len(found["delays_s"]) == found["found"]
        assert all(d >= 0 for d in found["delays_s"])
        assert c["false_per_100_wagon_days"] == round(
            100.0 * clean["by_kind"][kind]["flags"] / clean["wagon_days"], 2
        )
    lines: list[str] = []
    print_figures(figures, lines.append)
    assert "weak_brake" in lines[0] and "false per 100" in lines[0]
    assert not list(tmp_path.iterdir())  # the fleets and databases are removed


def test_bench_flags_refuses_what_it_cannot_do():
    with pytest.raises(BenchConfigError, match="fleets must be >= 1"):
        bench_flags(0)
    with pytest.raises(BenchConfigError, match="solver"):
        bench_flags(solver="fem")
