"""The solver benchmark's plumbing on a small problem (its figures are in docs/benchmarks.md):
both engines run in their children, the figures come back complete and consistent, and the
table prints."""

from __future__ import annotations

import pytest

from fleetbrake.bench.solver import bench_solver, print_table


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


def test_each_engine_reports_its_fastest_run(figures):
    assert figures["repeats"] == 2
    assert figures["seconds_total"] == min(figures["seconds_total_runs"])
    assert figures["skfem_seconds_total"] == min(figures["skfem_seconds_total_runs"])
    assert figures["speedup_vs_scikit_fem_median"] > 0.0


def test_the_figures_add_up(figures):
    assert figures["factorizations"] == 1  # the damped start shares Crank-Nicolson's factor
    parts = (
        figures["seconds_mesh_assembly"]
        + figures["seconds_factorization"]
        + figures["seconds_stepping"]
    )
    assert parts <= figures["seconds_total"] * 1.001
    assert figures["seconds_stepping_double"] > 0.0
    assert figures["speedup_vs_scikit_fem"] == pytest.approx(
        figures["skfem_seconds_total"] / figures["seconds_total"], rel=1e-3
    )
    # two solves a step, reading single-precision values (4 bytes) from a supernodal factor
    bytes_per_value = 4 if figures["supernodal"] else 8
    assert figures["bytes_per_step_values"] == 2 * figures["factor_nnz"] * bytes_per_value


def test_the_table_prints(figures, capsys):
    print_table(figures)
    out = capsys.readouterr().out
    assert "speedup vs scikit-fem" in out
    assert "double precision, same run" in out


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="precision must be one of"):
        bench_solver(precision="half")
    with pytest.raises(ValueError, match="repeats must be >= 1"):
        bench_solver(repeats=0)
