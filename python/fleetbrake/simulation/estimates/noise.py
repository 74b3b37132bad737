"""The estimation stage's noise: σ_v the wagon's
(:func:`~fleetbrake.simulation.estimates.wagon.wagon_noise`), σ_w the revision's
(:func:`revision_power_noise`): fitted by maximum likelihood on the innovations of the close
loop's fit days (:func:`fit_revision_noise`, each fit wagon a partition,
:func:`fit_wagon_noise`), else the documented default."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.fleet.registry import Registry, WagonConfig
from fleetbrake.model.estimator import EstimatorNoise, NoiseFit, fit_noise, prepare
from fleetbrake.simulation.estimates.config import EstimationConfig
from fleetbrake.simulation.estimates.store import StoredNoise, store_noise, stored_noise
from fleetbrake.simulation.estimates.wagon import (
    estimator_series,
    wagon_estimate,
    wagon_noise,
    wagon_rom,
)
from fleetbrake.simulation.predictions import Revision
from fleetbrake.simulation.store import Mapper, arrow_frame, chunk_table, sample_parts
from fleetbrake.warehouse.connection import Warehouse

__all__ = [
    "NoiseFitTask",
    "WagonNoiseFit",
    "fit_revision_noise",
    "fit_wagon_noise",
    "revision_power_noise",
]

logger = logging.getLogger(__name__)


_MIN_FIT_READINGS = 100
"""A wagon's fit data need at least this many valid readings to take part in the noise fit."""


def revision_power_noise(
    wh: Warehouse, rev: Revision, config: EstimationConfig
) -> tuple[float, str]:
    """The revision's σ_w and where it came from: given (``config.noise``), fitted by
    :func:`fit_revision_noise` (``ml``), else the default (``default``)."""
    if config.noise is not None:
        return config.noise.power_w_per_sqrt_s, "given"
    found = stored_noise(wh, rev.name)
    if found is not None:
        return found.noise.power_w_per_sqrt_s, found.method
    return config.power_noise_w_per_sqrt_s, "default"


def _fit_wagon_ids(ids: Sequence[str], count: int) -> list[str]:
    """``count`` ids spread evenly over the sorted ``ids`` (all of them if fewer)."""
    ordered = sorted(ids)
    if len(ordered) <= count:
        return ordered
    if count == 1:
        return [ordered[0]]
    picks = {round(i * (len(ordered) - 1) / (count - 1)) for i in range(count)}
    return [ordered[i] for i in sorted(picks)]


@dataclass(frozen=True)
class NoiseFitTask:
    """One wagon's part of :func:`fit_revision_noise`: everything :func:`fit_wagon_noise`
    reads (picklable: an engine ships it to a worker)."""

    wagon: WagonConfig
    samples: pa.Table
    """The wagon's samples (``q_simulation_wagon_samples.sql``; those of its fit days are
    used)."""
    days: tuple[dt.date, ...]
    """Its fit days (UTC), sorted."""
    rev: Revision
    config: EstimationConfig

    def __str__(self) -> str:  # how an engine names the partition in an error
        return f"wagon {self.wagon.wagon_id}"


@dataclass(frozen=True)
class WagonNoiseFit:
    """What :func:`fit_wagon_noise` hands back: the wagon's maximum-likelihood fit and what
    it was fitted on (the JSON of ``estimator_noise.fit_wagons``)."""

    wagon_id: str
    fit: NoiseFit
    used: dict[str, float | list[str]]


