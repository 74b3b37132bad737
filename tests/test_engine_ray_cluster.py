"""``--engine ray`` on a cluster of two nodes (``ray.cluster_utils.Cluster``: a head and a
second node of one CPU each, on this machine): ``run`` stores the public views of a run on the
local engine, ``close-loop`` reports what one on the local engine reports, and the tasks ran
on both nodes. About 45 s, the cluster's start included."""

from __future__ import annotations

import contextlib
import logging
import math
import re
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

ray = pytest.importorskip(
    "ray", reason='Ray is not installed (pip install "fleetbrake[ray]", part of ".[dev]")'
)

from fleetbrake.app.run import run_fleet  # noqa: E402
from fleetbrake.closeloop.config import CloseLoopConfig  # noqa: E402
from fleetbrake.closeloop.loop import run_close_loop  # noqa: E402
from fleetbrake.simulation.config import SimulationConfig  # noqa: E402
from test_closeloop_engine import HOLDOUT, report_differences  # noqa: E402

VIEWS = {
    "v_files": ("ingested_utc",),
    "v_events": (),
    "v_predictions": (),
    "v_flags": (),
    "v_contact_estimates": (),
    "v_model_revisions": ("created_utc",),
}
"""The public views compared, each without the columns that say when a row was written."""

TASKS_LOGGED = re.compile(r"ray engine: (\d+) tasks ran on (\d+) nodes")


@pytest.fixture(scope="module")
def cluster() -> Iterator[Any]:
    """A head node and one more, one CPU each; shut down after the module."""
    from ray.cluster_utils import Cluster

    nodes = Cluster(
        initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False}
    )
    try:
        nodes.add_node(num_cpus=1)
        nodes.wait_for_nodes()
        yield nodes
    finally:
        if ray.is_initialized():
            ray.shutdown()
        nodes.shutdown()


@pytest.fixture(scope="module")
def fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_cache_dir: Path,
) -> Path:
    """2 wagons x 2 days with an undeclared convection (what the close loop finds) and the
    anomalies."""
    from fleetbrake.model.effects import ConvectionSpeed, EffectSet
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    root = tmp_path_factory.mktemp("ray-cluster") / "fleet"
    effects = EffectSet((ConvectionSpeed(gain=2.0, exponent=0.8),))
    config = SynthConfig(wagons=2, days=2, seed=4, effects=effects, anomalies=True)
    generate_fleet(root, config, rom=reduced_model_for)
    return root


@pytest.fixture
def rom_env(monkeypatch: pytest.MonkeyPatch, rom_cache_dir: Path) -> None:
    """The session's reduced models, here and in the tasks (the engine passes the variable)."""
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))


def views(db: Path) -> dict[str, list[tuple[object, ...]]]:
    """The rows of :data:`VIEWS`, sorted, without their wall-clock columns."""
    import duckdb

    con = duckdb.connect(str(db), read_only=True)
    try:
        out = {}
        for view, skipped in VIEWS.items():
            columns = [
                name
                for (name,) in con.execute(
                    "SELECT column_name FROM information_schema.columns "
                    "WHERE table_name = $view ORDER BY ordinal_position",
                    {"view": view},
                ).fetchall()
                if name not in skipped
            ]
            quoted = ", ".join(f'"{c}"' for c in columns)
            out[view] = con.execute(f"SELECT {quoted} FROM {view} ORDER BY ALL").fetchall()
        return out
    finally:
        con.close()


def differences(
    a: dict[str, list[tuple[object, ...]]], b: dict[str, list[tuple[object, ...]]]
) -> list[str]:
    """Where two sets of views differ: row counts, then each value, floats to 1e-9."""
    found = []
    for view, rows in a.items():
        other = b[view]
        if len(rows) != len(other):
            found.append(f"{view}: {len(rows)} rows against {len(other)}")
            continue
        for i, (row, row_b) in enumerate(zip(rows, other, strict=True)):
            for j, (x, y) in enumerate(zip(row, row_b, strict=True)):
                same = (
                    math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-9)
                    if isinstance(x, float) and isinstance(y, float)
                    else x == y
                )
                if not same:
                    found.append(f"{view} row {i} column {j}: {x!r} against {y!r}")
    return found


