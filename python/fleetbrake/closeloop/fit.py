"""The close loop's third phase, fit: every single effect fitted on the screening events (the
earliest of each wagon: short chains), the fit events far off under the best of them left out
as outliers (data the flags missed), and the best refitted on every fit event from its screened
parameters (the next ones too when within ``bic_margin`` of it) (:func:`fit_candidates` ->
:class:`Fitted`). The candidates are fitted in parallel on the engine's workers."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from fleetbrake.closeloop.candidates import Candidate, Families, FitRequests, scored
from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.evidence import Evidence
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.leastsquares import kept_seconds
from fleetbrake.closeloop.stats import (
    event_rms,
    information_criterion,
    outlier_events,
    root_mean_square,
)
from fleetbrake.closeloop.workers import Workers
from fleetbrake.model.effects import EffectSet

__all__ = ["Fitted", "Outliers", "find_outliers", "fit_candidates"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Outliers:
    """The fit events left out as outliers, as the report gives them (``judged_with`` None:
    no outlier rule applied)."""

    events: int
    threshold_k: float | None = None
    median_event_rms_k: float | None = None
    judged_with: str | None = None
    """The effects the events' residual was judged under (the best screened single)."""
    event_ids: tuple[str, ...] = ()
    worst: tuple[tuple[str, float], ...] = ()
    """The worst few: event id and residual RMS (K)."""


@dataclass(frozen=True)
class Fitted:
    """The candidates fitted, and what the choice compares them with."""

    current: Candidate
    """The baseline as a candidate (nothing fitted), on the fit events less the outliers."""
    base_kept: tuple[np.ndarray, np.ndarray]
    """The baseline's residual on the seconds kept, and those seconds (fit data)."""
    requests: FitRequests
    """How later fits are asked for (the outliers left out)."""
    candidates: list[Candidate]
    """The refitted candidates, then the ones screened only."""
    comparable: list[Candidate]
    """Those fitted on every fit event (else every one), best criterion first."""
    outliers: Outliers


def find_outliers(
    data: FitData, effects: EffectSet, noise_k: float, config: CloseLoopConfig
) -> Outliers:
    """The fit events left out as outliers under ``effects`` (the best screened single): how
    many, the threshold and the worst few with their RMS."""
    rms = event_rms(data.residual(effects), data.event, len(data.event_ids))
    worst, threshold = outlier_events(
        rms,
        noise_k,
        noise_factor=config.outlier_noise_factor,
        z=config.outlier_z,
        max_fraction=config.max_outlier_fraction,
    )
    finite = rms[np.isfinite(rms)]
    for i in worst:
        logger.info("outlier event %s: residual RMS %.3f K", data.event_ids[i], rms[i])
    return Outliers(
        events=int(worst.size),
        threshold_k=round(threshold, 4) if math.isfinite(threshold) else None,
        median_event_rms_k=round(float(np.median(finite)), 5) if finite.size else None,
        judged_with=str(effects),
        event_ids=tuple(sorted(data.event_ids[i] for i in worst)),
        worst=tuple((data.event_ids[i], round(float(rms[i]), 4)) for i in worst[:5]),
    )


def fit_candidates(
    evidence: Evidence, families: Families, config: CloseLoopConfig, workers: Workers
) -> Fitted:
    """The close loop's third phase (see the module)."""
    timing = workers.timing
    fit_data, screen_data, n_eff = evidence.fit_data, evidence.screen_data, evidence.n_eff
    requests = FitRequests(evidence.base.effects, config.diff_step, config.refit_step_tolerance)
    r_all, ok = evidence.residual, evidence.ok
    current = Candidate(
        evidence.base.effects,
        root_mean_square(r_all[ok]),
        information_criterion(r_all[ok], 0, n_eff["fit"]),
        0,
    )
    base_kept = (r_all[ok], ok)
    # screening: every effect on the earliest fit events of each wagon, carried chains
    # as the predictions' (in parallel across the engine's workers)
    t = time.perf_counter()
    classes = families.singles
    results = workers.fit(
        [requests.task(screen_data, [cls], None, config.max_nfev) for cls in classes], "screen"
    )
    screened = [
        scored(res, len(cls.PARAMETER_RANGES), evidence.screened_on, n_eff)
        for cls, res in zip(classes, results, strict=True)
    ]
    for c in screened:
        logger.debug("screened %s: %s rmse %.4f K", c.label, c.effects, c.rmse_fit_k)
    screened.sort(key=lambda c: c.bic)
    timing["screen_s"] = time.perf_counter() - t
    # outlier events: data the flags did not catch, far off under the best screened single
    # effect, are left out of every fit on the fit events (and of the verdict)
    t = time.perf_counter()
    outliers = Outliers(events=0)
    if screened and config.max_outlier_fraction > 0:
        outliers = find_outliers(fit_data, screened[0].effects, evidence.noise_k, config)
        excluded = frozenset(outliers.event_ids)
        requests = FitRequests(
            requests.base, requests.diff_step, requests.refit_step_tolerance, excluded
        )
        workers.count("outliers", 1)
        kept = kept_seconds(fit_data, excluded)
        if kept is not None:
            keep = ok & kept
            base_kept = (r_all[keep], keep)
            current = Candidate(
                evidence.base.effects,
                root_mean_square(r_all[keep]),
                information_criterion(r_all[keep], 0, n_eff["fit"]),
                0,
            )
    timing["outliers_s"] = time.perf_counter() - t
    # the best refitted on every fit event, from the screened parameters (the second too
    # when within the margin of it)
    t = time.perf_counter()
    top = screened[: config.refit] if screen_data is not fit_data else []
    top = [c for c in top if c.bic < screened[0].bic + config.bic_margin] or top[:1]
    refits = workers.fit(
        [
            requests.task(
                fit_data,
                [type(e) for e in families.added(c.effects)],
                families.added(c.effects),
                max(4, config.max_nfev // 2),
                refit=True,
            )
            for c in top
        ],
        "refit",
    )
    candidates = [
        scored(res, c.n_parameters, "fit", n_eff) for c, res in zip(top, refits, strict=True)
    ]
    candidates += screened[len(top) :] if top else screened
    for c in candidates[: len(top)]:
        logger.debug("refitted %s: %s rmse %.4f K", c.label, c.effects, c.rmse_fit_k)
    timing["refit_s"] = time.perf_counter() - t
    # compared on the fit events only: a candidate screened only is ranked by screening
    comparable = [c for c in candidates if c.fitted_on == "fit"] or candidates
    comparable.sort(key=lambda c: c.bic)
    return Fitted(current, base_kept, requests, candidates, comparable, outliers)
