"""Where a close loop's fits and evaluations run (:class:`Workers`): the engine's workers or
this process, the data each is handed, and what they cost (candidates fitted, kernel calls,
model evaluations and seconds per phase: the report's ``cost``)."""

from __future__ import annotations

import dataclasses
import tempfile
import threading
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from fleetbrake.closeloop import fitdata
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.leastsquares import EvalTask, FitResult, FitTask, eval_task, fit_task
from fleetbrake.engine import Engine, InlineEngine, LocalEngine
from fleetbrake.model.effects import EffectSet

__all__ = ["Pending", "Workers"]


class Pending(Protocol):
    """Work started ahead on threads of this process (the interval terms), dropped when the
    run ends before it is used."""

    def drop(self, wait: bool = True) -> None: ...


@dataclass(frozen=True)
class _Key:
    """A task's place in its batch, named as the task is (an engine's error names it)."""

    index: int
    name: str

    def __str__(self) -> str:
        return self.name


class Workers:
    """Where a run's fits go: the engine (the inline one when none), and the data it is
    handed. Work that runs in this process (no engine, or a single task: an engine is not
    worth one) gets the data objects; the local engine's workers read each data set once
    from a file this run writes (:func:`fitdata.store`, only when tasks go to them), Ray gets
    them with the task. Safe to use from two threads at once (the interval terms beside the
    re-flag refit: ``CloseLoopConfig.overlap``)."""

    def __init__(self, engine: Engine | None) -> None:
        self.engine = engine
        self.files = isinstance(engine, LocalEngine)
        self._dir: tempfile.TemporaryDirectory[str] | None = None
        self._refs: dict[int, FitData | str] = {}
        self._lock = threading.Lock()
        self._stored = 0
        self.ahead: Pending | None = None
        """The interval terms started ahead (``CloseLoopConfig.overlap``), until used."""
        self.remote = engine is not None and not isinstance(engine, InlineEngine)
        """Whether tasks run in other processes (their kernel calls counted from their
        results)."""
        self.kernel_calls = 0
        self.fits = 0
        self.timing: dict[str, float] = {}
        self.evaluations: dict[str, int] = {}
        """Model evaluations (passes over a data set's events) per phase, the Jacobians'
        perturbed vectors included: the report's ``cost.evaluations``."""

    def count(self, phase: str, evaluations: int) -> None:
        with self._lock:
            self.evaluations[phase] = self.evaluations.get(phase, 0) + evaluations

    def ref(self, data: FitData | str) -> FitData | str:
        """What an engine's task is handed for ``data``: the object, or with the local
        engine the file it is stored in (written once per data set)."""
        if not self.files or isinstance(data, str):
            return data
        with self._lock:  # one file per data set (its id forgotten when it is freed)
            if id(data) not in self._refs:
                if self._dir is None:
                    self._dir = tempfile.TemporaryDirectory(prefix="fleetbrake-closeloop-")
                path = Path(self._dir.name) / f"fitdata-{self._stored}.pickle"
                self._stored += 1
                self._refs[id(data)] = str(fitdata.store(data, path))
                weakref.finalize(data, self._refs.pop, id(data), None)
            return self._refs[id(data)]

    def _inline(self, items: list[Any]) -> bool:
        return self.engine is None or len(items) <= 1

    def _map(self, fn: Any, items: list[Any]) -> list[Any]:
        """``fn`` of each item, in the items' order; on an engine taken as they finish (a
        long fit at the head of the queue does not hold back the next submissions)."""
        if self._inline(items):
            return [fn(item) for item in items]
        out: list[Any] = [None] * len(items)
        keyed = [(_Key(i, str(item)), item) for i, item in enumerate(items)]
        for key, result in self.engine.map_unordered(fn, keyed):  # type: ignore[union-attr]
            out[key.index] = result
        return out

    def shipped(self, tasks: list[FitTask]) -> list[FitTask]:
        """``tasks`` as the engine is handed them: with the local engine's workers, their
        data written now (:meth:`ref`)."""
        if self._inline(tasks):
            return tasks
        return [dataclasses.replace(t, data=self.ref(t.data)) for t in tasks]

    def fit(self, tasks: list[FitTask], phase: str) -> list[FitResult]:
        tasks = self.shipped(tasks)
        results: list[FitResult] = self._map(fit_task, tasks)
        self.count(phase, sum(r.evaluations for r in results))
        with self._lock:
            if self.remote and len(tasks) > 1:
                self.kernel_calls += sum(r.kernel_calls for r in results)
            self.fits += len(results)
        return results

    def evaluate(
        self, data: FitData, effect_sets: Sequence[EffectSet], phase: str
    ) -> list[np.ndarray]:
        self.count(phase, len(effect_sets))
        tasks = [EvalTask(data, (e,)) for e in effect_sets]
        if not self._inline(tasks):
            tasks = [dataclasses.replace(t, data=self.ref(data)) for t in tasks]
        out = self._map(eval_task, tasks)
        if self.remote and len(effect_sets) > 1:
            with self._lock:
                self.kernel_calls += sum(calls for _, calls in out)
        return [residuals[0] for residuals, _ in out]

    def close(self) -> None:
        if self.ahead is not None:  # an error before they were used: not waited for
            self.ahead.drop(wait=False)
            self.ahead = None
        if self._dir is not None:
            self._dir.cleanup()
            self._dir = None
