"""The engine that runs partitions in a pool of worker processes on this machine.

Workers are started with ``spawn`` (never ``fork``: the parent may already run polars' and
Rayon's threads, which a forked child would inherit as locks held by no one).
Large Arrow tables (a partition's data, a result's rows) cross between the processes as Arrow
IPC files in the engine's own directory (in ``/dev/shm``), mapped by the reader, not pickled
through the pipe (:func:`_ship_table`); the directory goes with the engine (and, should its
process be killed, with the next engine started on the machine). Each worker's
initializer, which runs before it unpickles any task and so before its first polars or
extension call, sets one thread per library (``RAYON_NUM_THREADS``, ``POLARS_MAX_THREADS``
and the BLAS ones = 1: the processes are the parallelism) and ignores SIGINT, so a Ctrl-C is
the parent's alone: it cancels what is queued, terminates the workers and propagates.

At most ``in_flight`` partitions (default: twice the workers) are submitted but not yet
handed to the caller: the caller, the single writer, paces the workers, and memory holds a
few partitions' data whatever the fleet's size.
"""

from __future__ import annotations

import importlib
import itertools
import logging
import multiprocessing
import os
import shutil
import signal
import sys
import tempfile
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from multiprocessing.reduction import ForkingPickler
from pathlib import Path
from typing import Any, TypeVar

from fleetbrake.engine.base import (
    EngineConfigError,
    call_in_worker,
    default_workers,
    partition_error,
)

__all__ = ["SHIPPED_MIN_BYTES", "WORKER_THREAD_ENV", "LocalEngine"]

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")
K = TypeVar("K")

