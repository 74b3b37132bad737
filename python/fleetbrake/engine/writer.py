"""The single writer's commits on a thread of their own: :class:`WriteBehind`.

A stage's parent process is the warehouse's one writer; it also reads the next partitions
and keeps the engine's workers fed. With its transactions on a thread of their own (DuckDB
releases the GIL while it inserts), its reads, its workers and its inserts overlap instead of
adding up (a writer blocked in its inserts leaves the workers idle:
``docs/decisions/0007-reading-and-writing-in-chunks.md``). Used by the simulation and the
estimate (:func:`fleetbrake.simulation.store.chunk_pipeline`), the event detection
(:func:`fleetbrake.ingest.events.update_events`) and the ingestion's batches of files
(:class:`fleetbrake.ingest.ledger.Batch`); knows nothing of the warehouse: ``write``
is the stage's.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Generic, TypeVar

__all__ = ["WriteBehind"]

B = TypeVar("B")


class WriteBehind(Generic[B]):
    """The single writer's commits on a thread of their own, one batch at a time and in
    order, while the caller reads the next partitions (through a second connection:
    :func:`fleetbrake.warehouse.connection.reader`) and keeps the engine's workers fed.
    :meth:`submit` waits for the batch before (raising its error) and starts this one;
    leaving the ``with`` block waits for the last. At most two batches are held: the one
    being written and the one being gathered."""

    def __init__(self, write: Callable[[B], None]) -> None:
        self._write = write
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="warehouse-writer")
        self._running: Future[None] | None = None

    def submit(self, batch: B) -> None:
        self.wait()
        self._running = self._pool.submit(self._write, batch)

    def wait(self) -> None:
        """Wait for the batch being written (raising its error)."""
        running, self._running = self._running, None
        if running is not None:
            running.result()

    def __enter__(self) -> WriteBehind[B]:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        try:
            if exc_type is None:
                self.wait()
        finally:
            self._pool.shutdown(wait=True)  # an error: the batch being written ends first
