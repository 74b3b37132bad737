"""The engine interface, its errors and what every engine shares."""

from __future__ import annotations

import os
import pickle
from collections.abc import Callable, Iterable, Iterator
from typing import Protocol, TypeVar

from fleetbrake.errors import EXIT_FAILED, ConfigError, FleetbrakeError

__all__ = [
    "Engine",
    "EngineConfigError",
    "PartitionError",
    "call_in_worker",
    "default_workers",
    "partition_error",
]

T = TypeVar("T")
R = TypeVar("R")
K = TypeVar("K")

_NAME_CHARS = 120
"""A partition named by its ``str`` is cut to this many characters in messages."""


class EngineConfigError(ConfigError):
    """An engine that cannot be made as asked (unknown name, bad worker count): exit 2."""


class PartitionError(FleetbrakeError):
    """A partition's function raised: the message names the partition and the failure; the
    worker's exception is the ``__cause__``. Keeps the exit code of an expected failure."""

    def __init__(self, partition: str, error: BaseException) -> None:
        super().__init__(f"partition {partition}: {type(error).__name__}: {error}")
        self.partition = partition
        self.exit_code = error.exit_code if isinstance(error, FleetbrakeError) else EXIT_FAILED

    def __reduce__(self) -> tuple[object, ...]:  # picklable (a distributed engine ships it)
        return (_rebuild_partition_error, (self.partition, str(self), self.exit_code))


def _rebuild_partition_error(partition: str, message: str, exit_code: int) -> PartitionError:
    error = PartitionError.__new__(PartitionError)
    FleetbrakeError.__init__(error, message)
    error.partition = partition
    error.exit_code = exit_code
    return error


def partition_name(item: object, key: object, name: Callable[[object], str] | None) -> str:
    """How messages name a partition: ``name(item)``, else its key, else its ``str``."""
    if name is not None:
        return name(item)
    text = str(key) if key is not None else str(item)
    return text if len(text) <= _NAME_CHARS else text[: _NAME_CHARS - 3] + "..."


def partition_error(
    item: object, key: object, name: Callable[[object], str] | None, error: BaseException
) -> PartitionError:
    return PartitionError(partition_name(item, key, name), error)


def default_workers() -> int:
    """The cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


class Engine(Protocol):
    """Runs a function over partitions (see :mod:`fleetbrake.engine`)."""

    @property
    def workers(self) -> int:
        """Partitions that run at once."""
        ...

    def map(
        self,
        fn: Callable[[T], R],
        items: Iterable[T],
        *,
        name: Callable[[T], str] | None = None,
    ) -> Iterator[R]:
        """``fn(item)`` for each item, in the order of ``items``, a bounded number ahead."""
        ...

    def map_unordered(
        self, fn: Callable[[T], R], keyed_items: Iterable[tuple[K, T]]
    ) -> Iterator[tuple[K, R]]:
        """``(key, fn(item))`` for each ``(key, item)``, as they finish."""
        ...

    def start(self) -> None:
        """Start the workers now rather than at the first ``map`` (nothing for inline)."""
        ...

    def close(self) -> None:
        """Stop the workers (the engine cannot map afterwards)."""
        ...

    def __enter__(self) -> Engine: ...

    def __exit__(self, exc_type: object, *rest: object) -> None: ...


def call_in_worker(fn: Callable[[T], R], item: T) -> R:
    """``fn(item)`` in a worker process or task; an exception that would not reach the parent
    intact (it does not pickle) is replaced by a RuntimeError saying what it was."""
    try:
        return fn(item)
    except Exception as error:
        try:
            pickle.loads(pickle.dumps(error))
        except Exception:
            raise RuntimeError(f"{type(error).__name__}: {error}") from None
        raise