WORKER_THREAD_ENV: dict[str, str] = {
    "RAYON_NUM_THREADS": "1",
    "POLARS_MAX_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}
"""Set in every worker before its first task: one thread per library and process."""


SHIPPED_MIN_BYTES = 1 << 20
"""An Arrow table of at least this many bytes crosses between the writer and a worker as a
file (:func:`_ship_table`), a smaller one pickled."""

_ship_dir: str | None = None
"""Where this process writes the Arrow tables it ships (the engine's directory); None:
tables are pickled as usual."""
_shipped = itertools.count()


def _ship_table(table: Any) -> tuple[Any, ...]:
    """How ``multiprocessing`` pickles an Arrow table between the engine's processes: a
    large one is written once as an Arrow IPC file in the engine's directory (in memory,
    ``/dev/shm`` where there is one) and the other side maps it (:func:`_load_shipped`),
    instead of being copied into a pickle, through the pipe and out of the pickle again
    (a 36 MB table: 68 ms pickled and unpickled, 24 ms written, mapped and read:
    ``docs/decisions/0007-reading-and-writing-in-chunks.md``)."""
    import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

    if _ship_dir is None or table.nbytes < SHIPPED_MIN_BYTES:
        return table.__reduce__()  # type: ignore[no-any-return,unused-ignore]
    path = os.path.join(_ship_dir, f"{os.getpid()}-{next(_shipped)}.arrow")
    with pa.OSFile(path, "wb") as sink, pa.ipc.new_file(sink, table.schema) as writer:
        writer.write_table(table)
    return _load_shipped, (path,)


def _load_shipped(path: str) -> Any:
    """The table :func:`_ship_table` wrote, mapped (no copy); the file is removed at once
    (the mapping keeps its pages until the table is dropped)."""
    import pyarrow as pa

    try:
        return pa.ipc.open_file(pa.memory_map(path)).read_all()
    finally:
        os.unlink(path)


def _ship_tables_through(directory: str | None) -> None:
    """Ship this process's large Arrow tables through ``directory`` (None: pickle them)."""
    global _ship_dir
    import pyarrow as pa

    _ship_dir = directory
    ForkingPickler.register(pa.Table, _ship_table)


def _ship_root() -> str | None:
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None


def _remove_stale_ship_dirs(root: str | None) -> None:
    """Remove the directories of engines whose process is gone (killed before closing)."""
    for path in Path(root or tempfile.gettempdir()).glob(f"{_SHIP_PREFIX}*"):
        try:
            pid = int(path.name[len(_SHIP_PREFIX) :].split("-")[0])
            os.kill(pid, 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
        except (ValueError, OSError):
            continue


_SHIP_PREFIX = "fleetbrake-engine-"


def _init_worker(
    env: dict[str, str], preload: tuple[str, ...], ship_dir: str | None = None
) -> None:
    os.environ.update(env)
    if ship_dir is not None:
        _ship_tables_through(ship_dir)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if "polars" in sys.modules:  # imported by the parent's main module: its pool is lazy
        logger.debug("worker %d: polars imported before the initializer", os.getpid())
    for module in preload:
        importlib.import_module(module)


def _ready() -> int:
    return os.getpid()


class LocalEngine:
    """:class:`~fleetbrake.engine.base.Engine` on ``workers`` processes of this machine
    (default: the cores this process may use). The pool starts at :meth:`start` or the
    first ``map`` and serves every ``map`` until :meth:`close`; use it as a context manager.
    ``preload``: modules each worker imports as it starts (the stages' modules: a worker
    spends about half a second importing polars and DuckDB)."""

    def __init__(
        self,
        workers: int | None = None,
        *,
        in_flight: int | None = None,
        preload: tuple[str, ...] = (),
    ) -> None:
        self._workers = default_workers() if workers is None else workers
        if self._workers < 1:
            raise EngineConfigError(f"workers must be >= 1, got {self._workers}")
        self.in_flight = 2 * self._workers if in_flight is None else in_flight
        if self.in_flight < 1:
            raise EngineConfigError(f"in_flight must be >= 1, got {self.in_flight}")
        self._preload = preload
        self._pool: ProcessPoolExecutor | None = None
        self._closed = False
        self._ship_dir: str | None = None

    @property
    def workers(self) -> int:
        return self._workers

    def _ensure_pool(self) -> ProcessPoolExecutor:
        if self._closed:
            raise RuntimeError("LocalEngine: closed")
        if self._pool is None:
            root = _ship_root()
            _remove_stale_ship_dirs(root)
            self._ship_dir = tempfile.mkdtemp(prefix=f"{_SHIP_PREFIX}{os.getpid()}-", dir=root)
            _ship_tables_through(self._ship_dir)
            self._pool = ProcessPoolExecutor(
                max_workers=self._workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_init_worker,
                initargs=(WORKER_THREAD_ENV, self._preload, self._ship_dir),
            )
        return self._pool

    def _remove_ship_dir(self) -> None:
        """The pool is down: the tables still in its directory were never read."""
        directory, self._ship_dir = self._ship_dir, None
        if directory is not None:
            if _ship_dir == directory:
                _ship_tables_through(None)
            shutil.rmtree(directory, ignore_errors=True)

    def start(self) -> None:
        """Start the workers now (and import ``preload`` in them) without waiting for them,
        so that they start while the caller prepares its first partitions; else they start
        at the first ``map``."""
        pool = self._ensure_pool()
        for _ in range(self._workers):
            pool.submit(_ready)  # each submission before a worker is idle starts one

    def map(
        self,
        fn: Callable[[T], R],
        items: Iterable[T],
        *,
        name: Callable[[T], str] | None = None,
    ) -> Iterator[R]:
        pool = self._ensure_pool()
        pending: deque[tuple[Future[R], T]] = deque()
        queue = iter(items)
        try:
            for item in queue:
                pending.append((pool.submit(call_in_worker, fn, item), item))
                if len(pending) >= self.in_flight:
                    break
            while pending:
                future, item = pending.popleft()
                try:
                    result = future.result()
                except Exception as error:
                    raise partition_error(item, None, name, error) from error  # type: ignore[arg-type]
                for following in queue:
                    pending.append((pool.submit(call_in_worker, fn, following), following))
                    break
                yield result
        except KeyboardInterrupt:
            self._terminate()
            raise
        finally:
            for future, _ in pending:
                future.cancel()

    def map_unordered(
        self, fn: Callable[[T], R], keyed_items: Iterable[tuple[K, T]]
    ) -> Iterator[tuple[K, R]]:
        pool = self._ensure_pool()
        pending: dict[Future[R], tuple[K, T]] = {}
        queue = iter(keyed_items)

        def submit_next() -> None:
            for key, item in queue:
                pending[pool.submit(call_in_worker, fn, item)] = (key, item)
                return

        try:
            while len(pending) < self.in_flight:
                before = len(pending)
                submit_next()
                if len(pending) == before:
                    break
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    key, item = pending.pop(future)
                    try:
                        result = future.result()
                    except Exception as error:
                        raise partition_error(item, key, None, error) from error
                    submit_next()
                    yield key, result
        except KeyboardInterrupt:
            self._terminate()
            raise
        finally:
            for future in pending:
                future.cancel()

    def _terminate(self) -> None:
        """Stop now: cancel what is queued, kill the running partitions."""
        pool, self._pool, self._closed = self._pool, None, True
        if pool is None:
            return
        # ProcessPoolExecutor has no public terminate before Python 3.14
        processes = list(getattr(pool, "_processes", {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            if process.is_alive():
                process.terminate()
        for process in processes:
            process.join(timeout=5)
        self._remove_ship_dir()
        logger.info("local engine: %d workers terminated", len(processes))

    def close(self) -> None:
        """Let running partitions finish, stop the workers."""
        pool, self._pool, self._closed = self._pool, None, True
        if pool is not None:
            try:
                pool.shutdown(wait=True, cancel_futures=True)
            except KeyboardInterrupt:
                self._pool = pool
                self._terminate()
                raise
            self._remove_ship_dir()

    def __enter__(self) -> LocalEngine:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is KeyboardInterrupt:
            self._terminate()
        else:
            self.close()

    def __repr__(self) -> str:
        return f"LocalEngine(workers={self._workers})"
