"""Executors of partitions: the one interface every stage hands its work to.

A stage cuts its work into *partitions* (a wagon, or a wagon's new files), each processed by
a pure function of its inputs (picklable: a module-level function, or a
:func:`functools.partial` of one), and consumes the results in the parent process, which is
the single writer of the warehouse::

    from fleetbrake.engine import make_engine

    with make_engine("local", workers=2) as engine:
        for result in engine.map(parse_partition, partitions):   # in the order given
            write(result)                                          # one transaction each

The interface (:class:`Engine`), which the distributed engine implements too
(``--engine ray``):

* ``map(fn, items, *, name=None)``: the results of ``fn(item)``, yielded in the order of
  ``items``; ``items`` is consumed lazily and at most ``in_flight`` items are submitted but
  not yet yielded, so memory holds a few partitions' data, never the fleet's.
* ``map_unordered(fn, keyed_items)``: ``(key, fn(item))`` pairs of ``(key, item)`` pairs, as
  they finish (same bound).
* A partition's exception is re-raised in the caller as :class:`PartitionError` naming the
  partition (``name(item)``, else the key, else the item's ``str``), with the worker's
  exception as its cause; the remaining work is cancelled. An expected failure
  (:class:`~fleetbrake.errors.FleetbrakeError`) keeps its exit code.
* ``start()``: start the workers now (else at the first ``map``).
* ``close()`` (and ``with``): the workers stop; a KeyboardInterrupt while mapping cancels what
  is queued, stops the workers and propagates.
* ``workers``: how many partitions run at once.

Engines: :class:`InlineEngine` (the calling process, one partition at a time: tests, and
``workers=1``) and :class:`LocalEngine` (a pool of ``workers`` processes on this machine,
``spawn``-started, each limited to one Rayon and one polars thread), and
:class:`~fleetbrake.engine.ray.RayEngine` (``make_engine("ray", workers, address=...)``: Ray
tasks on a cluster, or on a local Ray instance; needs ``pip install "fleetbrake[ray]"`` and
is imported only when asked for, so ``fleetbrake.engine`` never imports Ray). The builtin
``map`` can stand in wherever an engine is optional.
"""

from __future__ import annotations

from fleetbrake.engine.base import Engine, EngineConfigError, PartitionError, default_workers
from fleetbrake.engine.factory import ENGINES, make_engine
from fleetbrake.engine.inline import InlineEngine
from fleetbrake.engine.local import LocalEngine

__all__ = [
    "ENGINES",
    "Engine",
    "EngineConfigError",
    "InlineEngine",
    "LocalEngine",
    "PartitionError",
    "default_workers",
    "make_engine",
]
