"""The engine that runs partitions as Ray tasks: a fleet that outgrows one machine.

``pip install "fleetbrake[ray]"``. :class:`RayEngine` connects to the cluster at ``address``
(``ray start --head`` on one machine, ``ray start --address HEAD`` on the others), or starts a
local one of ``workers`` CPUs when there is none. Every partition is a Ray task running the
stage's function on one item, with one thread per library (``RAYON_NUM_THREADS``,
``POLARS_MAX_THREADS``, the BLAS ones = 1: the tasks are the parallelism, one CPU each);
the compiled extension is the installed package on every node (the same wheel, the same
version). Results come back to the caller, the single writer of the warehouse, in the order
of the items (``map``) or as they finish (``map_unordered``), at most ``in_flight`` tasks
submitted but not yet handed over (``ray.wait``). A task's exception is re-raised as a
:class:`~fleetbrake.engine.base.PartitionError` naming the partition, as the local engine
does; the remaining tasks are cancelled without killing their workers (a task already
running finishes and its result is dropped), so a cancel never reaches a task submitted
after it. A task whose worker process dies (killed, out of memory, its node lost) is run
again, up to :data:`SYSTEM_RETRIES` times: a partition is a pure function of its item, the
writer commits only what comes back. Every task reports the node it ran on:
:attr:`RayEngine.tasks_per_node` counts them, and :meth:`RayEngine.close` logs how many ran on
how many nodes; it shuts down only a cluster the engine started itself.
"""

from __future__ import annotations

import importlib
import logging
import os
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

from fleetbrake.engine.base import (
    EngineConfigError,
    call_in_worker,
    default_workers,
    partition_error,
)
from fleetbrake.engine.local import WORKER_THREAD_ENV

__all__ = ["RAY_MISSING", "SYSTEM_RETRIES", "RayEngine", "import_ray"]

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")
K = TypeVar("K")

RAY_MISSING = '--engine ray needs Ray: pip install "fleetbrake[ray]"'
"""The one line said when Ray is not installed."""

SYSTEM_RETRIES = 2
"""Runs more of a task whose worker died (Ray's ``max_retries``: system failures only; an
exception the partition raises is never retried)."""

_PASSED_ENV = ("FLEETBRAKE_CACHE_DIR",)
"""Variables of the caller's environment the tasks see too (the only one the library reads)."""


def _call_on_node(fn: Callable[[T], R], item: T) -> tuple[str, R]:
    """The task: the id of the node it runs on, and ``fn(item)``."""
    node_id = str(importlib.import_module("ray").get_runtime_context().get_node_id())
    return node_id, call_in_worker(fn, item)


def import_ray() -> Any:
    """The ``ray`` module, or :class:`EngineConfigError` (exit 2) saying how to install it."""
    try:
        return importlib.import_module("ray")
    except ImportError:
        raise EngineConfigError(RAY_MISSING) from None


