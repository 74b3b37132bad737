"""The solver benchmark (its figures are in docs/benchmarks.md).

On a small problem, both engines run in their children and solve the same problem, and the
table prints. With scripted children (no solver runs), what the benchmark decides: each
engine's figures are those of its own fastest run, the traffic bound counts the bytes of the
precision the solves actually read, and bad settings or a missing peer end in one line and
exit code 2.
"""

from __future__ import annotations

import sys
from typing import Any

import pytest
from typer.testing import CliRunner

from fleetbrake.bench import BenchConfigError, BenchExtraMissingError
from fleetbrake.bench import solver as bench
from fleetbrake.bench.solver import bench_solver, print_table
from fleetbrake.cli.main import app


@pytest.fixture(scope="module")
def figures():
    return bench_solver(element="hex8", steps=240, refinement=0.5, precision="mixed", repeats=2)


def test_both_engines_solve_the_same_problem(figures):
    assert figures["nodes"] == figures["skfem_nodes"]
    assert figures["precision"] == "mixed"
    # hex8: the same trilinear geometry and scheme, so only the solves' rounding differs
    # (the single-precision factor values: of order 1e-8 K)
    assert figures["sensor_max_abs_diff_k"] < 1e-6
    diff_vs_double = figures["sensor_max_abs_diff_vs_double_k"]
    assert diff_vs_double < 1e-6
    # a simplicial factor (this small mesh, when faer picks it) is solved in double anyway
    assert (diff_vs_double > 0.0) == figures["supernodal"]
    assert figures["sensor_peak_c"] > 23.0
    assert figures["factorizations"] == 1  # the damped start shares Crank-Nicolson's factor
    assert len(figures["seconds_total_runs"]) == len(figures["skfem_seconds_total_runs"]) == 2


def test_the_table_prints(figures, capsys):
    print_table(figures)
    out = capsys.readouterr().out
    assert "speedup vs scikit-fem" in out
    assert "double precision, same run" in out


# --------------------------------------------------------------------------------------------
# Scripted children: what the parent makes of their figures


def _ours(run: int, seconds_total: float, *, supernodal: bool = True) -> dict[str, Any]:
    return {
        "run": run,
        "nodes": 1000,
        "element": "hex8",
        "ordering": None,
        "matrix_nnz": 20_000,
        "factor_nnz": 1_000_000,
        "supernodal": supernodal,
        "factorizations": 1,
        "seconds_mesh_assembly": 0.1,
        "seconds_factorization": 0.1,
        "seconds_stepping": seconds_total / 2,
        "seconds_total": seconds_total,
        "cpu_seconds": seconds_total,
        "cpu_seconds_simulate": seconds_total,
        "peak_rss_mb": 100.0 + run,
        "rss_before_mb": 50.0,
        "sensor_c": [23.0, 24.0, 23.5],
        "precision": "mixed",
        "seconds_stepping_double": 1.0,
        "sensor_max_abs_diff_vs_double_k": 1e-9,
    }


def _skfem(run: int, seconds_total: float) -> dict[str, Any]:
    return {
        "run": run,
        "nodes": 1000,
        "solver": "splu",
        "factorizations": 1,
        "seconds_mesh_assembly": 0.2,
        "seconds_factorization": 0.2,
        "seconds_stepping": seconds_total / 2,
        "seconds_total": seconds_total,
        "cpu_seconds": seconds_total,
        "cpu_seconds_simulate": seconds_total,
        "peak_rss_mb": 200.0 + run,
        "rss_before_mb": 60.0,
        "sensor_c": [23.0, 24.0, 23.5],
    }


@pytest.fixture
def scripted(monkeypatch: pytest.MonkeyPatch):
    """``script(ours_totals, skfem_totals, supernodal)``: the children return these totals,
    run after run; the bandwidth probe says 10 GB/s."""

    def script(
        ours_totals: list[float], skfem_totals: list[float], supernodal: bool = True
    ) -> list[str]:
        calls: list[str] = []
        runs = {"ours": iter(enumerate(ours_totals)), "skfem": iter(enumerate(skfem_totals))}

        def child(args: list[str]) -> dict[str, Any]:
            engine = args[args.index("--engine") + 1]
            calls.append(engine)
            run, total = next(runs[engine])
            if engine == "ours":
                return _ours(run, total, supernodal=supernodal)
            return _skfem(run, total)

        monkeypatch.setattr(bench, "_run_child", child)
        monkeypatch.setattr(bench, "read_bandwidth_gb_s", lambda *a, **k: 10.0)
        return calls

    return script


def test_each_engine_reports_its_own_fastest_run(scripted):
    calls = scripted([3.0, 1.0, 2.0], [4.0, 6.0, 5.0])
    figures = bench_solver(element="hex8", repeats=3)
    assert calls == ["ours", "skfem"] * 3  # alternately
    # ours: the second run (1.0 s), all its figures; scikit-fem: its first (4.0 s)
    assert figures["seconds_total"] == 1.0
    assert figures["peak_rss_mb"] == 101.0
    assert figures["skfem_seconds_total"] == 4.0
    assert figures["skfem_peak_rss_mb"] == 200.0
    assert figures["seconds_total_runs"] == [3.0, 1.0, 2.0]
    assert figures["skfem_seconds_total_runs"] == [4.0, 6.0, 5.0]
    assert figures["speedup_vs_scikit_fem"] == 4.0
    assert figures["speedup_vs_scikit_fem_median"] == 2.5  # medians 5.0 and 2.0


def test_the_bound_counts_single_precision_values_of_a_supernodal_factor(scripted):
    scripted([1.0], [2.0], supernodal=True)
    figures = bench_solver(element="hex8", precision="mixed", repeats=1)
    # two triangular solves over 1e6 factor entries of 4 bytes (+ 8-byte row indices)
    assert figures["bytes_per_step_values"] == 8_000_000
    assert figures["bytes_per_step_values_indices"] == 24_000_000
    assert figures["bound_s_values"] == pytest.approx(0.0008)  # 8 MB at 10 GB/s


def test_the_bound_counts_double_values_of_a_simplicial_factor(scripted):
    # faer solves a simplicial factor in double precision whatever was asked
    scripted([1.0], [2.0], supernodal=False)
    figures = bench_solver(element="hex8", precision="mixed", repeats=1)
    assert figures["bytes_per_step_values"] == 16_000_000
    assert figures["bound_s_values"] == pytest.approx(0.0016)


def test_bad_arguments_are_refused():
    with pytest.raises(BenchConfigError, match="precision must be one of"):
        bench_solver(precision="half")
    with pytest.raises(BenchConfigError, match="repeats must be >= 1"):
        bench_solver(repeats=0)
    result = CliRunner().invoke(app, ["bench", "solver", "--element", "hex27"])
    assert result.exit_code == 2
    assert result.stderr.strip() == (
        "fleetbrake bench solver: element must be one of ('hex8', 'hex20'), got 'hex27'"
    )


def test_without_the_bench_extra_it_says_what_to_install(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setitem(sys.modules, "skfem", None)  # as if scikit-fem were not installed
    with pytest.raises(BenchExtraMissingError, match=r"fleetbrake\[bench\]"):
        bench_solver(element="hex8", repeats=1)
    result = CliRunner().invoke(app, ["bench", "solver"])
    assert result.exit_code == 2
    assert len(result.stderr.strip().splitlines()) == 1
    assert "skfem" in result.stderr and 'pip install "fleetbrake[bench]"' in result.stderr