class TaskLines(logging.Handler):
    """Keeps the ray engine's closing lines: (tasks, nodes) of each."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.counts: list[tuple[int, int]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if found := TASKS_LOGGED.search(record.getMessage()):
            self.counts.append((int(found[1]), int(found[2])))


@contextlib.contextmanager
def ray_tasks() -> Iterator[list[tuple[int, int]]]:
    """The (tasks, nodes) the ray engine logs as it closes, while the block runs."""
    handler, logger = TaskLines(), logging.getLogger("fleetbrake.engine.ray")
    level = logger.level
    logger.setLevel(logging.INFO)
    logger.addHandler(handler)
    try:
        yield handler.counts
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


@dataclass(frozen=True)
class Runs:
    """The fleet run on the local engine and on the cluster, and the ray engine's tasks."""

    dbs: dict[str, Path]
    simulation: SimulationConfig
    engine: str
    tasks: list[tuple[int, int]]


@pytest.fixture(scope="module")
def runs(
    cluster: Any, fleet: Path, tmp_path_factory: pytest.TempPathFactory, rom_cache_dir: Path
) -> Iterator[Runs]:
    from conftest import TEST_REFINEMENT

    out = tmp_path_factory.mktemp("ray-cluster-runs")
    simulation = SimulationConfig(refinement=TEST_REFINEMENT)
    dbs = {name: out / f"{name}.duckdb" for name in ("local", "ray")}
    with pytest.MonkeyPatch.context() as mp, ray_tasks() as tasks:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        run_fleet(fleet, dbs["local"], simulation=simulation, progress=False, workers=2)
        report = run_fleet(
            fleet,
            dbs["ray"],
            simulation=simulation,
            progress=False,
            engine="ray",
            address=cluster.address,
        )
        assert report.simulation.events_simulated > 0
        yield Runs(dbs, simulation, report.engine, tasks)


def test_run_on_two_nodes_stores_the_views_of_a_run_on_the_local_engine(runs: Runs) -> None:
    assert runs.engine.startswith("RayEngine(address=")
    assert len(runs.tasks) == 1 and runs.tasks[0][1] == 2, f"(tasks, nodes) {runs.tasks}"
    tables = views(runs.dbs["ray"])
    assert tables["v_predictions"] and tables["v_contact_estimates"] and tables["v_flags"]
    assert differences(tables, views(runs.dbs["local"])) == []


@pytest.mark.usefixtures("rom_env")
def test_close_loop_on_two_nodes_reports_and_stores_what_the_local_engine_does(
    cluster: Any, runs: Runs, tmp_path: Path
) -> None:
    config = CloseLoopConfig(
        HOLDOUT,
        simulation=runs.simulation,
        candidates=("convection_speed", "sensor_lag", "ambient_offset"),
        max_nfev=6,
    )
    dbs = {name: tmp_path / db.name for name, db in runs.dbs.items()}
    for name, db in runs.dbs.items():
        shutil.copy(db, dbs[name])
    with ray_tasks() as tasks:
        reports = {
            name: run_close_loop(
                dbs[name],
                HOLDOUT,
                tmp_path / f"{name}.json",
                config=config,
                engine=name,
                workers=2 if name == "local" else None,
                address=cluster.address if name == "ray" else None,
            )
            for name in ("local", "ray")
        }
    assert reports["ray"]["effect"] == "convection_speed", reports["ray"]["candidates"]
    assert report_differences(reports["ray"], reports["local"], rel=1e-9) == []
    assert len(tasks) == 1 and tasks[0][1] == 2, f"(tasks, nodes) {tasks}"
    assert differences(views(dbs["ray"]), views(dbs["local"])) == []
