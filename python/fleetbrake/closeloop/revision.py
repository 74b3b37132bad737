"""The close loop's sixth phase, new revision: the chosen effects become a new model revision
(the current one, predicting with its parent's solver: before and after compare one model
form), every event is re-simulated with it and the virtual sensor re-estimated, the flags are
judged again with it (the baseline's flags take a fleet-wide misfit for weak brakes or failing
sensors) and the effect is refitted on the events usable then; a refit that moves the answer
beyond the fit's own uncertainty makes the revision again (:func:`new_revision` ->
:class:`NewRevision`, with the chosen model's verdict given on the fit it ends with)."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as wait_for
from dataclasses import dataclass

import polars as pl

from fleetbrake.closeloop.candidates import Candidate, Families, scored
from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.evidence import (
    Evidence,
    event_sets,
    load_wagons,
    rmse_from_predictions,
)
from fleetbrake.closeloop.fit import Fitted
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.leastsquares import FitResult, fit_intervals
from fleetbrake.closeloop.stats import BlockedIntervals
from fleetbrake.closeloop.verdict import TermsAhead, Verdict, chosen_verdict
from fleetbrake.closeloop.workers import Workers
from fleetbrake.engine import Engine
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import Effect, EffectSet
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.simulation.estimates import (
    EstimationConfig,
    estimate_wagons,
    fit_revision_noise,
)
from fleetbrake.simulation.predictions import Revision, WagonData, simulate_events
from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = [
    "NewRevision",
    "make_revision",
    "new_revision",
    "record_revision",
    "refit_moved",
    "reflag",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class NewRevision:
    """The new revision made, simulated and judged: the chosen candidate as it ends (refitted
    when the re-flagging moved it), the fit and holdout events as they stand then, the RMSE
    of both revisions on them (from ``v_predictions``) and the chosen model's verdict."""

    name: str
    chosen: Candidate
    added: list[Effect]
    """The effects it adds to the baseline."""
    fit_ids: list[str]
    hold_ids: list[str]
    flags_judged_with: str
    """The revision the flags the event sets leave out were judged with."""
    rmse: dict[tuple[str, str], float | None]
    """(``fit`` or ``holdout``, revision name) -> RMSE (None: no events)."""
    verdict: Verdict


@dataclass(frozen=True)
class _Standing:
    """The chosen fit as the revision stands: the candidate, the data and events it is fitted
    on, and the fit and holdout events the flags leave."""

    chosen: Candidate
    data: FitData
    events: pl.DataFrame
    fit: pl.DataFrame
    holdout: pl.DataFrame


def new_revision(
    wh: Warehouse,
    chosen: Candidate,
    ahead: TermsAhead | None,
    evidence: Evidence,
    families: Families,
    fitted: Fitted,
    config: CloseLoopConfig,
    engine: Engine | None,
    workers: Workers,
) -> NewRevision:
    """The close loop's sixth phase (see the module); ``ahead``: the interval terms started
    ahead (:func:`~fleetbrake.closeloop.verdict.start_terms`), released once the flags are
    judged."""
    base, fit = evidence.base, evidence.events.fit
    loaded = dict(evidence.loaded)
    name = _new_revision_name(wh, chosen.label)
    record_revision(wh, name, base, chosen)
    new_rev = Revision(name, chosen.effects, base.solver, base.refinement)
    event_ids = evidence.all_events["event_id"].to_list()
    release = ahead.release if ahead is not None else (lambda: None)
    t = time.perf_counter()
    try:
        make_revision(wh, evidence.wagons, new_rev, config.simulation, event_ids, fit, engine)
    except BaseException:
        release()
        raise
    workers.timing["revision_s"] = time.perf_counter() - t
    standing = _Standing(chosen, evidence.fit_data, fit, fit, evidence.events.holdout)
    flags_judged_with = base.name
    if config.reflag:
        standing = _judged_again(
            wh,
            new_rev,
            standing,
            loaded,
            event_ids,
            release,
            evidence,
            families,
            fitted,
            config,
            engine,
            workers,
        )
        flags_judged_with = name
    else:
        release()
    fit_ids = standing.fit["event_id"].to_list()
    hold_ids = standing.holdout["event_id"].to_list()
    rmse = {
        (key, rev): rmse_from_predictions(wh, rev, idset) if idset else None
        for key, idset in (("fit", fit_ids), ("holdout", hold_ids))
        for rev in (base.name, name)
    }
    wh.con.execute(
        sql("q_closeloop_set_revision_rmse"),
        {
            "name": name,
            "rmse_fit_k": rmse[("fit", name)],
            "rmse_holdout_k": rmse[("holdout", name)],
        },
    )
    best = standing.chosen
    verdict = chosen_verdict(
        best,
        standing.data,
        standing.events,
        loaded,
        ahead,
        evidence,
        families,
        fitted,
        config,
        workers,
    )
    added = families.added(best.effects)
    return NewRevision(name, best, added, fit_ids, hold_ids, flags_judged_with, rmse, verdict)


