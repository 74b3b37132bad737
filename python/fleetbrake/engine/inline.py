"""The engine that runs every partition in the calling process, one at a time."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

from fleetbrake.engine.base import partition_error

__all__ = ["InlineEngine"]

T = TypeVar("T")
R = TypeVar("R")
K = TypeVar("K")


class InlineEngine:
    """:class:`~fleetbrake.engine.base.Engine` in the calling process: ``workers = 1``; the
    same results and errors as :class:`~fleetbrake.engine.local.LocalEngine`, no pickling.

    ``threads > 1``: ``map`` runs ``fn`` on that many threads of this process, at most
    ``2 * threads`` items ahead of the caller (for work that releases the GIL: reading,
    decompressing and parsing files), still yielding in order."""

    workers = 1

    def __init__(self, threads: int = 1) -> None:
        self.threads = max(1, threads)

    def map(
        self,
        fn: Callable[[T], R],
        items: Iterable[T],
        *,
        name: Callable[[T], str] | None = None,
    ) -> Iterator[R]:
        if self.threads > 1:
            yield from self._map_threads(fn, items, name)
            return
        for item in items:
            try:
                result = fn(item)
            except Exception as error:
                raise partition_error(item, None, name, error) from error  # type: ignore[arg-type]
            yield result

    def _map_threads(
        self, fn: Callable[[T], R], items: Iterable[T], name: Callable[[T], str] | None
    ) -> Iterator[R]:
        with ThreadPoolExecutor(max_workers=self.threads) as pool:
            pending: deque[tuple[Future[R], T]] = deque()
            queue = iter(items)
            try:
                for item in queue:
                    pending.append((pool.submit(fn, item), item))
                    if len(pending) >= 2 * self.threads:
                        break
                while pending:
                    future, item = pending.popleft()
                    try:
                        result = future.result()
                    except Exception as error:
                        raise partition_error(item, None, name, error) from error  # type: ignore[arg-type]
                    for following in queue:
                        pending.append((pool.submit(fn, following), following))
                        break
                    yield result
            finally:
                for future, _ in pending:
                    future.cancel()

    def map_unordered(
        self, fn: Callable[[T], R], keyed_items: Iterable[tuple[K, T]]
    ) -> Iterator[tuple[K, R]]:
        for key, item in keyed_items:
            try:
                result = fn(item)
            except Exception as error:
                raise partition_error(item, key, None, error) from error
            yield key, result

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> InlineEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return "InlineEngine()" if self.threads == 1 else f"InlineEngine(threads={self.threads})"
