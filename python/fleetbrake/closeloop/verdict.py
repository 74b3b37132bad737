"""The close loop's fifth phase, verdict: the chosen model's residual judged against the
sensor noise (``adequate``, ``unexplained``), and its parameters' 95 % intervals, the widest of
the Jacobian one on n_eff, the cluster-robust one and the delete-one-wagon-day jackknife,
widened for the report by a numerical term (the chosen effects refitted through coarser
meshes, Roache's grid convergence index of the shift) and an input term (the chosen parameters'
shift when the speed is read without the bias its noise puts in a magnitude), each added in
quadrature (:class:`Verdict`). The terms may be started ahead (:func:`start_terms`) and are
given on the fit the new revision ends with (:func:`chosen_verdict`)."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_for
from dataclasses import dataclass
from typing import Any

import numpy as np
import polars as pl

from fleetbrake.closeloop.candidates import Candidate, Families, FitRequests, adequacy_of
from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.evidence import Evidence
from fleetbrake.closeloop.fit import Fitted
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.leastsquares import (
    effects_at,
    fit_intervals,
    parameter_bounds,
    report_key,
)
from fleetbrake.closeloop.stats import (
    Adequacy,
    BlockedIntervals,
    DriftReport,
    combined_half_width,
    parameter_drift,
    with_numerical_term,
)
from fleetbrake.closeloop.terms import (
    InputTerm,
    Numerical,
    input_shift,
    input_term,
    numerical_term,
    speed_noise_kmh,
    with_speed_debiased,
)
from fleetbrake.closeloop.workers import Workers
from fleetbrake.simulation.predictions import Revision, WagonData

__all__ = [
    "TermsAhead",
    "Verdict",
    "baseline_verdict",
    "chosen_drift",
    "chosen_intervals",
    "chosen_verdict",
    "start_terms",
]


def chosen_intervals(chosen: Candidate, data: FitData) -> BlockedIntervals | None:
    """95 % intervals of the chosen effects' parameters, keyed as the report's ``parameters``:
    the widest of the Jacobian interval on the effective sample size, the cluster-robust one
    and the delete-one-wagon-day jackknife
    (:func:`~fleetbrake.closeloop.leastsquares.fit_intervals`)."""
    fitted = chosen.fitted
    if fitted is None or fitted.x.size == 0:
        return None
    got = fit_intervals(fitted, data)
    qualified = len({name.split(".", 1)[0] for name in fitted.names}) > 1

    def keyed(d: Mapping[str, Any]) -> dict[str, Any]:
        return {report_key(k, qualified): v for k, v in d.items()}

    return BlockedIntervals(
        intervals=keyed(got.intervals),
        jacobian=keyed(got.jacobian),
        sandwich=keyed(got.sandwich),
        jackknife=keyed(got.jackknife),
        blocks=got.blocks,
        method=keyed(got.method),
    )


def _numerical(
    best: Candidate,
    events: pl.DataFrame,
    loaded: Mapping[str, WagonData],
    base: Revision,
    families: Families,
    requests: FitRequests,
    config: CloseLoopConfig,
    workers: Workers,
    ready: Callable[[], object] | None = None,
) -> Numerical | None:
    """The chosen effects through coarser meshes, on the same fit events (``events``), from
    the chosen parameters: the numerical term of the reported intervals (None when not asked
    for or nothing was fitted). The coarse fits run on the engine's workers, once ``ready()``
    returns (their data built and written for the workers before)."""
    if not (config.numerical_grid_ratios and best.fitted is not None and best.fitted.x.size):
        return None
    t = time.perf_counter()
    added_now = families.added(best.effects)
    coarse_bases = [
        dataclasses.replace(base, refinement=base.refinement / ratio)
        for ratio in config.numerical_grid_ratios
    ]
    tasks = workers.shipped(
        [
            requests.task(
                FitData.build(loaded, events, config.simulation, coarse_base),
                [type(e) for e in added_now],
                added_now,
                max(4, config.max_nfev // 2),
                refit=True,
            )
            for coarse_base in coarse_bases
        ]
    )
    waited = _wait(ready)
    coarse_fits = workers.fit(tasks, "numerical")
    numerical = numerical_term(best.fitted, coarse_fits, base, config)
    workers.timing["numerical_s"] = time.perf_counter() - t - waited
    return numerical


def _input(
    best: Candidate,
    events: pl.DataFrame,
    loaded: Mapping[str, WagonData],
    base: Revision,
    families: Families,
    config: CloseLoopConfig,
    workers: Workers,
    ready: Callable[[], object] | None = None,
) -> InputTerm | None:
    """The chosen parameters' residual with the speed's magnitude bias taken out, on the same
    fit events (``events``), and the parameters' response to it by the fit's Jacobian: the
    input term of the reported intervals (None when not asked for, nothing was fitted or the
    speed has no noise). Its evaluations run in this process, one after another, once
    ``ready()`` returns (its data built before)."""
    speed_noise = speed_noise_kmh(loaded) if config.speed_input_term else math.nan
    if not (best.fitted is not None and best.fitted.x.size and speed_noise > 0.0):
        return None
    t = time.perf_counter()
    added_now = families.added(best.effects)
    debiased_data = FitData.build(
        with_speed_debiased(loaded, speed_noise), events, config.simulation, base
    )
    fitted_now, classes_now = best.fitted, [type(e) for e in added_now]
    lower, upper = parameter_bounds(classes_now)

    def residual_at(x: np.ndarray) -> np.ndarray:
        moved = [effects_at(fitted_now.effects, classes_now, x)]
        return workers.evaluate(debiased_data, moved, "input")[0]

    waited = _wait(ready)
    shift, steps = input_shift(fitted_now, residual_at, lower, upper, config.input_step_tolerance)
    inputs = input_term(fitted_now, shift, speed_noise, steps)
    workers.timing["input_s"] = time.perf_counter() - t - waited
    return inputs


def _wait(ready: Callable[[], object] | None) -> float:
    """Seconds spent in ``ready()`` (none when None)."""
    if ready is None:
        return 0.0
    t = time.perf_counter()
    ready()
    return time.perf_counter() - t


class TermsAhead:
    """The interval terms of a chosen fit (``chosen`` on ``events``, the wagons ``loaded``),
    on two threads of this process (``CloseLoopConfig.overlap``): their data built while the
    revision is made and re-flagged, their work done while it is refitted (the numerical
    term's thread hands its coarse fits to the engine's workers, the input term's evaluates
    here). Neither touches the warehouse (the
    parent stays its single writer) nor data the refit evaluates."""

    def __init__(
        self,
        chosen: Candidate,
        events: pl.DataFrame,
        loaded: Mapping[str, WagonData],
        numerical: Callable[[], Numerical | None],
        inputs: Callable[[], InputTerm | None],
        released: threading.Event,
    ) -> None:
        self.chosen, self.events, self.loaded = chosen, events, loaded
        self._released = released
        self._pool = ThreadPoolExecutor(2, thread_name_prefix="closeloop-terms")
        self._numerical: Future[Numerical | None] = self._pool.submit(numerical)
        self._inputs: Future[InputTerm | None] = self._pool.submit(inputs)

    def release(self) -> None:
        """The flags are judged (the engine's workers are free): the terms' work may start."""
        self._released.set()

    def same(
        self, chosen: Candidate, events: pl.DataFrame, loaded: Mapping[str, WagonData]
    ) -> bool:
        """Whether these terms are the ones of ``chosen`` on ``events`` (the refit moved
        nothing and loaded no other wagon)."""
        return (
            chosen is self.chosen and events is self.events and loaded.keys() == self.loaded.keys()
        )

    def result(self) -> tuple[Numerical | None, InputTerm | None]:
        """Both terms (an error in either raised here, as the sequential run would)."""
        try:
            return self._numerical.result(), self._inputs.result()
        finally:
            self._pool.shutdown(wait=True)

    def drop(self, wait: bool = True) -> None:
        """Not used: waited for (``wait``; their errors dropped) or left to end."""
        if wait:
            futures: list[Future[Any]] = [self._numerical, self._inputs]
            wait_for(futures)
        self._pool.shutdown(wait=wait, cancel_futures=True)


@dataclass(frozen=True)
class Verdict:
    """The chosen model judged: whether its fit residual is consistent with the sensor noise
    (``adequacy``), its parameters' 95 % statistical intervals (None: nothing fitted; the
    widest of the Jacobian one on n_eff, the cluster-robust one and the delete-one-wagon-day
    jackknife) and the numerical and input terms added to them for the report."""

    adequacy: Adequacy
    intervals: BlockedIntervals | None = None
    numerical: Numerical | None = None
    inputs: InputTerm | None = None
    drift: DriftReport | None = None
    """The parameters refitted per day of the fit events and their change over the days
    (:func:`~fleetbrake.closeloop.stats.parameter_drift`; None: fewer than two days)."""

    def reported_intervals(
        self, parameters: Mapping[str, float]
    ) -> Mapping[str, tuple[float, float]]:
        """The report's ``parameter_intervals``: the statistical ones widened by the numerical
        and input terms in quadrature about the fitted ``parameters``
        (:func:`~fleetbrake.closeloop.stats.with_numerical_term`)."""
        if self.intervals is None:
            return {}
        intervals: Mapping[str, tuple[float, float]] = self.intervals.intervals
        terms = [t.half_width for t in (self.numerical, self.inputs) if t is not None]
        if terms:
            intervals = with_numerical_term(intervals, parameters, combined_half_width(terms))
        return intervals


def baseline_verdict(evidence: Evidence, fitted: Fitted) -> Verdict:
    """The verdict when nothing is added: the baseline's residual against the noise."""
    return Verdict(
        adequacy_of(None, evidence.fit_data, fitted.base_kept, evidence.noise_k, fitted.current)
    )


