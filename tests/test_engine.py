"""The engines: results in order (or keyed), errors naming the partition, inline = local."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetbrake.engine import (
    EngineConfigError,
    InlineEngine,
    LocalEngine,
    PartitionError,
    make_engine,
)
from fleetbrake.errors import EXIT_USAGE, ConfigError


def _square_slowly_first(x: int) -> int:
    # the first items take longest: a pool that yields as finished would reorder them
    total = 0
    for i in range((20 - x) * 20_000 if x < 20 else 0):
        total += i
    return x * x


def _fail_on_seven(x: int) -> int:
    if x == 7:
        raise ValueError(f"bad value {x}")
    return x


def _config_error(x: int) -> int:
    raise ConfigError(f"threshold of wagon {x} is not a number")


def _thread_env(_: int) -> tuple[str | None, str | None, int]:
    return os.environ.get("RAYON_NUM_THREADS"), os.environ.get("POLARS_MAX_THREADS"), os.getpid()


class _Unpicklable(Exception):
    def __init__(self, a: int, b: int) -> None:
        super().__init__(f"{a}/{b}")


def _raise_unpicklable(x: int) -> int:
    raise _Unpicklable(x, 0)


@pytest.fixture(scope="module")
def local() -> Iterator[LocalEngine]:
    with LocalEngine(2, in_flight=3) as engine:
        yield engine


def test_map_keeps_the_order_of_the_items(local: LocalEngine) -> None:
    items = list(range(24))
    assert list(local.map(_square_slowly_first, items)) == [x * x for x in items]
    assert list(InlineEngine().map(_square_slowly_first, items)) == [x * x for x in items]
    threaded = InlineEngine(threads=3)
    assert list(threaded.map(_square_slowly_first, items)) == [x * x for x in items]


def test_inline_and_local_give_the_same_results(local: LocalEngine) -> None:
    items = list(range(40))
    assert list(local.map(_fail_on_seven, [i for i in items if i != 7])) == list(
        InlineEngine().map(_fail_on_seven, [i for i in items if i != 7])
    )
    keyed = [(f"wagon-{i}", i) for i in range(10)]
    assert sorted(local.map_unordered(_square_slowly_first, keyed)) == sorted(
        InlineEngine().map_unordered(_square_slowly_first, keyed)
    )


def test_map_consumes_its_items_lazily(local: LocalEngine) -> None:
    taken: list[int] = []

    def items() -> Iterator[int]:
        for i in range(1000):
            taken.append(i)
            yield i

    results = local.map(_fail_on_seven, (i for i in items() if i != 7))
    assert next(results) == 0
    assert len(taken) <= local.in_flight + 2  # never the whole fleet in flight
    results.close()


def _identity(x: int) -> int:
    return x


@pytest.mark.parametrize("kind", ["inline", "threads", "local", "local-unordered"])
def test_the_results_ahead_of_the_caller_stay_bounded_whatever_the_items(
    kind: str, local: LocalEngine
) -> None:
    """Backpressure, counted: over a long stream, the items taken but not yet handed to the
    caller (the single writer) never exceed the engine's bound, so memory holds a few
    partitions, never the fleet's, however slowly the caller writes."""
    threads = InlineEngine(threads=2)
    engine = {"inline": InlineEngine(), "threads": threads}.get(kind, local)
    bound = {"inline": 0, "threads": 2 * threads.threads}.get(kind, local.in_flight)
    taken = 0

    def items() -> Iterator[int]:
        nonlocal taken
        for i in range(60):
            taken += 1
            yield i

    if kind == "local-unordered":
        results: Iterator[object] = local.map_unordered(_identity, ((i, i) for i in items()))
    else:
        results = engine.map(_identity, items())
    ahead = []
    for handed, _ in enumerate(results, start=1):
        ahead.append(taken - handed)
    assert len(ahead) == 60
    assert max(ahead) <= bound
    assert max(ahead) == bound or kind == "inline"  # the bound is used: work runs ahead


@pytest.mark.parametrize("kind", ["inline", "threads", "local"])
def test_an_error_names_its_partition(kind: str, local: LocalEngine) -> None:
    engine = {"local": local, "inline": InlineEngine(), "threads": InlineEngine(threads=2)}[kind]
    with pytest.raises(PartitionError, match=r"partition wagon SGG-0007: ValueError: bad value 7"):
        list(engine.map(_fail_on_seven, range(10), name=lambda x: f"wagon SGG-{x:04d}"))
    with pytest.raises(PartitionError, match=r"partition w7: ValueError") as caught:
        list(engine.map_unordered(_fail_on_seven, [(f"w{i}", i) for i in range(10)]))
    assert isinstance(caught.value.__cause__, ValueError)
    assert caught.value.exit_code == 1


def test_an_expected_failure_keeps_its_exit_code(local: LocalEngine) -> None:
    with pytest.raises(PartitionError, match="partition 3: ConfigError: threshold of wagon 3") as e:
        list(local.map(_config_error, [3]))
    assert e.value.exit_code == EXIT_USAGE


def test_an_exception_that_does_not_pickle_still_names_its_partition(local: LocalEngine) -> None:
    with pytest.raises(PartitionError, match=r"partition 5: RuntimeError: _Unpicklable: 5/0"):
        list(local.map(_raise_unpicklable, [5]))
    # the pool survives a partition's failure
    assert list(local.map(_fail_on_seven, [1, 2])) == [1, 2]


def test_workers_run_one_thread_per_library() -> None:
    with LocalEngine(2, preload=("fleetbrake.ingest.files",)) as engine:
        engine.start()
        seen = list(engine.map(_thread_env, range(4)))
    assert {(rayon, polars) for rayon, polars, _ in seen} == {("1", "1")}
    assert os.getpid() not in {pid for _, _, pid in seen}


def test_make_engine(monkeypatch: pytest.MonkeyPatch) -> None:
    assert isinstance(make_engine("local", 1), InlineEngine)
    engine = make_engine("local", 2)
    assert isinstance(engine, LocalEngine) and engine.workers == 2
    engine.close()
    monkeypatch.setitem(sys.modules, "ray", None)  # Ray not installed
    with pytest.raises(EngineConfigError, match=r'pip install "fleetbrake\[ray\]"') as ray:
        make_engine("ray")
    assert ray.value.exit_code == EXIT_USAGE
    with pytest.raises(EngineConfigError, match="--workers must be >= 1"):
        make_engine("local", 0)
    with pytest.raises(EngineConfigError, match="--engine must be one of local, ray"):
        make_engine("dask")


def test_run_refuses_the_ray_engine_and_a_bad_worker_count(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from typer.testing import CliRunner

    from fleetbrake.cli.main import app

    monkeypatch.setitem(sys.modules, "ray", None)  # Ray not installed
    runner = CliRunner()
    db = str(tmp_path / "fleet.duckdb")
    ray = runner.invoke(app, ["run", str(tmp_path), "--db", db, "--engine", "ray"])
    assert ray.exit_code == EXIT_USAGE
    assert '--engine ray needs Ray: pip install "fleetbrake[ray]"' in ray.output
    zero = runner.invoke(app, ["run", str(tmp_path), "--db", db, "--workers", "0"])
    assert zero.exit_code == EXIT_USAGE and "--workers must be >= 1, got 0" in zero.output
    assert not (tmp_path / "fleet.duckdb").exists()  # refused before anything was written