def _judged_again(
    wh: Warehouse,
    made: Revision,
    standing: _Standing,
    loaded: dict[str, WagonData],
    event_ids: Sequence[str],
    release: Callable[[], None],
    evidence: Evidence,
    families: Families,
    fitted: Fitted,
    config: CloseLoopConfig,
    engine: Engine | None,
    workers: Workers,
) -> _Standing:
    """The flags judged again with the ``made`` revision (the baseline's, which lacks the
    effect, take a fleet-wide misfit for weak brakes or failing sensors; ``release``d then),
    and the chosen effect refitted on the events usable now when they changed enough; a refit
    that moves the answer beyond the fit's own uncertainty makes the revision again. The
    wagons of the new fit events are added to ``loaded``."""
    base, sim, timing, wagons = evidence.base, config.simulation, workers.timing, evidence.wagons
    best = standing.chosen
    fit_ids = standing.fit["event_id"].to_list()
    t = time.perf_counter()
    try:
        reflag(wh, wagons, made, sim, engine)
    finally:  # the terms' work may start (the workers are the flags' until now)
        release()
    fit, holdout, _ = event_sets(wh, base.name, config, evidence.unknown_heat)
    timing["reflag_s"] = time.perf_counter() - t
    standing = dataclasses.replace(standing, fit=fit, holdout=holdout)
    changed = set(fit["event_id"].to_list()) ^ set(fit_ids)
    if not (fit.height and len(changed) >= config.refit_changed_fraction * max(1, len(fit_ids))):
        return standing
    t = time.perf_counter()
    loaded.update(load_wagons(wh, wagons, fit, sim, have=loaded))
    refit_data = FitData.build(loaded, fit, sim, base)
    added = families.added(best.effects)
    (res,) = workers.fit(
        [
            fitted.requests.task(
                refit_data,
                [type(e) for e in added],
                added,
                max(1, config.max_nfev // 2),
                refit=True,
            )
        ],
        "reflag_refit",
    )
    moved = refit_moved(best, res, fit_intervals(res, refit_data), config.refit_tolerance)
    timing["reflag_refit_s"] = time.perf_counter() - t
    logger.debug(
        "refitted on %d events after re-flagging: %s, chosen %s (moved beyond tolerance: %s)",
        fit.height,
        res.effects,
        best.effects,
        ", ".join(moved) or "none",
    )
    if not moved:
        return standing
    # the answer changed: the revision made again with the refitted parameters
    t = time.perf_counter()
    best = scored(res, best.n_parameters, "fit", evidence.n_eff)
    _set_revision_effects(wh, made.name, best.effects)
    remade = Revision(made.name, best.effects, base.solver, base.refinement)
    make_revision(wh, wagons, remade, sim, event_ids, fit, engine)
    reflag(wh, wagons, remade, sim, engine)
    after, holdout, _ = event_sets(wh, base.name, config, evidence.unknown_heat)
    timing["remake_s"] = time.perf_counter() - t
    return _Standing(best, refit_data, fit, after, holdout)


def reflag(
    wh: Warehouse,
    wagons: Mapping[str, WagonConfig],
    revision: Revision,
    sim: SimulationConfig,
    engine: Engine | None = None,
) -> None:
    """Judge every wagon's flags again with ``revision``: the simulation stage's flow, its
    timeline simulated and stored first (nothing to do for a wagon already simulated with it
    from the same data), then the flags judged from what was stored."""
    from fleetbrake.flags import raise_flags

    simulate_events(wh, wagons, revision, sim, progress=False, engine=engine)
    raise_flags(wh, wagons, revision.name, engine=engine)


def make_revision(
    wh: Warehouse,
    wagons: Mapping[str, WagonConfig],
    revision: Revision,
    sim: SimulationConfig,
    event_ids: Sequence[str],
    fit: pl.DataFrame,
    engine: Engine | None,
) -> None:
    """Simulate ``event_ids`` with the new ``revision`` and re-estimate the virtual sensor
    with it (every wagon), its sigma_w fitted first on the days of the ``fit`` events (a
    property of the revision: docs/estimator.md, "How each noise is set").

    The simulation and the estimate are independent (the estimate and the sigma_w fit read
    the samples, not the predictions; they write other tables), so the simulation runs on a
    second connection (a cursor of ``wh``'s, its writes on its own writer thread) in a thread
    of its own while sigma_w is fitted and the wagons are estimated: the partitions of both
    share the engine's workers, which do not wait between the three steps for the parent's
    reads and last commits. The same rows as the three one after the other (the
    same pure functions of the same partitions); the simulation's progress bar is not shown
    (one live display at a time)."""
    config = EstimationConfig(chain=sim.chain)
    ids = list(event_ids)
    cursor = wh.con.cursor()
    try:
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="revision-simulation") as pool:
            simulated = pool.submit(
                simulate_events,
                Warehouse(wh.path, cursor, None),
                wagons,
                revision,
                sim,
                event_ids=ids,
                progress=False,
                engine=engine,
            )
            try:
                fit_revision_noise(wh, wagons, revision, fit, config, engine=engine)
                estimate_wagons(wh, wagons, revision, config, engine=engine)
            finally:
                # the thread ends before anything is raised: the estimate's error, else the
                # simulation's
                wait_for([simulated])
            simulated.result()
    finally:
        cursor.close()


