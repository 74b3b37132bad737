"""The Ray engine keeps the engine's contract (order, a bounded number ahead, errors naming the
partition with their exit code) and ``run --engine ray`` stores the tables of
``--engine local``. A local Ray instance of 2 CPUs serves the module."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from fleetbrake.engine import EngineConfigError, LocalEngine, PartitionError, make_engine
from fleetbrake.engine.ray import SYSTEM_RETRIES
from fleetbrake.errors import ConfigError
from fleetgen import snapshot
from test_run_engine import WALL_CLOCK, _run


def test_without_ray_installed_the_engine_is_refused_saying_how_to_install_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    with pytest.raises(EngineConfigError, match=r'pip install "fleetbrake\[ray\]"') as caught:
        make_engine("ray", 2)
    assert caught.value.exit_code == 2


def test_an_address_is_refused_without_the_ray_engine() -> None:
    with pytest.raises(EngineConfigError, match="--address needs --engine ray"):
        make_engine("local", 2, address="127.0.0.1:6379")


@pytest.fixture(scope="module")
def ray_cluster() -> Iterator[Any]:
    """A local Ray instance of 2 CPUs; this module's functions are shipped by value (the
    workers cannot import the tests)."""
    ray = pytest.importorskip("ray")
    from ray import cloudpickle

    ray.init(num_cpus=2, include_dashboard=False)
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        yield ray
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
        ray.shutdown()


def _square(x: int) -> int:
    if x == 7:
        raise ConfigError(f"row {x}: bad value")
    if x == 8:
        raise ZeroDivisionError("division by zero")
    return x * x


def _threads(_: int) -> tuple[str, str]:
    return os.environ["RAYON_NUM_THREADS"], os.environ["POLARS_MAX_THREADS"]


def test_map_yields_in_item_order_with_one_thread_per_task(ray_cluster: Any) -> None:
    engine = make_engine("ray", 2)
    with engine:
        assert engine.workers == 2
        assert list(engine.map(_square, range(7))) == [x * x for x in range(7)]
        assert set(engine.map(_threads, range(4))) == {("1", "1")}
        pairs = list(engine.map_unordered(_square, [(f"k{x}", x) for x in range(6)]))
        assert sorted(pairs) == sorted((f"k{x}", x * x) for x in range(6))
    assert ray_cluster.is_initialized()  # a cluster the engine did not start stays up


def test_map_is_lazy_and_bounded(ray_cluster: Any) -> None:
    taken: list[int] = []

    def items() -> Iterator[int]:
        for x in range(100):
            taken.append(x)
            yield x

    with make_engine("ray", 2) as engine:
        results = engine.map(_square, items())
        assert next(results) == 0
        assert len(taken) <= 1 + 2 * engine.workers
        results.close()


def test_a_failing_partition_is_named_and_keeps_its_exit_code(ray_cluster: Any) -> None:
    with make_engine("ray", 2) as engine:
        with pytest.raises(PartitionError) as caught:
            list(engine.map(_square, range(10), name=lambda x: f"wagon W{x:03d}"))
        assert str(caught.value) == "partition wagon W007: ConfigError: row 7: bad value"
        assert caught.value.exit_code == 2
        assert isinstance(caught.value.__cause__, ConfigError)
        with pytest.raises(PartitionError, match="partition k8: ZeroDivisionError") as failed:
            list(engine.map_unordered(_square, [("k8", 8)]))
        assert failed.value.exit_code == 1
        assert list(engine.map(_square, [2, 3])) == [4, 9]  # still serves after a failure


def _dies_first(marker: str) -> int:
    """Kills its worker process on the first run (no exception: the process is gone), then
    returns the number of runs before this one."""
    path = Path(marker)
    runs = int(path.read_text()) if path.exists() else 0
    path.write_text(str(runs + 1))
    if runs == 0 or marker.endswith("always"):
        os._exit(1)
    return runs


def test_a_task_whose_worker_dies_is_run_again_and_one_that_always_dies_is_named(
    ray_cluster: Any, tmp_path: Path
) -> None:
    once, always = tmp_path / "once", tmp_path / "always"
    with make_engine("ray", 2) as engine:
        assert list(engine.map(_dies_first, [str(once)])) == [1]
        with pytest.raises(PartitionError, match=r"partition k1: \w*(Crashed|Died)\w*Error"):
            list(engine.map_unordered(_dies_first, [("k1", str(always))]))
        assert always.read_text() == str(1 + SYSTEM_RETRIES)  # ran, then retried, no more
        assert list(engine.map(_square, [2, 3])) == [4, 9]


@pytest.fixture(scope="module")
def fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_cache_dir: Path,
) -> Iterator[Path]:
    """2 wagons x 1 day with the anomalies."""
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    root = tmp_path_factory.mktemp("run-ray") / "fleet"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        generate_fleet(root, SynthConfig(wagons=2, days=1, seed=5), rom=reduced_model_for)
        yield root


def test_run_on_ray_stores_the_tables_of_run_on_the_local_engine(
    ray_cluster: Any, fleet: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    local_db, ray_db = tmp_path / "local.duckdb", tmp_path / "ray.duckdb"
    with LocalEngine(2) as local:
        _run(fleet, local_db, local, rom_refinement, rom_cache_dir)
    with make_engine("ray", 2) as engine:
        report = _run(fleet, ray_db, engine, rom_refinement, rom_cache_dir)
    assert report.engine.startswith("RayEngine(")  # type: ignore[attr-defined]
    assert report.simulation.events_simulated > 0  # type: ignore[attr-defined]
    tables = snapshot(ray_db, ignore=WALL_CLOCK)
    assert tables["predictions"]
    assert tables == snapshot(local_db, ignore=WALL_CLOCK)
