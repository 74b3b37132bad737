"""fleetbrake as a user installs it: the wheel built from this checkout, installed into a fresh
virtualenv, run from a folder outside the checkout (no source tree on any path).

The wheel is ``$FLEETBRAKE_TEST_WHEEL`` when set (``make test`` builds it once, into
``dist/``), else built here with ``maturin build --release``.
"""

from __future__ import annotations

import ast
import datetime as dt
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

CHECKOUT = Path(__file__).resolve().parents[1]


def _clean_env(home: Path | None = None) -> dict[str, str]:
    """The environment of a user's shell: nothing pointing into the checkout."""
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in {"PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME"} and not k.startswith("PYTEST")
    }
    env["PATH"] = os.pathsep.join(
        p for p in env.get("PATH", "").split(os.pathsep) if not p.startswith(str(CHECKOUT))
    )
    return env


def _wheel(out_dir: Path) -> Path:
    given = os.environ.get("FLEETBRAKE_TEST_WHEEL")
    if given:
        path = Path(given).resolve()  # pip runs elsewhere: a relative path would not hold
        assert path.is_file(), f"$FLEETBRAKE_TEST_WHEEL={given} is not a file"
        return path
    maturin = shutil.which("maturin", path=str(Path(sys.executable).parent)) or "maturin"
    subprocess.run(
        [maturin, "build", "--release", "--out", str(out_dir), "-q"],
        cwd=CHECKOUT,
        check=True,
    )
    (wheel,) = out_dir.glob("fleetbrake-*.whl")
    return wheel


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The ``bin/`` of a fresh virtualenv with the wheel installed (runtime dependencies only)."""
    root = tmp_path_factory.mktemp("wheel")
    wheel = _wheel(root / "dist")
    venv = root / "venv"
    base = getattr(sys, "_base_executable", sys.executable)
    subprocess.run([base, "-m", "venv", str(venv)], check=True, env=_clean_env())
    pip = [
        str(venv / "bin" / "python"),
        "-m",
        "pip",
        "install",
        "-q",
        "--disable-pip-version-check",
    ]
    subprocess.run([*pip, str(wheel)], check=True, env=_clean_env(), cwd=root)
    return venv / "bin"


def _run(bin_dir: Path, cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(
        [str(bin_dir / args[0]), *args[1:]],
        cwd=cwd,
        env=_clean_env(),
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, (
        f"{' '.join(args)} exited {done.returncode}\nstdout:\n{done.stdout[-3000:]}\n"
        f"stderr:\n{done.stderr[-3000:]}"
    )
    return done


def test_the_installed_wheel_has_no_source_tree_behind_it(installed: Path, tmp_path: Path) -> None:
    probe = (
        "import fleetbrake, fleetbrake.warehouse.connection as c, fleetbrake.cli.main, sys; "
        "print(fleetbrake.__file__); print(len(c.sql_files())); "
        "print(sorted(m for m in ('psutil', 'skfem') if m in sys.modules))"
    )
    done = _run(installed, tmp_path, "python", "-c", probe)
    where, n_sql, bench_modules = done.stdout.split("\n")[:3]
    assert str(CHECKOUT) not in where and "site-packages" in where
    assert int(n_sql) >= 8
    assert bench_modules == "[]"  # the benchmarks' peers are an extra, not the product's path
    # the benchmarks' peer is not installed by the wheel's own dependencies (psutil may be:
    # other packages depend on it)
    missing = _run(
        installed,
        tmp_path,
        "python",
        "-c",
        "import importlib.util as u; print(u.find_spec('skfem'))",
    )
    assert missing.stdout.strip() == "None"


def test_run_close_loop_record_report_and_paper_from_a_folder_outside_the_checkout(
    installed: Path, tmp_path: Path
) -> None:
    work = tmp_path / "job"  # a scheduled job's working directory, nowhere near the checkout
    work.mkdir()
    start = dt.date(2024, 3, 4)
    _run(
        installed,
        work,
        "fleetbrake",
        "synth",
        "fleet",
        "--wagons",
        "2",
        "--days",
        "2",
        "--seed",
        "11",
        "--start",
        start.isoformat(),
        "--effect",
        "convection_speed",
    )
    _run(installed, work, "fleetbrake", "run", "fleet", "--db", "fleet.duckdb")
    again = _run(installed, work, "fleetbrake", "run", "fleet", "--db", "fleet.duckdb")
    assert "simulated 0 events" in again.stdout  # idempotent: the second run adds nothing

    holdout = (start + dt.timedelta(days=1)).isoformat()
    _run(
        installed,
        work,
        "fleetbrake",
        "close-loop",
        "--db",
        "fleet.duckdb",
        "--holdout-from",
        holdout,
        "--json",
        "close-loop.json",
    )
    report = json.loads((work / "close-loop.json").read_text())
    assert report["baseline_revision"] == "declared"
    assert report["fit"]["events"] > 0 and report["holdout"]["events"] > 0
    assert (work / "close-loop.md").is_file()

    count = _run(
        installed,
        work,
        "python",
        "-c",
        "import duckdb; con = duckdb.connect('fleet.duckdb', read_only=True); "
        "print(con.sql('SELECT count(*), min(wagon_id) FROM v_predictions').fetchall()[0])",
    )
    rows, wagon = ast.literal_eval(count.stdout.strip())
    assert rows > 0

    _run(
        installed,
        work,
        "fleetbrake",
        "record",
        "--db",
        "fleet.duckdb",
        "--wagon",
        wagon,
        "--out",
        "wagon.rrd",
    )
    assert (work / "wagon.rrd").stat().st_size > 0

    _run(
        installed,
        work,
        "fleetbrake",
        "report",
        "--db",
        "fleet.duckdb",
        "--out",
        "report",
        "--close-loop",
        "close-loop.json",
    )
    assert (work / "report" / "report.md").is_file()

    _run(installed, work, "fleetbrake", "paper", "--out", "paper")
    assert sorted(p.suffix for p in (work / "paper").iterdir()) >= [".png"]
