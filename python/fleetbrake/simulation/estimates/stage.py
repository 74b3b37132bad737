"""The estimation stage of ``fleetbrake run`` and ``close-loop`` (:func:`estimate_wagons`):
which wagons changed since they were estimated with a revision (:func:`model_key`, the
stored data keys), their partitions estimated on the engine and their rows written by the
parent, several whole wagons per transaction."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field

from fleetbrake.fleet.registry import Registry, WagonConfig
from fleetbrake.simulation.estimates.config import EstimationConfig
from fleetbrake.simulation.estimates.noise import revision_power_noise
from fleetbrake.simulation.estimates.store import (
    estimated_wagon_ids,
    estimated_wagons,
    estimation_chunk,
    estimation_data_keys,
    forget_wagon,
    replace_estimates,
)
from fleetbrake.simulation.estimates.wagon import EstimateChunk, EstimateResult, estimate_chunk
from fleetbrake.simulation.predictions import Revision
from fleetbrake.simulation.store import Mapper, chunk_pipeline
from fleetbrake.warehouse.connection import Warehouse

__all__ = ["EstimationReport", "estimate_wagons", "model_key"]

logger = logging.getLogger(__name__)


@dataclass
class EstimationReport:
    """What the estimation stage did."""

    wagons_estimated: list[str] = field(default_factory=list)
    rows: int = 0
    """Rows written to ``contact_estimates``."""
    power_noise_w_per_sqrt_s: float | None = None
    """The revision's σ_w (None when there was nothing to estimate)."""
    noise_method: str | None = None
    """Where σ_w came from: ``default``, ``ml`` (fitted by the close loop) or ``given``."""
    skipped: list[str] = field(default_factory=list)


def model_key(wagon: WagonConfig, rev: Revision, config: EstimationConfig, power: float) -> str:
    """What a wagon's stored estimates depend on besides its data (its σ_v is a function of
    its data, or given)."""
    estimator = dataclasses.asdict(config.estimator)
    estimator.pop("noise")
    text = json.dumps(
        {
            "wagon": asdict(wagon),
            "effects": rev.effects.to_list(),
            "refinement": rev.refinement,
            "estimator": estimator,
            "power_noise_w_per_sqrt_s": power,
            "given_noise": None if config.noise is None else dataclasses.asdict(config.noise),
            # the stage's noise when none is given: σ_v and σ_w are the wagon's and the
            # revision's, the rest (σ_q, the fallbacks) the estimator config's
            "default_noise": dataclasses.asdict(config.estimator.noise),
            "min_measurement_noise_k": config.min_measurement_noise_k,
            "frozen": [config.frozen_min_s, config.frozen_resolution_k, config.frozen_noise_k],
            "speed_median_samples": config.chain.speed_median_samples,
            "bridge_max_s": config.chain.bridge_max_s,
            # the kernel: the Rust one computes every estimate (None, as in the stored keys)
            "kernel": None,
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()


def estimate_wagons(
    wh: Warehouse,
    registry: Registry | Mapping[str, WagonConfig],
    rev: Revision,
    config: EstimationConfig | None = None,
    *,
    wagons: Iterable[str] | None = None,
    progress: bool | None = None,
    engine: Mapper | None = None,
) -> EstimationReport:
    """Estimate with ``rev`` every wagon whose data, registry entry, the revision's σ_w or
    the configuration changed since it was last estimated with it (or, forced, ``wagons``),
    storing a row per logged second; each wagon whole in one transaction, several per
    transaction up to ``config.batch_rows`` rows. Each wagon's results depend on its own
    data and the revision only (:func:`wagon_noise`, :func:`revision_power_noise`)."""
    config = config or EstimationConfig()
    wagons_by_id = registry.wagons if isinstance(registry, Registry) else registry
    report = EstimationReport()
    keys = estimation_data_keys(wh)
    done = estimated_wagons(wh, rev.name)
    forced = set(wagons or ())
    if wagons is None:
        for wagon_id in sorted(set(done) - set(keys)):  # its samples are gone
            forget_wagon(wh, wagon_id)
    candidates = [w for w in keys if w in wagons_by_id]
    report.skipped = [f"wagon {w}: no valid registry entry" for w in keys if w not in wagons_by_id]
    if not candidates:
        return report
    power, report.noise_method = revision_power_noise(wh, rev, config)
    report.power_noise_w_per_sqrt_s = power
    todo = []
    for wagon_id in candidates:
        if wagons is not None and wagon_id not in forced:
            continue
        wagon_key = model_key(wagons_by_id[wagon_id], rev, config, power)
        stored = done.get(wagon_id)
        if (
            wagon_id in forced
            or stored is None
            or (stored.data_key, stored.model_key) != (keys[wagon_id], wagon_key)
        ):
            todo.append((wagons_by_id[wagon_id], keys[wagon_id], wagon_key))
    if not todo:
        return report
    holding = estimated_wagon_ids(wh, rev.name)  # the others' rows are only inserted
    by_id = {wagon.wagon_id: (wagon, data_key, key) for wagon, data_key, key in todo}

    def read(source: Warehouse, ids: list[str]) -> EstimateChunk:
        return estimation_chunk(source, [by_id[w] for w in ids], rev, config, power)

    def write(batch: list[EstimateResult]) -> None:
        replace_estimates(wh, rev.name, batch, delete=any(r.wagon_id in holding for r in batch))

    results = chunk_pipeline(
        wh,
        list(by_id),
        read=read,
        compute=estimate_chunk,
        write=write,
        result_rows=lambda result: result.seconds,
        chunk_rows=config.chunk_rows,
        batch_rows=config.batch_rows,
        engine=engine,
    )
    show = progress if progress is not None else os.isatty(1)
    from rich.progress import Progress

    with Progress(disable=not show, transient=True) as bar:
        task = bar.add_task("estimating wagons", total=len(todo))
        for result in results:
            logger.info(
                "wagon %s: %d seconds estimated with revision %s (%.0f %% steady)",
                result.wagon_id,
                result.seconds,
                result.revision,
                100 * result.frozen_fraction,
            )
            report.wagons_estimated.append(result.wagon_id)
            report.rows += result.seconds
            bar.advance(task)
    return report