def fit_wagon_noise(task: NoiseFitTask) -> WagonNoiseFit | None:
    """One wagon's σ_w by maximum likelihood on the first ``noise_fit_s`` seconds of its fit
    days, its own σ_v (:func:`wagon_noise`) held; None when those hold fewer than 100 valid
    readings. No database: a pure function of the task (the reduced model made, or read
    from its cache, once per process)."""
    config, wagon, rev = task.config, task.wagon, task.rev
    samples = arrow_frame(task.samples).filter(pl.col("time_utc").dt.date().is_in(list(task.days)))
    series, _ = estimator_series(
        wagon, samples, config.chain, max_s=config.noise_fit_s, config=config
    )
    if int(np.isfinite(series.reading_c).sum()) < _MIN_FIT_READINGS:
        return None
    sigma_v = wagon_noise(series, dataclasses.replace(config, noise=None), 1.0).measurement_k
    contact = None
    if rev.effects.state_dependent:  # the fade evaluated on a first estimate's contact
        # (its filtered contact: the passes of estimate_contact unsmoothed, 2.4 times cheaper)
        start = dataclasses.replace(
            config.estimator.noise,
            measurement_k=sigma_v,
            power_w_per_sqrt_s=config.power_noise_w_per_sqrt_s,
        )
        first = wagon_estimate(wagon, series, rev, config, start, smooth=False)
        contact = None if first is None else first.contact_mean_c
    problem = prepare(
        wagon_rom(wagon, rev.refinement),
        wagon,
        series,
        effects=rev.effects,
        config=config.estimator,
        contact_c=contact,
    )
    fit = fit_noise(
        [problem],
        config=config.estimator,
        min_power_noise_w_per_sqrt_s=config.min_power_noise_w_per_sqrt_s,
        measurement_k=sigma_v,
    )
    used: dict[str, float | list[str]] = {
        "days": [d.isoformat() for d in task.days],
        "seconds": float(series.time_s[-1] - series.time_s[0] + 1),
        "readings": fit.readings,
        "sigma_v_k": sigma_v,
        "sigma_w_w_per_sqrt_s": fit.noise.power_w_per_sqrt_s,
    }
    return WagonNoiseFit(wagon.wagon_id, fit, used)


def fit_revision_noise(
    wh: Warehouse,
    registry: Registry | Mapping[str, WagonConfig],
    rev: Revision,
    fit_events: pl.DataFrame,
    config: EstimationConfig | None = None,
    *,
    engine: Mapper | None = None,
) -> StoredNoise | None:
    """Fit the revision's σ_w by maximum likelihood on the innovations of its fit days, and
    store it (replacing any stored for the revision): what the close loop calls when it makes
    a revision, before estimating with it. The fit days: the UTC days of ``fit_events``
    (``wagon_id``, ``start_utc``) per wagon; ``config.noise_fit_wagons`` of those wagons
    spread over their sorted ids, the first ``config.noise_fit_s`` seconds of each one's fit
    days, each fitted on its own with its own σ_v (:func:`wagon_noise`) held; the revision's
    σ_w is the median (a wagon whose fit days hold a failing sensor does not set it). None,
    and nothing stored, when no wagon has 100 valid readings there.

    Each wagon's fit is a partition (:func:`fit_wagon_noise`): the parent reads the fit
    wagons' samples with one query, ``engine.map`` fits them (default: the builtin ``map``,
    in this process; an engine's workers otherwise), the result is the same either way."""
    config = config or EstimationConfig()
    wagons = registry.wagons if isinstance(registry, Registry) else registry
    days: dict[str, set[dt.date]] = {}
    if fit_events.height:
        for wagon_id, start in fit_events.select("wagon_id", "start_utc").iter_rows():
            if wagon_id in wagons and start is not None:
                days.setdefault(str(wagon_id), set()).add(start.date())
    ids = _fit_wagon_ids(list(days), config.noise_fit_wagons)
    tasks = []
    if ids:
        samples = chunk_table(wh, "q_simulation_chunk_samples", ids)
        parts = sample_parts(samples, ids)
        tasks = [
            NoiseFitTask(wagons[w], parts[w], tuple(sorted(days[w])), rev, config) for w in ids
        ]
    done = map(fit_wagon_noise, tasks) if engine is None else engine.map(fit_wagon_noise, tasks)
    fits: dict[str, NoiseFit] = {}
    used: dict[str, dict[str, float | list[str]]] = {}
    for found in done:
        if found is not None:
            fits[found.wagon_id], used[found.wagon_id] = found.fit, found.used
    if not fits:
        logger.warning(
            "revision %s: no fit day with %d valid readings to fit sigma_w on; the default "
            "%g W/sqrt(s) applies",
            rev.name,
            _MIN_FIT_READINGS,
            config.power_noise_w_per_sqrt_s,
        )
        return None
    noise = EstimatorNoise(
        float(np.median([f.noise.measurement_k for f in fits.values()])),
        float(np.median([f.noise.power_w_per_sqrt_s for f in fits.values()])),
    )
    logger.info(
        "revision %s: sigma_w %.4g W/sqrt(s), the median of %d wagons' maximum-likelihood fits",
        rev.name,
        noise.power_w_per_sqrt_s,
        len(fits),
    )
    stored = StoredNoise(
        noise,
        "ml",
        json.dumps(used, sort_keys=True),
        sum(f.readings for f in fits.values()),
        sum(f.log_likelihood for f in fits.values()),
        noise.power_w_per_sqrt_s <= config.min_power_noise_w_per_sqrt_s * 1.01,
    )
    store_noise(wh, rev.name, stored)
    return stored