def start_terms(
    chosen: Candidate,
    evidence: Evidence,
    families: Families,
    fitted: Fitted,
    config: CloseLoopConfig,
    workers: Workers,
) -> TermsAhead | None:
    """The interval terms of ``chosen`` on the fit events, started ahead on threads of this
    process (``CloseLoopConfig.overlap``, with an engine of worker processes; None
    otherwise): they depend on the chosen fit and its events only, so their data is built
    while the revision is made and re-flagged (this process is mostly idle then: the workers
    estimate and judge), and their work done once :meth:`TermsAhead.release` says the flags
    are judged, while the chosen effect is refitted; used when the refit leaves the answer
    as it was (:func:`chosen_verdict`)."""
    if not (config.overlap and workers.remote):
        return None
    released = threading.Event()
    events, snapshot, ready = evidence.events.fit, dict(evidence.loaded), released.wait
    base, requests = evidence.base, fitted.requests
    ahead = TermsAhead(
        chosen,
        events,
        snapshot,
        lambda: _numerical(
            chosen, events, snapshot, base, families, requests, config, workers, ready
        ),
        lambda: _input(chosen, events, snapshot, base, families, config, workers, ready),
        released,
    )
    workers.ahead = ahead
    return ahead


def chosen_verdict(
    chosen: Candidate,
    data: FitData,
    events: pl.DataFrame,
    loaded: Mapping[str, WagonData],
    started: TermsAhead | None,
    evidence: Evidence,
    families: Families,
    fitted: Fitted,
    config: CloseLoopConfig,
    workers: Workers,
) -> Verdict:
    """The verdict of ``chosen`` fitted on ``events`` (``data``; the wagons ``loaded``): its
    adequacy, its intervals and their terms, those ``started`` ahead when they were started
    for the same fit (else they are waited for and dropped, and computed here)."""
    numerical: Numerical | None
    inputs: InputTerm | None
    if started is not None:
        workers.ahead = None
    if started is not None and started.same(chosen, events, loaded):
        clock = time.perf_counter()
        numerical, inputs = started.result()
        workers.timing["terms_wait_s"] = time.perf_counter() - clock
    else:
        if started is not None:
            started.drop()
        base = evidence.base
        numerical = _numerical(
            chosen, events, loaded, base, families, fitted.requests, config, workers
        )
        inputs = _input(chosen, events, loaded, base, families, config, workers)
    return Verdict(
        adequacy_of(chosen, data, fitted.base_kept, evidence.noise_k, fitted.current),
        chosen_intervals(chosen, data),
        numerical,
        inputs,
        chosen_drift(chosen, data),
    )


def chosen_drift(chosen: Candidate, data: FitData) -> DriftReport | None:
    """The chosen effects' parameters per day of the fit events, and their drift, keyed as
    the report's ``parameters`` (None: nothing fitted or fewer than two days)."""
    fitted = chosen.fitted
    if fitted is None or fitted.x.size == 0:
        return None
    scored = fitted.scored
    return parameter_drift(
        fitted.jacobian,
        fitted.aligned,
        fitted.x,
        fitted.report_keys,
        data.blocks[scored],
        data.time_utc[scored],
    )
