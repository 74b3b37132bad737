"""``fleetbrake bench solver``: the Rust block model against scikit-fem on the same problem.

The problem: the reference block (registry defaults) under the paper's manoeuvre A in the
declared model -- Phi_b of manoeuvre A for 47 s then 0, initial 23 C, ambient 10 C,
h = 10 W/m^2 K on "air" and "holder" -- Crank-Nicolson with the contract's default damping
(Rannacher half steps), ``steps`` steps of 1 s, the sensor seat as probe. Each engine runs in
its own child process (``python -m fleetbrake.bench.solver --engine ours|skfem --json-child``),
so that the peak resident memory (``resource.getrusage(RUSAGE_SELF).ru_maxrss``) is that
engine's alone:

- ours: ``BlockModel`` (mesh + assembly + symbolic analysis), then ``simulate`` (numeric
  Cholesky of the step matrix -- Crank-Nicolson's, which the damped start's backward-Euler
  half steps share -- and the time loop: a mat-vec and two triangular solves per step) with
  the factor's values read in ``precision`` ("mixed": single, the default; or "double");
  then the same run again with the other precision (factor cached: its stepping alone),
  so that both are timed side by side in one run;
- scikit-fem: ``SkfemBlockModel`` on OUR mesh arrays (written by the first child to a
  temporary ``.npz``) with its default, fastest solver (SuperLU, minimum-degree ordering of
  A^T + A, symmetric mode), each system matrix factorised once.

Imports are outside every timing. The parent measures the machine's single-core read
bandwidth (numpy sum over a 512 MB float64 array, best of 3) and from it the memory-traffic
bound of the two triangular solves of a step: 2 x nnz(L) x 4 or 8 bytes (the values in
the precision read) and 2 x nnz(L) x (that + 8) bytes (values + one 8-byte row index per
entry, as a simplicial CSC factor would read). See ``docs/benchmarks.md``.

The two engines run alternately ``repeats`` times (3 by default); each engine's figures are
those of its fastest run (a shared machine's neighbours only ever add time), every run's
total is reported beside them (``seconds_total_runs``, ``skfem_seconds_total_runs``) with
the ratio of the medians (``speedup_vs_scikit_fem_median``).

The figures come back as one flat dict (ours without prefix, scikit-fem's with ``skfem_``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from fleetbrake.bench import BenchConfigError, BenchError, require_extra

__all__ = [
    "CHOLESKY",
    "ELEMENTS",
    "PRECISIONS",
    "bench_solver",
    "print_table",
    "read_bandwidth_gb_s",
]

ELEMENTS = ("hex8", "hex20")
CHOLESKY = ("auto", "simplicial", "supernodal")
PRECISIONS = ("mixed", "double")
WAGON_ID = "BENCH-0001"
DT_S = 1.0
H_W_M2K = {"air": 10.0, "holder": 10.0}
AMBIENT_C = 10.0
BANDWIDTH_ARRAY_MB = 512
BYTES_VALUE = {"mixed": 4, "double": 8}
BYTES_INDEX = 8


def _peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (2^20 bytes; Linux gives KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _problem(steps: int) -> tuple[Any, np.ndarray, float]:
    """The wagon (registry defaults), the flux series of manoeuvre A and the initial C."""
    from fleetbrake.fleet.registry import WagonConfig
    from fleetbrake.model.physics import PAPER_MANOEUVRES, event_flux_series_w_m2

    wagon = WagonConfig(wagon_id=WAGON_ID)
    manoeuvre = PAPER_MANOEUVRES["A"]
    flux = event_flux_series_w_m2(wagon, manoeuvre, steps, DT_S)
    return wagon, flux, manoeuvre.t0_c


# --- the children ----------------------------------------------------------------------------


def _child_ours(
    element: str,
    steps: int,
    refinement: float,
    cholesky: str,
    precision: str,
    mesh_out: str | None,
) -> dict[str, Any]:
    from fleetbrake.model.thermal import BlockModel

    wagon, flux, initial_c = _problem(steps)
    rss_before = _peak_rss_mb()
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    model = BlockModel(
        wagon.geometry,
        wagon.block_material,
        element=element,  # type: ignore[arg-type]
        refinement=refinement,
        sensor_m=wagon.sensor_point_m,
        cholesky=cholesky,  # type: ignore[arg-type]
    )
    t1 = time.perf_counter()
    cpu1 = _cpu_seconds()

    def run(precision: str) -> Any:
        return model.simulate(
            dt_s=DT_S,
            flux_w_m2=flux,
            ambient_c=AMBIENT_C,
            initial_c=initial_c,
            h_w_m2k=H_W_M2K,
            probes_m=[wagon.sensor_point_m],
            precision=precision,  # type: ignore[arg-type]
        )

    res = run(precision)
    t2 = time.perf_counter()
    cpu2 = _cpu_seconds()
    other_precision = "double" if precision == "mixed" else "mixed"
    other = run(other_precision)  # the factor is cached: stepping alone
    figures = {
        "nodes": model.n_nodes,
        "element": element,
        # the fill-reducing ordering the core chose, where the extension reports it
        "ordering": getattr(model, "ordering", None) or getattr(model._core, "ordering", None),
        "matrix_nnz": model.matrix_nnz,
        "factor_nnz": model.factor_nnz,
        "supernodal": model.is_supernodal,
        "factorizations": int(res.factorizations),
        "seconds_mesh_assembly": t1 - t0,
        "seconds_factorization": float(res.seconds_factorization),
        "seconds_stepping": float(res.seconds_stepping),
        "seconds_total": t2 - t0,
        "cpu_seconds": cpu2 - cpu0,
        "cpu_seconds_simulate": cpu2 - cpu1,
        "peak_rss_mb": _peak_rss_mb(),
        "rss_before_mb": rss_before,
        "sensor_c": res.probe_c[:, 0].tolist(),
        "precision": precision,
        f"seconds_stepping_{other_precision}": float(other.seconds_stepping),
        f"sensor_max_abs_diff_vs_{other_precision}_k": float(
            np.abs(res.probe_c - other.probe_c).max()
        ),
    }
    if mesh_out:
        mesh = model.mesh
        arrays: dict[str, Any] = {"nodes": mesh.nodes, "elements": mesh.elements}
        arrays.update({f"face_{name}": faces for name, faces in mesh.face_sets.items()})
        np.savez(mesh_out, **arrays)
    return figures


def _child_skfem(steps: int, mesh_in: str) -> dict[str, Any]:
    # imported here, outside the timings
    import scipy.sparse.linalg  # noqa: F401
    import skfem  # noqa: F401

    from fleetbrake.bench.peers.skfem_block import DEFAULT_SOLVER, SOLVERS, SkfemBlockModel

    wagon, flux, initial_c = _problem(steps)
    with np.load(mesh_in) as data:
        nodes, elements = data["nodes"], data["elements"]
        face_sets = {k.removeprefix("face_"): data[k] for k in data.files if k.startswith("face_")}
    rss_before = _peak_rss_mb()
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    model = SkfemBlockModel(nodes, elements, face_sets, wagon.block_material)
    cpu1 = _cpu_seconds()
    res = model.simulate(
        DT_S, flux, AMBIENT_C, initial_c, H_W_M2K, np.array([wagon.sensor_point_m])
    )
    t2 = time.perf_counter()
    cpu2 = _cpu_seconds()
    figures: dict[str, Any] = {
        "nodes": model.n_nodes,
        "solver": res.solver,
        "factorizations": int(res.n_factorisations),
        "seconds_mesh_assembly": float(res.seconds_assembly),
        "seconds_factorization": float(res.seconds_factorisation),
        "seconds_stepping": float(res.seconds_stepping),
        "seconds_total": t2 - t0,
        "cpu_seconds": cpu2 - cpu0,
        "cpu_seconds_simulate": cpu2 - cpu1,
        "peak_rss_mb": _peak_rss_mb(),
        "rss_before_mb": rss_before,
        "sensor_c": res.probe_c[:, 0].tolist(),
    }
    # fill of SuperLU's factor, for comparison with ours: the Crank-Nicolson matrix factorised
    # once more, after the peak memory is read (public matrices, caller's node order)
    k = model.conduction_matrix
    for name, h in H_W_M2K.items():
        k = k + h * model.convection_matrix(name)
    solve = SOLVERS[DEFAULT_SOLVER]((model.capacity_matrix / DT_S + 0.5 * k).tocsc())
    lu = getattr(solve, "__self__", None)
    if lu is not None and hasattr(lu, "L"):
        figures["factor_nnz_l"] = int(lu.L.nnz)
        figures["factor_nnz_lu"] = int(lu.L.nnz + lu.U.nnz)
    return figures


def _run_child(args: list[str]) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "fleetbrake.bench.solver", "--json-child", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise BenchError(
            f"benchmark child {' '.join(args)} failed (exit {proc.returncode}):\n"
            + proc.stderr[-3000:]
        )
    lines = proc.stdout.strip().splitlines()
    if not lines:
        raise BenchError(f"benchmark child {' '.join(args)} printed nothing")
    result: dict[str, Any] = json.loads(lines[-1])
    return result


# --- the parent ------------------------------------------------------------------------------


def read_bandwidth_gb_s(size_mb: int = BANDWIDTH_ARRAY_MB, repeats: int = 3) -> float:
    """Single-core read bandwidth, GB/s (1e9 bytes): numpy sum over a float64 array of
    ``size_mb`` MB (far larger than the caches), best of ``repeats``."""
    a = np.ones(size_mb * 2**20 // 8)  # pages touched by the fill
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        a.sum()
        best = min(best, time.perf_counter() - t0)
    return a.nbytes / best / 1e9


def bench_solver(
    element: str = "hex20",
    steps: int = 600,
    refinement: float = 1.0,
    cholesky: str = "auto",
    precision: str = "mixed",
    repeats: int = 3,
) -> dict[str, Any]:
    """Run both engines (each in a child process, alternately, ``repeats`` times) and the
    bandwidth probe; the figures of each engine's fastest run (shared machines add noise,
    never speed), with every run's total time beside them. Needs scikit-fem (the ``bench``
    extra)."""
    if element not in ELEMENTS:
        raise BenchConfigError(f"element must be one of {ELEMENTS}, got {element!r}")
    if cholesky not in CHOLESKY:
        raise BenchConfigError(f"cholesky must be one of {CHOLESKY}, got {cholesky!r}")
    if precision not in PRECISIONS:
        raise BenchConfigError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if steps < 1:
        raise BenchConfigError(f"steps must be >= 1, got {steps}")
    if repeats < 1:
        raise BenchConfigError(f"repeats must be >= 1, got {repeats}")
    if not (refinement > 0 and np.isfinite(refinement)):
        raise BenchConfigError(f"refinement must be a positive number, got {refinement}")

    require_extra("bench solver", "skfem")
    load = os.getloadavg()[0]
    common = ["--steps", str(steps)]
    ours_args = [
        "--engine",
        "ours",
        "--element",
        element,
        "--refinement",
        repr(refinement),
        "--cholesky",
        cholesky,
        "--precision",
        precision,
    ]
    ours_runs: list[dict[str, Any]] = []
    skfem_runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="fleetbrake-bench-") as tmp:
        mesh_path = str(Path(tmp) / "mesh.npz")
        for run in range(repeats):
            mesh_arg = ["--mesh-out", mesh_path] if run == 0 else []
            ours_runs.append(_run_child([*ours_args, *mesh_arg, *common]))
            skfem_runs.append(_run_child(["--engine", "skfem", "--mesh-in", mesh_path, *common]))
    ours = min(ours_runs, key=lambda f: f["seconds_total"])
    skfem = min(skfem_runs, key=lambda f: f["seconds_total"])

    # after the children: a child's ru_maxrss starts from this process's resident size at the
    # spawn (Linux keeps the high-water mark of the image replaced by exec), so no 512 MB here
    bandwidth = read_bandwidth_gb_s()

    sensor = np.array(ours.pop("sensor_c"))
    sensor_ref = np.array(skfem.pop("sensor_c"))
    for figures in (ours, skfem):
        figures["seconds_per_step"] = figures["seconds_stepping"] / steps

    nnz_l = int(ours["factor_nnz"])
    # a simplicial factor is solved by faer in double precision whatever was asked
    read = precision if ours["supernodal"] else "double"
    bytes_values = 2 * nnz_l * BYTES_VALUE[read]
    bytes_values_indices = 2 * nnz_l * (BYTES_VALUE[read] + BYTES_INDEX)
    bound_values = bytes_values / (bandwidth * 1e9)
    bound_values_indices = bytes_values_indices / (bandwidth * 1e9)

    out: dict[str, Any] = {"steps": steps, "dt_s": DT_S, "refinement": refinement}
    out["cholesky"] = cholesky
    out.update(ours)
    out.update({f"skfem_{k}": v for k, v in skfem.items()})
    ours_totals = [f["seconds_total"] for f in ours_runs]
    skfem_totals = [f["seconds_total"] for f in skfem_runs]
    out.update(
        {
            "repeats": repeats,
            "seconds_total_runs": ours_totals,
            "skfem_seconds_total_runs": skfem_totals,
            "speedup_vs_scikit_fem": skfem["seconds_total"] / ours["seconds_total"],
            "speedup_vs_scikit_fem_median": float(np.median(skfem_totals))
            / float(np.median(ours_totals)),
            "speedup_stepping_vs_scikit_fem": skfem["seconds_stepping"] / ours["seconds_stepping"],
            "read_bandwidth_gb_s": bandwidth,
            "bytes_per_step_values": bytes_values,
            "bytes_per_step_values_indices": bytes_values_indices,
            "bound_s_values": bound_values,
            "bound_s_values_indices": bound_values_indices,
            "step_over_bound": ours["seconds_per_step"] / bound_values,
            "step_over_bound_values_indices": ours["seconds_per_step"] / bound_values_indices,
            "sensor_max_abs_diff_k": float(np.abs(sensor - sensor_ref).max()),
            "sensor_peak_c": float(sensor.max()),
            "load_average_1min": load,
            "cpus": os.cpu_count(),
        }
    )

    # six significant digits (not decimals: the differences in kelvins are small numbers)
    def rounded(v: Any) -> Any:
        if isinstance(v, float):
            return float(f"{v:.6g}")
        if isinstance(v, list):
            return [rounded(x) for x in v]
        return v

    return {k: rounded(v) for k, v in out.items()}


def print_table(figures: dict[str, Any]) -> None:
    """The figures as a table (rich), on stdout."""
    from rich.console import Console
    from rich.table import Table

    f = figures
    table = Table(
        title=(
            f"Block model, manoeuvre A, {f['steps']} steps of {f['dt_s']:g} s "
            f"({f['element']}, refinement {f['refinement']:g}, {f['nodes']:,} nodes)"
        )
    )
    table.add_column("")
    table.add_column("ours (Rust, faer)", justify="right")
    table.add_column("scikit-fem (SuperLU)", justify="right")

    def row(label: str, key: str, fmt: str) -> None:
        a, b = f.get(key), f.get(f"skfem_{key}")
        table.add_row(
            label,
            "" if a is None else format(a, fmt),
            "" if b is None else format(b, fmt),
        )

    table.add_row("nodes", f"{f['nodes']:,}", f"{f['skfem_nodes']:,}")
    table.add_row("matrix nnz", f"{f['matrix_nnz']:,}", "")
    table.add_row(
        "factor nnz (L)",
        f"{f['factor_nnz']:,} ({'supernodal' if f['supernodal'] else 'simplicial'}"
        + (f", {f['ordering']})" if f.get("ordering") else ")"),
        f"{f['skfem_factor_nnz_l']:,}" if "skfem_factor_nnz_l" in f else "",
    )
    row("factorisations", "factorizations", "d")
    row("mesh + assembly s", "seconds_mesh_assembly", ".3f")
    row("factorisation s", "seconds_factorization", ".3f")
    row(f"stepping s ({f['precision']} precision)", "seconds_stepping", ".3f")
    for other in PRECISIONS:
        if f"seconds_stepping_{other}" in f:
            table.add_row(
                f"stepping s ({other} precision, same run)",
                f"{f[f'seconds_stepping_{other}']:.3f}",
                "",
            )
    table.add_row(
        "per step ms",
        f"{1e3 * f['seconds_per_step']:.2f}",
        f"{1e3 * f['skfem_seconds_per_step']:.2f}",
    )
    row("total s", "seconds_total", ".3f")
    row("CPU s (all)", "cpu_seconds", ".3f")
    row("CPU s (factorisation + stepping)", "cpu_seconds_simulate", ".3f")
    row("peak RSS MB", "peak_rss_mb", ".1f")
    console = Console(width=100)
    console.print(table)
    vs_other = "".join(
        f"; vs our {o}-precision run {f[f'sensor_max_abs_diff_vs_{o}_k']:.1e} K"
        for o in PRECISIONS
        if f"sensor_max_abs_diff_vs_{o}_k" in f
    )
    runs = ""
    if "seconds_total_runs" in f:
        runs = (
            f" (fastest of {f['repeats']} runs each; totals ours "
            + ", ".join(f"{s:.2f}" for s in f["seconds_total_runs"])
            + " s, scikit-fem "
            + ", ".join(f"{s:.2f}" for s in f["skfem_seconds_total_runs"])
            + f" s; medians' ratio {f['speedup_vs_scikit_fem_median']:.2f}x)"
        )
    console.print(
        f"speedup vs scikit-fem: {f['speedup_vs_scikit_fem']:.2f}x total, "
        f"{f['speedup_stepping_vs_scikit_fem']:.2f}x stepping{runs}\n"
        f"read bandwidth {f['read_bandwidth_gb_s']:.1f} GB/s (numpy sum, 512 MB, best of 3); "
        f"two triangular solves read {f['bytes_per_step_values'] / 1e6:.0f} MB of values "
        f"({f['bytes_per_step_values_indices'] / 1e6:.0f} MB with 8-byte row indices) per step\n"
        f"bound {1e3 * f['bound_s_values']:.2f} ms/step (values) / "
        f"{1e3 * f['bound_s_values_indices']:.2f} ms (values + indices); "
        f"measured/bound {f['step_over_bound']:.2f} / {f['step_over_bound_values_indices']:.2f}\n"
        f"sensor: max |ours - scikit-fem| = {f['sensor_max_abs_diff_k']:.2e} K{vs_other} "
        f"(peak {f['sensor_peak_c']:.2f} C); load average {f['load_average_1min']:.2f} on "
        f"{f['cpus']} CPUs",
        highlight=False,
    )


def main(argv: list[str] | None = None) -> None:
    """Child entry point: ``python -m fleetbrake.bench.solver --engine ours --json-child``."""
    parser = argparse.ArgumentParser(prog="python -m fleetbrake.bench.solver")
    parser.add_argument("--engine", choices=("ours", "skfem"))
    parser.add_argument("--json-child", action="store_true")
    parser.add_argument("--element", choices=ELEMENTS, default="hex20")
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--refinement", type=float, default=1.0)
    parser.add_argument("--cholesky", choices=CHOLESKY, default="auto")
    parser.add_argument("--precision", choices=PRECISIONS, default="mixed")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--mesh-out")
    parser.add_argument("--mesh-in")
    args = parser.parse_args(argv)
    if args.engine is None:  # the whole benchmark, as `fleetbrake bench solver --json`
        figures = bench_solver(
            args.element, args.steps, args.refinement, args.cholesky, args.precision, args.repeats
        )
        print_table(figures)
        print(json.dumps(figures))
        return
    if args.engine == "ours":
        figures = _child_ours(
            args.element,
            args.steps,
            args.refinement,
            args.cholesky,
            args.precision,
            args.mesh_out,
        )
    else:
        if not args.mesh_in:
            parser.error("--engine skfem needs --mesh-in (the .npz written by --engine ours)")
        figures = _child_skfem(args.steps, args.mesh_in)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