def refit_moved(
    chosen: Candidate, refit: FitResult, intervals: BlockedIntervals, tolerance: float
) -> list[str]:
    """The parameters (``effect.parameter``) of the re-flag ``refit`` that moved from the
    ``chosen`` candidate's by more than ``tolerance`` times the half-width of their 95 %
    interval (``intervals``, the refit's own, keyed as its names): a move inside that is
    within the fit's uncertainty and leaves the revision as it was made. A parameter the
    chosen candidate lacks counts as moved; one whose interval is not finite never does (the
    data do not determine it: its move changes nothing)."""
    before = {f"{e.name}.{k}": v for e in chosen.effects for k, v in e.parameters.items()}
    moved = []
    for name, value in zip(refit.names, refit.x, strict=True):
        if name not in before:
            moved.append(name)
            continue
        lo, hi = intervals.intervals.get(name, (-math.inf, math.inf))
        half = 0.5 * (hi - lo)
        if math.isfinite(half) and abs(float(value) - before[name]) > tolerance * half:
            moved.append(name)
    return moved


def _set_revision_effects(wh: Warehouse, name: str, effects: EffectSet) -> None:
    wh.con.execute(
        sql("q_closeloop_set_revision_effects"),
        {"name": name, "parameters_json": json.dumps({"effects": effects.to_list()})},
    )


def _new_revision_name(wh: Warehouse, label: str) -> str:
    ((count,),) = wh.con.execute(sql("q_closeloop_revision_count")).fetchall()
    return f"r{count}-{label}"


def record_revision(wh: Warehouse, name: str, parent: Revision, best: Candidate) -> None:
    """Record ``best`` as revision ``name``, the current one, child of ``parent``, predicting
    with the parent's solver (a closed loop changes the effects, never the model form)."""
    now = dt.datetime.now(dt.UTC).replace(tzinfo=None)
    with wh.transaction() as con:
        con.execute(sql("q_closeloop_clear_current"))
        con.execute(
            sql("q_closeloop_insert_revision"),
            {
                "name": name,
                "parent": parent.name,
                "effect": best.label,
                "parameters_json": json.dumps({"effects": best.effects.to_list()}),
                "solver": parent.solver,
                "refinement": parent.refinement,
                "created_utc": now,
            },
        )
