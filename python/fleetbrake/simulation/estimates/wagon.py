"""The estimate of one span of a wagon (the stage's computation, no database): its logged
seconds as the estimator's series (:func:`estimator_series`, a frozen sensor's readings
dropped, :func:`frozen_readings`), its noise (:func:`wagon_noise`), its estimate under a
revision (:func:`wagon_estimate`) and the partitions an engine runs (:func:`estimate_wagon`
on an :class:`EstimateTask`, :func:`estimate_chunk` on an :class:`EstimateChunk`), whose rows
the parent writes. Each span stands alone: the filter starts from its prior at the span's
first reading, and σ_v is the span's own (``docs/decisions/0009-spans.md``)."""

from __future__ import annotations

import dataclasses
import datetime as dt
from dataclasses import dataclass

import numpy as np
import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.ingest.spans import Span
from fleetbrake.model.estimator import (
    ContactEstimate,
    EstimatorNoise,
    estimate_contact,
    measurement_noise,
)
from fleetbrake.model.estimator import WagonSeries as EstimatorSeries
from fleetbrake.model.rom import ReducedModel
from fleetbrake.simulation.chains import ChainParams, constant_runs
from fleetbrake.simulation.estimates.config import EstimationConfig
from fleetbrake.simulation.estimates.rows import estimate_rows
from fleetbrake.simulation.predictions import Revision
from fleetbrake.simulation.series import WagonSeries, running_median
from fleetbrake.simulation.store import arrow_frame, chunk_name, sample_parts

__all__ = [
    "EstimateChunk",
    "EstimateResult",
    "EstimateTask",
    "chunk_tasks",
    "estimate_chunk",
    "estimate_wagon",
    "estimator_series",
    "frozen_readings",
    "reading_noise_k",
    "wagon_estimate",
    "wagon_noise",
    "wagon_rom",
]


_ROMS: dict[tuple[object, ...], ReducedModel] = {}
_ROMS_KEPT = 16


def wagon_rom(wagon: WagonConfig, refinement: float) -> ReducedModel:
    """The wagon's reduced model (the estimator's process model, whatever the revision's
    solver), made or read from the cache once per process."""
    key = (wagon.geometry, wagon.block, wagon.sensor_point_m, refinement)
    rom = _ROMS.get(key)
    if rom is None:
        if len(_ROMS) >= _ROMS_KEPT:
            _ROMS.clear()
        rom = _ROMS[key] = ReducedModel.for_wagon(wagon, refinement=refinement)
    return rom


def estimator_series(
    wagon: WagonConfig,
    samples: pl.DataFrame,
    chain: ChainParams,
    *,
    max_s: float | None = None,
    config: EstimationConfig | None = None,
) -> tuple[EstimatorSeries, dt.datetime | None]:
    """The wagon's logged seconds as the estimator's series (seconds since the first
    sample, returned with it; None without samples): the simulation's 1 Hz grid per span
    (:meth:`WagonSeries.spans_from_frame`), its interpolated pressure and air, the running
    median of its speed, the valid readings (NaN where missing or faulty), at the seconds with
    a sample row, the readings of a frozen sensor (:func:`frozen_readings`, with ``config``'s
    numbers) NaN too. ``max_s``: only the first this many seconds."""
    spans = WagonSeries.spans_from_frame(
        wagon.wagon_id,
        samples,
        ambient_default_c=float(wagon.ambient_temp_c),
        bridge_max_s=chain.bridge_max_s,
    )
    if not spans:
        empty = np.zeros(0)
        return EstimatorSeries(empty, empty, empty, empty, empty, wagon.wagon_id), None
    t0 = spans[0].t0
    parts: dict[str, list[np.ndarray]] = {
        name: [] for name in ("time_s", "p_bar", "speed_kmh", "ambient_c", "reading_c")
    }
    for span in spans:
        k = np.flatnonzero(span.present)
        offset = int((span.t0 - t0).total_seconds())
        parts["time_s"].append((offset + k).astype(np.float64))
        parts["p_bar"].append(span.pressure_bar[k])
        parts["speed_kmh"].append(running_median(span.speed_kmh, chain.speed_median_samples)[k])
        parts["ambient_c"].append(span.ambient_c[k])
        parts["reading_c"].append(span.measured_c[k])
    values = {name: np.concatenate(p) for name, p in parts.items()}
    if max_s is not None:
        keep = values["time_s"] < max_s
        values = {name: v[keep] for name, v in values.items()}
    frozen = frozen_readings(values["time_s"], values["reading_c"], config)
    values["reading_c"] = np.where(frozen, np.nan, values["reading_c"])
    return EstimatorSeries(wagon_id=wagon.wagon_id, **values), t0