class RayEngine:
    """:class:`~fleetbrake.engine.base.Engine` on a Ray cluster: ``address`` (None: a local
    cluster of ``workers`` CPUs started here, or the one this process is already connected
    to); ``workers``: partitions at once (default: the cluster's CPUs)."""

    def __init__(
        self,
        address: str | None = None,
        workers: int | None = None,
        *,
        in_flight: int | None = None,
    ) -> None:
        if workers is not None and workers < 1:
            raise EngineConfigError(f"workers must be >= 1, got {workers}")
        if in_flight is not None and in_flight < 1:
            raise EngineConfigError(f"in_flight must be >= 1, got {in_flight}")
        self._ray = import_ray()
        self.address = address
        self._asked_workers = workers
        self._asked_in_flight = in_flight
        self._workers = workers if workers is not None else default_workers()
        self.in_flight = in_flight if in_flight is not None else 2 * self._workers
        self._remote: Any = None
        self._tasks_per_node: Counter[str] = Counter()
        self._owns_cluster = False
        self._closed = False

    @property
    def workers(self) -> int:
        return self._workers

    @property
    def tasks_per_node(self) -> dict[str, int]:
        """Tasks whose results came back, by the id of the node that ran them."""
        return dict(self._tasks_per_node)

    def start(self) -> None:
        """Connect to (or start) the cluster and declare the task."""
        if self._closed:
            raise RuntimeError("RayEngine: closed")
        if self._remote is not None:
            return
        ray = self._ray
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"include_dashboard": False}
            if self.address is None:  # "local": a new instance, whatever RAY_ADDRESS says
                kwargs["num_cpus"] = self._workers
            try:
                ray.init(address=self.address or "local", **kwargs)
            except (ConnectionError, ValueError) as error:
                raise EngineConfigError(
                    f"--address {self.address}: cannot connect to the Ray cluster ({error})"
                ) from None
            self._owns_cluster = True
        if self._asked_workers is None:
            cpus = int(ray.cluster_resources().get("CPU", 1))
            self._workers = max(1, cpus)
            if self._asked_in_flight is None:
                self.in_flight = 2 * self._workers
        env = dict(WORKER_THREAD_ENV)
        env.update({k: os.environ[k] for k in _PASSED_ENV if k in os.environ})
        self._remote = ray.remote(_call_on_node).options(
            num_cpus=1, max_retries=SYSTEM_RETRIES, runtime_env={"env_vars": env}
        )
        logger.info("ray engine: %d workers, %s", self._workers, self.address or "local cluster")

    def _submit(self, fn: Callable[[T], R], item: T) -> Any:
        return self._remote.remote(fn, item)

    def _cancel(self, refs: Iterable[Any]) -> None:
        for ref in refs:
            try:
                # not force=True: that kills the worker process, and Ray may already have
                # handed it the next task (seen as that task's WorkerCrashedError)
                self._ray.cancel(ref)
            except Exception:  # already finished, or the cluster is gone
                pass

    def _result(self, ref: Any) -> Any:
        ray = self._ray
        try:
            node_id, result = ray.get(ref)
        except ray.exceptions.RayTaskError as error:
            cause = error.as_instanceof_cause()
            # the original exception: its type, message and exit code
            original = getattr(error, "cause", None)
            raise (original if isinstance(original, BaseException) else cause) from None
        self._tasks_per_node[node_id] += 1
        return result

    def map(
        self,
        fn: Callable[[T], R],
        items: Iterable[T],
        *,
        name: Callable[[T], str] | None = None,
    ) -> Iterator[R]:
        self.start()
        fn_ref = self._ray.put(fn)  # shipped once, not with every task
        pending: deque[tuple[Any, T]] = deque()
        queue = iter(items)
        try:
            for item in queue:
                pending.append((self._submit(fn_ref, item), item))
                if len(pending) >= self.in_flight:
                    break
            while pending:
                ref, item = pending.popleft()
                try:
                    result = self._result(ref)
                except Exception as error:
                    raise partition_error(item, None, name, error) from error  # type: ignore[arg-type]
                for following in queue:
                    pending.append((self._submit(fn_ref, following), following))
                    break
                yield result
        finally:
            self._cancel(ref for ref, _ in pending)

    def map_unordered(
        self, fn: Callable[[T], R], keyed_items: Iterable[tuple[K, T]]
    ) -> Iterator[tuple[K, R]]:
        self.start()
        ray = self._ray
        fn_ref = ray.put(fn)
        pending: dict[Any, tuple[K, T]] = {}
        queue = iter(keyed_items)

        def submit_next() -> None:
            for key, item in queue:
                pending[self._submit(fn_ref, item)] = (key, item)
                return

        try:
            while len(pending) < self.in_flight:
                before = len(pending)
                submit_next()
                if len(pending) == before:
                    break
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    key, item = pending.pop(ref)
                    try:
                        result = self._result(ref)
                    except Exception as error:
                        raise partition_error(item, key, None, error) from error
                    submit_next()
                    yield key, result
        finally:
            self._cancel(pending)

    def close(self) -> None:
        """Disconnect; shut down the cluster only if this engine started it."""
        if self._closed:
            return
        self._closed = True
        self._remote = None
        if self._tasks_per_node:
            logger.info(
                "ray engine: %d tasks ran on %d nodes",
                self._tasks_per_node.total(),
                len(self._tasks_per_node),
            )
        if self._owns_cluster and self._ray.is_initialized():
            self._ray.shutdown()
            logger.info("ray engine: local cluster shut down")

    def __enter__(self) -> RayEngine:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        self.close()

    def __repr__(self) -> str:
        where = f"address={self.address!r}, " if self.address else ""
        return f"RayEngine({where}workers={self._workers})"
