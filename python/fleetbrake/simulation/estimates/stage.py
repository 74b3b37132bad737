"""The estimation stage of ``fleetbrake run`` and ``close-loop`` (:func:`estimate_wagons`):
which spans changed since they were estimated with a revision (:func:`model_key`, the
spans' data keys), their partitions estimated on the engine and their rows written by the
parent, several whole spans per transaction."""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import json
import logging
import os
from collections.abc import Collection, Iterable, Mapping
from dataclasses import asdict, dataclass, field

from fleetbrake.fleet.registry import Registry, WagonConfig
from fleetbrake.ingest.spans import Span, SpanKey, ranges_of, stale_spans, stored_spans
from fleetbrake.simulation.estimates.config import EstimationConfig
from fleetbrake.simulation.estimates.noise import revision_power_noise
from fleetbrake.simulation.estimates.spans import forget_span_estimates, replace_span_estimates
from fleetbrake.simulation.estimates.store import estimated_spans, estimation_chunk
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
    """The wagons some of whose spans were (re)estimated."""
    spans_estimated: list[tuple[str, dt.datetime, dt.datetime]] = field(default_factory=list)
    """The spans (re)estimated, per second: (``wagon_id``, ``span_start_utc``,
    ``span_end_utc``)."""
    rows: int = 0
    """Rows written to ``contact_estimates``."""
    power_noise_w_per_sqrt_s: float | None = None
    """The revision's σ_w (None when there was nothing to estimate)."""
    noise_method: str | None = None
    """Where σ_w came from: ``default``, ``ml`` (fitted by the close loop) or ``given``."""
    skipped: list[str] = field(default_factory=list)


def model_key(wagon: WagonConfig, rev: Revision, config: EstimationConfig, power: float) -> str:
    """What a span's stored estimates depend on besides its data (its σ_v is a function of
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
    spans: Collection[SpanKey] = (),
    progress: bool | None = None,
    engine: Mapper | None = None,
) -> EstimationReport:
    """Estimate with ``rev`` every span (:mod:`fleetbrake.ingest.spans`) whose data,
    registry entry, the revision's σ_w or the configuration changed since it was last
    estimated with it, and the spans of ``spans`` (those the flags judge in this run: their
    flags are judged on estimates computed in the same run), or, forced, every span of
    ``wagons`` and no other; storing a row per logged second, each span whole in one
    transaction, several per transaction up to ``config.batch_rows`` rows. The rows of spans
    that no longer exist are deleted first. Each span stands alone: its results depend on its
    own data and the revision only (:func:`wagon_noise`, :func:`revision_power_noise`)."""
    config = config or EstimationConfig()
    wagons_by_id = registry.wagons if isinstance(registry, Registry) else registry
    report = EstimationReport()
    current = stored_spans(wh)
    ledger = {key: row.ledger for key, row in estimated_spans(wh, rev.name).items()}
    if wagons is not None:
        only = set(wagons)
        current = [s for s in current if s.wagon_id in only]
    held = {s.wagon_id for s in current}
    report.skipped = [
        f"wagon {w}: no valid registry entry" for w in sorted(held - set(wagons_by_id))
    ]
    power, report.noise_method = revision_power_noise(wh, rev, config)
    keys = {w: model_key(entry, rev, config, power) for w, entry in wagons_by_id.items()}
    forced = {s.key for s in current} if wagons is not None else set(spans)
    todo, orphans = stale_spans(current, ledger, lambda s: keys.get(s.wagon_id), forced)
    if wagons is None:
        forget_span_estimates(wh, rev.name, ranges_of(orphans))
    if not todo:
        return report
    report.power_noise_w_per_sqrt_s = power
    units = [(wagons_by_id[span.wagon_id], span, key) for span, key in todo]

    def read(source: Warehouse, part: list[tuple[WagonConfig, Span, str]]) -> EstimateChunk:
        return estimation_chunk(source, part, rev, config, power)

    def write(batch: list[EstimateResult]) -> None:
        replace_span_estimates(wh, rev.name, batch)

    results = chunk_pipeline(
        wh,
        units,
        unit_rows=lambda unit: unit[1].sample_rows,
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
        task = bar.add_task("estimating spans", total=len(units))
        for result in results:
            logger.info(
                "%s: %d seconds estimated with revision %s (%.0f %% steady)",
                result.span or f"wagon {result.wagon_id}",
                result.seconds,
                result.revision,
                100 * result.frozen_fraction,
            )
            if result.wagon_id not in report.wagons_estimated:
                report.wagons_estimated.append(result.wagon_id)
            span = result.span
            assert span is not None  # the stage's tasks are spans
            report.spans_estimated.append((span.wagon_id, span.start_utc, span.end_utc))
            report.rows += result.seconds
            bar.advance(task)
    return report