def _on_grid(time_s: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``values`` at their whole seconds on a 1 Hz grid from the first (NaN elsewhere), and
    each value's index there."""
    k = np.rint(time_s - time_s[0]).astype(np.int64)
    grid = np.full(int(k[-1]) + 1, np.nan)
    grid[k] = values
    return grid, k


def frozen_readings(
    time_s: np.ndarray, reading_c: np.ndarray, config: EstimationConfig | None = None
) -> np.ndarray:
    """Which readings a frozen sensor gave (True: skip the update): runs of readings
    unchanged to within ``frozen_resolution_k`` for ``frozen_min_s`` or more
    (:func:`~fleetbrake.simulation.chains.constant_runs`, the detector the flags'
    ``find_frozen`` uses), when the sensor's noise outside them
    (:func:`~fleetbrake.model.estimator.measurement_noise`) is at least ``frozen_noise_k``;
    all False for a sensor quiet enough to repeat itself (or whose noise cannot be told)."""
    config = config or EstimationConfig()
    out = np.zeros(reading_c.size, dtype=bool)
    if reading_c.size < config.frozen_min_s:
        return out
    grid, k = _on_grid(time_s, reading_c)
    found = constant_runs(grid, config.frozen_min_s, config.frozen_resolution_k)
    if not found:
        return out
    stuck = np.zeros(grid.size, dtype=bool)
    for a, b, _ in found:
        stuck[a:b] = True
    rest = np.where(stuck, np.nan, grid)
    noise = measurement_noise(np.arange(grid.size, dtype=np.float64), rest)
    if noise is None or noise < config.frozen_noise_k:
        return out
    return stuck[k]


@dataclass(frozen=True)
class EstimateTask:
    """One span's partition of the estimation stage: everything :func:`estimate_wagon`
    reads (picklable: an engine ships it to a worker)."""

    wagon: WagonConfig
    samples: pa.Table
    """The span's samples (``q_simulation_span_samples.sql``)."""
    rev: Revision
    config: EstimationConfig
    power_noise_w_per_sqrt_s: float
    """The revision's σ_w (σ_v is the span's, :func:`wagon_noise`)."""
    data_key: str
    model_key: str
    span: Span | None = None
    """The span (None: samples of another range, estimated alone, not to be stored)."""

    def __str__(self) -> str:  # how an engine names the partition in an error
        return f"wagon {self.wagon.wagon_id}" if self.span is None else str(self.span)


@dataclass(frozen=True)
class EstimateResult:
    """What :func:`estimate_wagon` hands back for the parent to write."""

    wagon_id: str
    revision: str
    data_key: str
    model_key: str
    rows: pa.Table
    """The rows of ``contact_estimates``
    (:data:`~fleetbrake.simulation.estimates.rows.ESTIMATE_SCHEMA`)."""
    frozen_fraction: float
    """Share of the seconds the filter ran at its steady state (the fast path)."""
    noise: EstimatorNoise | None = None
    """The noise it was estimated with (None: no seconds)."""
    span: Span | None = None
    """The span estimated (its task's)."""

    @property
    def seconds(self) -> int:
        return int(self.rows.num_rows)


def wagon_estimate(
    wagon: WagonConfig,
    series: EstimatorSeries,
    rev: Revision,
    config: EstimationConfig,
    noise: EstimatorNoise,
    *,
    smooth: bool = True,
) -> ContactEstimate | None:
    """The wagon's estimate under ``rev`` (None without seconds); ``smooth=False``: filtered
    only (the filtered values are the same either way, the smoother costs more than the
    filter: ``docs/estimator.md``, "Speed")."""
    if series.time_s.size == 0:
        return None
    return estimate_contact(
        wagon_rom(wagon, rev.refinement),
        wagon,
        series,
        effects=rev.effects,
        config=dataclasses.replace(config.estimator, noise=noise),
        smooth=smooth,
    )


def estimate_wagon(task: EstimateTask) -> EstimateResult:
    """One span estimated from its partition, no database: a pure function of the task (the
    reduced model made, or read from its cache, once per process). The filter starts at the
    span's first reading and σ_v comes from the span's readings: the rows depend on the
    span's data and the revision only, never on the order its files landed."""
    wagon = task.wagon
    series, t0 = estimator_series(
        wagon, arrow_frame(task.samples), task.config.chain, config=task.config
    )
    noise = wagon_noise(series, task.config, task.power_noise_w_per_sqrt_s)
    est = wagon_estimate(wagon, series, task.rev, task.config, noise)
    return EstimateResult(
        wagon_id=wagon.wagon_id,
        revision=task.rev.name,
        data_key=task.data_key,
        model_key=task.model_key,
        rows=estimate_rows(wagon.wagon_id, task.rev.name, t0, est),
        frozen_fraction=0.0 if est is None else est.frozen_fraction,
        noise=None if est is None else noise,
        span=task.span,
    )


@dataclass(frozen=True)
class EstimateChunk:
    """Several spans' partitions of the estimation stage read together: the chunk's samples
    as one Arrow table with ``part_ix`` and ``file_id`` (``q_simulation_chunk_span_samples.sql``,
    the spans' time ranges only, in stored order), and each span's entry and model key.
    :func:`chunk_tasks` cuts it into the spans' :class:`EstimateTask` (the tables
    :func:`~fleetbrake.simulation.estimates.store.estimate_task` reads: a test compares them),
    which :func:`estimate_chunk` estimates one by one. Picklable."""

    units: tuple[tuple[WagonConfig, Span, str], ...]
    """(entry, span, model key) of each span, in order."""
    samples: pa.Table
    rev: Revision
    config: EstimationConfig
    power_noise_w_per_sqrt_s: float

    def __str__(self) -> str:  # how an engine names the partition in an error
        return chunk_name([span.label for _, span, _ in self.units])


def chunk_tasks(chunk: EstimateChunk) -> list[EstimateTask]:
    """The chunk cut into its spans' tasks, each span's samples sorted as the per-span
    query sorts them (:func:`fleetbrake.simulation.store.wagon_parts`)."""
    samples = sample_parts(chunk.samples, [span.label for _, span, _ in chunk.units], "part_ix")
    return [
        EstimateTask(
            wagon,
            samples[span.label],
            chunk.rev,
            chunk.config,
            chunk.power_noise_w_per_sqrt_s,
            span.data_key,
            model_key,
            span,
        )
        for wagon, span, model_key in chunk.units
    ]


def estimate_chunk(chunk: EstimateChunk) -> list[EstimateResult]:
    """Each span of the chunk estimated (:func:`estimate_wagon`), in order: a pure function
    of the chunk, so an engine can run it in a worker process."""
    return [estimate_wagon(task) for task in chunk_tasks(chunk)]


def wagon_noise(
    series: EstimatorSeries, config: EstimationConfig, power_noise_w_per_sqrt_s: float
) -> EstimatorNoise:
    """The noise a span is estimated with: ``config.noise`` when given; else σ_v from the
    series' own readings (the span's) (:func:`~fleetbrake.model.estimator.measurement_noise`, at least
    ``min_measurement_noise_k``; the estimator's default with fewer than 10 second
    differences) and the revision's σ_w, the rest (σ_q, the manoeuvre test's) ``config.
    estimator.noise``'s. A function of the series' data alone."""
    if config.noise is not None:
        return config.noise
    sigma_v = reading_noise_k(series.time_s, series.reading_c, config)
    return dataclasses.replace(
        config.estimator.noise, measurement_k=sigma_v, power_w_per_sqrt_s=power_noise_w_per_sqrt_s
    )


def reading_noise_k(
    time_s: np.ndarray, reading_c: np.ndarray, config: EstimationConfig | None = None
) -> float:
    """σ_v (K) from a wagon's readings (NaN: none): :func:`~fleetbrake.model.estimator.
    measurement_noise`, at least ``min_measurement_noise_k``, the estimator's default with
    fewer than 10 second differences. The one rule of the stage and of the flags'
    innovation scale (``flags.estimated.sensor_noise_k``)."""
    config = config or EstimationConfig()
    found = measurement_noise(time_s, reading_c)
    sigma_v = config.estimator.noise.measurement_k if found is None else found
    return max(sigma_v, config.min_measurement_noise_k)
