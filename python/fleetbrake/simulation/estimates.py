"""The estimation stage of ``fleetbrake run`` and ``close-loop``: the virtual sensor's contact
temperature at every logged second of every wagon (``v_contact_estimates``, interface v2).

::

    from fleetbrake.simulation.estimates import estimate_wagons, wagon_estimates

    report = estimate_wagons(wh, registry, rev, engine=engine)   # what changed, re-estimated
    frame = wagon_estimates(wh, "SGG-0001", rev.name)            # one wagon's rows, polars

Per wagon, with :mod:`fleetbrake.model.estimator` (a Kalman filter and Rauch-Tung-Striebel
smoother on the reduced model's state, augmented with the unexplained friction-face heat
power; ``docs/estimator.md``), over every logged second of the wagon's whole data as one
series: the declared inputs are the simulation's (the same 1 Hz grid, the speed's running
median of :class:`~fleetbrake.simulation.chains.ChainParams`), the revision's effects
applied; missing, faulty and frozen readings (:func:`frozen_readings`) skip the update; an
unlogged interval longer than ``max_interpolated_gap_s`` is a standstill.

Stored (``warehouse/sql/schema_estimates.sql``):

* ``contact_estimates`` (behind ``v_contact_estimates``): one row per wagon, logged second and
  revision, the filtered and smoothed estimates with their 95 % bounds, the innovation, and
  for the flags and recordings the smoothed maximum and power and the innovation's sd;
* ``estimated_wagons``: the keys each wagon was estimated from, and the noise it was
  estimated with. A wagon whose data (its files and samples: ``q_estimates_wagon_data.sql``),
  registry entry, revision, the revision's σ_w and configuration are unchanged is not
  estimated again (a second ``run`` adds nothing); a late file re-estimates its wagon only,
  whose rows are replaced whole in one transaction (several wagons per transaction, never
  splitting one);
* ``estimator_noise``: a revision's σ_w fitted by maximum likelihood on the innovations of
  the close loop's fit days (:func:`fit_revision_noise`, called by the close loop when it
  makes a revision).

The noise (``docs/estimator.md``): a wagon's results are a function of its own data and the
revision only. σ_v is the **wagon's**, from its own readings (:func:`wagon_noise`: the median
absolute deviation of their second differences); σ_w is the **revision's**: fitted when the
close loop makes it, else the documented default ``EstimationConfig.power_noise_w_per_sqrt_s``.
``EstimationConfig.noise`` gives both instead (method ``given``).

The wagon is the unit of work: the parent reads a chunk of whole wagons' samples as Arrow
with one query (:func:`estimation_chunk`, about ``EstimationConfig.chunk_rows`` samples;
:func:`estimate_task` reads one wagon's, the same table), :func:`estimate_chunk` cuts it into
the wagons' tasks and :func:`estimate_wagon` (pure, picklable, no database) estimates each
and returns its rows as Arrow; the parent, the single writer, commits them in bulk, several
whole wagons per transaction (``EstimationConfig.batch_rows``), on a writer thread while it
reads and hands out the next chunks (the simulation's pipeline,
:func:`~fleetbrake.simulation.store.chunk_pipeline`).
``engine``: the builtin ``map`` by default, an engine's workers otherwise; the rows are the
same either way. :func:`fit_revision_noise` fits its wagons on the engine the same way
(:func:`fit_wagon_noise`, one partition a wagon).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import json
import logging
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.fleet.registry import Registry, WagonConfig
from fleetbrake.model.estimator import (
    ContactEstimate,
    EstimatorConfig,
    EstimatorNoise,
    NoiseFit,
    estimate_contact,
    fit_noise,
    measurement_noise,
    prepare,
)
from fleetbrake.model.estimator import WagonSeries as EstimatorSeries
from fleetbrake.model.rom import ReducedModel
from fleetbrake.simulation.chains import ChainParams, constant_runs
from fleetbrake.simulation.predictions import Revision
from fleetbrake.simulation.series import WagonSeries, running_median
from fleetbrake.simulation.store import (
    Mapper,
    chunk_name,
    chunk_pipeline,
    chunk_table,
    sample_parts,
    utc_now,
)
from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = [
    "DEFAULT_POWER_NOISE_W_PER_SQRT_S",
    "ESTIMATE_SCHEMA",
    "EstimateChunk",
    "EstimateResult",
    "EstimateTask",
    "EstimatedWagon",
    "EstimationConfig",
    "EstimationReport",
    "NoiseFitTask",
    "StoredNoise",
    "WagonNoiseFit",
    "chunk_tasks",
    "estimate_chunk",
    "estimate_task",
    "estimate_wagon",
    "estimate_wagons",
    "estimated_wagon_ids",
    "estimated_wagons",
    "estimation_chunk",
    "estimation_data_keys",
    "estimator_series",
    "fit_revision_noise",
    "fit_wagon_noise",
    "frozen_readings",
    "reading_noise_k",
    "replace_estimates",
    "revision_power_noise",
    "stored_noise",
    "wagon_estimates",
    "wagon_noise",
]

logger = logging.getLogger(__name__)

DEFAULT_POWER_NOISE_W_PER_SQRT_S = 3.0
"""σ_w of a revision the close loop did not fit (``docs/estimator.md``: the evidence)."""


@dataclass(frozen=True)
class EstimationConfig:
    """How the stage estimates (everything it is set with; the estimator's own numbers in
    ``estimator``, whose ``noise`` is replaced by the revision's)."""

    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    chain: ChainParams = field(default_factory=ChainParams)
    """The simulation's numbers the declared inputs are built with (the speed's running
    median, the spans): pass the simulation's, so the estimate is driven as the prediction."""
    noise: EstimatorNoise | None = None
    """None: σ_v per wagon from its readings, σ_w the revision's (stored by
    :func:`fit_revision_noise`, else ``power_noise_w_per_sqrt_s``); else these for every wagon
    (method ``given``)."""
    power_noise_w_per_sqrt_s: float = DEFAULT_POWER_NOISE_W_PER_SQRT_S
    """σ_w of a revision without a fitted one (the declared revision): the documented default
    (``docs/estimator.md``: the maximum-likelihood fits on generated fleets behind it)."""
    min_measurement_noise_k: float = 0.02
    """σ_v's floor (a sensor whose log is rounded, or nearly noise-free, still has this)."""
    frozen_min_s: int = 120
    """s: readings unchanged (to within ``frozen_resolution_k``) this long are a frozen
    sensor's and skip the update (:func:`frozen_readings`; the flags' ``frozen_min_s``)."""
    frozen_resolution_k: float = 0.01
    """K: the resolution a frozen reading repeats to (the flags' ``frozen_resolution_k``)."""
    frozen_noise_k: float = 0.03
    """K: ... when the sensor's noise outside such runs is at least this (a noisy sensor
    cannot repeat itself that long; a near noise-free one can: its runs are kept; the flags'
    ``frozen_noise_k``)."""
    noise_fit_wagons: int = 5
    """:func:`fit_revision_noise`: how many wagons σ_w is fitted on (spread over the sorted
    ids of the wagons with fit days), each on its own; the revision's is the median."""
    noise_fit_s: float = 21_600.0
    """:func:`fit_revision_noise`: the first this many seconds of each fit wagon's fit days."""
    min_power_noise_w_per_sqrt_s: float = 3.0
    """σ_w's floor in the fit (``docs/estimator.md``: why)."""
    batch_rows: int = 1_000_000
    """Several wagons per transaction, up to about this many rows (a wagon never split; the
    simulation's transactions: DuckDB's insert costs about half the processor time per row
    at 1 M rows that it does at 0.2 M, ``docs/benchmarks.md``). Changes no row."""
    chunk_rows: int = 200_000
    """The parent reads the wagons' samples a chunk of whole wagons at a time, about this
    many samples (one query, :func:`estimation_chunk`), and a worker estimates the chunk's
    wagons one by one (the simulation's ``chunk_rows``). Changes no row."""
    kernel: str | None = None
    """The estimator's kernel: None (Rust when built), ``rust`` or ``numpy``."""

    def __post_init__(self) -> None:
        if self.noise_fit_wagons < 1:
            raise ValueError("EstimationConfig.noise_fit_wagons must be >= 1")
        if not self.noise_fit_s > 0:
            raise ValueError("EstimationConfig.noise_fit_s must be > 0")
        if not (self.power_noise_w_per_sqrt_s > 0 and self.min_measurement_noise_k > 0):
            raise ValueError(
                "EstimationConfig.power_noise_w_per_sqrt_s and min_measurement_noise_k must be > 0"
            )
        if self.frozen_min_s < 2 or not self.frozen_resolution_k > 0:
            raise ValueError(
                "EstimationConfig.frozen_min_s must be >= 2 and frozen_resolution_k > 0"
            )
        if self.batch_rows < 1 or self.chunk_rows < 1:
            raise ValueError("EstimationConfig.batch_rows and chunk_rows must be >= 1")
        if self.kernel not in (None, "rust", "numpy"):
            raise ValueError(f"EstimationConfig.kernel: unknown {self.kernel!r}")


@dataclass
class EstimationReport:
    wagons_estimated: list[str] = field(default_factory=list)
    rows: int = 0
    """Rows written to ``contact_estimates``."""
    power_noise_w_per_sqrt_s: float | None = None
    """The revision's σ_w (None when there was nothing to estimate)."""
    noise_method: str | None = None
    """Where σ_w came from: ``default``, ``ml`` (fitted by the close loop) or ``given``."""
    skipped: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class EstimatedWagon:
    """A row of ``estimated_wagons``."""

    wagon_id: str
    data_key: str
    model_key: str
    seconds: int
    created_utc: dt.datetime
    measurement_k: float | None = None
    """σ_v it was estimated with (the wagon's own unless given)."""
    power_w_per_sqrt_s: float | None = None
    """σ_w it was estimated with (the revision's)."""


@dataclass(frozen=True)
class StoredNoise:
    """A row of ``estimator_noise``."""

    noise: EstimatorNoise
    method: str
    fit_wagons: str | None
    fit_readings: int | None
    log_likelihood: float | None
    at_floor: bool | None


ESTIMATE_SCHEMA = pl.Schema(
    {
        "wagon_id": pl.String(),
        "time_utc": pl.Datetime("us"),
        "model_revision": pl.String(),
        "contact_mean_c": pl.Float64(),
        "contact_mean_lo_c": pl.Float64(),
        "contact_mean_hi_c": pl.Float64(),
        "contact_max_c": pl.Float64(),
        "contact_max_hi_c": pl.Float64(),
        "smoothed_contact_mean_c": pl.Float64(),
        "smoothed_contact_mean_lo_c": pl.Float64(),
        "smoothed_contact_mean_hi_c": pl.Float64(),
        "unexplained_power_w": pl.Float64(),
        "unexplained_power_lo_w": pl.Float64(),
        "unexplained_power_hi_w": pl.Float64(),
        "innovation_k": pl.Float64(),
        "innovation_sd_k": pl.Float64(),
        "smoothed_contact_max_c": pl.Float64(),
        "smoothed_contact_max_hi_c": pl.Float64(),
        "smoothed_unexplained_power_w": pl.Float64(),
        "smoothed_unexplained_power_lo_w": pl.Float64(),
        "smoothed_unexplained_power_hi_w": pl.Float64(),
    }
)
"""The columns of ``contact_estimates`` (those of ``v_contact_estimates`` first)."""


# --------------------------------------------------------------------------------------------
# One wagon


_MIN_FIT_READINGS = 100
"""A wagon's fit data need at least this many valid readings to take part in the noise fit."""

_ROMS: dict[tuple[object, ...], ReducedModel] = {}
_ROMS_KEPT = 16


def _rom(wagon: WagonConfig, refinement: float) -> ReducedModel:
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


def _model_key(wagon: WagonConfig, rev: Revision, config: EstimationConfig, power: float) -> str:
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
            "kernel": config.kernel,
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class EstimateTask:
    """One wagon's partition of the estimation stage: everything :func:`estimate_wagon`
    reads (picklable: an engine ships it to a worker)."""

    wagon: WagonConfig
    samples: pa.Table
    """The wagon's samples (``q_simulation_wagon_samples.sql``)."""
    rev: Revision
    config: EstimationConfig
    power_noise_w_per_sqrt_s: float
    """The revision's σ_w (σ_v is the wagon's, :func:`wagon_noise`)."""
    data_key: str
    model_key: str

    def __str__(self) -> str:  # how an engine names the partition in an error
        return f"wagon {self.wagon.wagon_id}"


@dataclass(frozen=True)
class EstimateResult:
    """What :func:`estimate_wagon` hands back for the parent to write."""

    wagon_id: str
    revision: str
    data_key: str
    model_key: str
    rows: pa.Table
    """The rows of ``contact_estimates`` (:data:`ESTIMATE_SCHEMA`)."""
    frozen_fraction: float
    """Share of the seconds the filter ran at its steady state (the fast path)."""
    noise: EstimatorNoise | None = None
    """The noise it was estimated with (None: no seconds)."""

    @property
    def seconds(self) -> int:
        return int(self.rows.num_rows)


def estimate_task(
    wh: Warehouse,
    wagon: WagonConfig,
    rev: Revision,
    config: EstimationConfig,
    power_noise_w_per_sqrt_s: float,
    *,
    data_key: str,
    model_key: str,
) -> EstimateTask:
    """The wagon's partition, read from the warehouse by the parent."""
    samples = wh.con.sql(
        sql("q_simulation_wagon_samples"), params={"wagon_id": wagon.wagon_id}
    ).to_arrow_table()
    return EstimateTask(wagon, samples, rev, config, power_noise_w_per_sqrt_s, data_key, model_key)


def _frame(table: pa.Table) -> pl.DataFrame:
    frame = pl.from_arrow(table)
    assert isinstance(frame, pl.DataFrame)
    return frame


_ROWS_SCHEMA = pa.schema(
    [
        (
            name,
            pa.float64()
            if kind == pl.Float64()
            else pa.timestamp("us")
            if kind == pl.Datetime("us")
            else pa.large_string(),
        )
        for name, kind in ESTIMATE_SCHEMA.items()
    ]
)
"""The Arrow schema of :attr:`EstimateResult.rows`: :data:`ESTIMATE_SCHEMA`'s columns, the
strings large (as polars hands them over, and as they were until session 13)."""


def _rows(
    wagon_id: str, revision: str, t0: dt.datetime | None, est: ContactEstimate | None
) -> pa.Table:
    """The wagon's rows of ``contact_estimates`` as Arrow, built from the estimate's arrays
    (a NaN is stored as null; a column not smoothed is null throughout)."""
    if est is None or t0 is None or est.time_s.size == 0:
        return _ROWS_SCHEMA.empty_table()
    n = est.time_s.size
    times = np.datetime64(t0, "us") + (np.rint(est.time_s).astype(np.int64) * 1_000_000).astype(
        "timedelta64[us]"
    )
    columns: dict[str, np.ndarray | None] = {
        "contact_mean_c": est.contact_mean_c,
        "contact_mean_lo_c": est.contact_mean_lo_c,
        "contact_mean_hi_c": est.contact_mean_hi_c,
        "contact_max_c": est.contact_max_c,
        "contact_max_hi_c": est.contact_max_hi_c,
        "smoothed_contact_mean_c": est.smoothed_contact_mean_c,
        "smoothed_contact_mean_lo_c": est.smoothed_contact_mean_lo_c,
        "smoothed_contact_mean_hi_c": est.smoothed_contact_mean_hi_c,
        "unexplained_power_w": est.unexplained_power_w,
        "unexplained_power_lo_w": est.unexplained_power_lo_w,
        "unexplained_power_hi_w": est.unexplained_power_hi_w,
        "innovation_k": est.innovation_k,
        "innovation_sd_k": np.sqrt(est.innovation_var_k2),
        "smoothed_contact_max_c": est.smoothed_contact_max_c,
        "smoothed_contact_max_hi_c": est.smoothed_contact_max_hi_c,
        "smoothed_unexplained_power_w": est.smoothed_unexplained_power_w,
        "smoothed_unexplained_power_lo_w": est.smoothed_unexplained_power_lo_w,
        "smoothed_unexplained_power_hi_w": est.smoothed_unexplained_power_hi_w,
    }

    def floats(values: np.ndarray | None) -> pa.Array:
        if values is None:
            return pa.nulls(n, pa.float64())
        return pa.array(values, pa.float64(), from_pandas=True)  # NaN: null

    arrays = {
        "wagon_id": pa.repeat(pa.scalar(wagon_id, pa.large_string()), n),
        "time_utc": pa.array(times, pa.timestamp("us")),
        "model_revision": pa.repeat(pa.scalar(revision, pa.large_string()), n),
        **{name: floats(values) for name, values in columns.items()},
    }
    return pa.table([arrays[name] for name in _ROWS_SCHEMA.names], schema=_ROWS_SCHEMA)


def _estimate(
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
    filter: ``docs/benchmarks.md``)."""
    if series.time_s.size == 0:
        return None
    return estimate_contact(
        _rom(wagon, rev.refinement),
        wagon,
        series,
        effects=rev.effects,
        config=dataclasses.replace(config.estimator, noise=noise),
        smooth=smooth,
        engine=config.kernel,  # type: ignore[arg-type]  # checked in EstimationConfig
    )


def estimate_wagon(task: EstimateTask) -> EstimateResult:
    """One wagon estimated from its partition, no database: a pure function of the task (the
    reduced model made, or read from its cache, once per process)."""
    wagon = task.wagon
    series, t0 = estimator_series(
        wagon, _frame(task.samples), task.config.chain, config=task.config
    )
    noise = wagon_noise(series, task.config, task.power_noise_w_per_sqrt_s)
    est = _estimate(wagon, series, task.rev, task.config, noise)
    return EstimateResult(
        wagon_id=wagon.wagon_id,
        revision=task.rev.name,
        data_key=task.data_key,
        model_key=task.model_key,
        rows=_rows(wagon.wagon_id, task.rev.name, t0, est),
        frozen_fraction=0.0 if est is None else est.frozen_fraction,
        noise=None if est is None else noise,
    )


@dataclass(frozen=True)
class EstimateChunk:
    """Several wagons' partitions of the estimation stage read together: the chunk's samples
    as one Arrow table with ``wagon_ix`` and ``file_id`` (``q_simulation_chunk_samples.sql``,
    in stored order), and each wagon's entry and keys. :func:`chunk_tasks` cuts it into the
    wagons' :class:`EstimateTask` (the tables :func:`estimate_task` reads: a test compares
    them), which :func:`estimate_chunk` estimates one by one. Picklable."""

    wagons: tuple[tuple[WagonConfig, str, str], ...]
    """(entry, data key, model key) of each wagon, in order."""
    samples: pa.Table
    rev: Revision
    config: EstimationConfig
    power_noise_w_per_sqrt_s: float

    def __str__(self) -> str:  # how an engine names the partition in an error
        return chunk_name([w.wagon_id for w, _, _ in self.wagons])


def estimation_chunk(
    wh: Warehouse,
    wagons: Iterable[tuple[WagonConfig, str, str]],
    rev: Revision,
    config: EstimationConfig,
    power_noise_w_per_sqrt_s: float,
) -> EstimateChunk:
    """The chunk's partitions, read from the warehouse with one query (by the parent: the
    workers never open it)."""
    todo = tuple(wagons)
    samples = chunk_table(wh, "q_simulation_chunk_samples", [w.wagon_id for w, _, _ in todo])
    return EstimateChunk(todo, samples, rev, config, power_noise_w_per_sqrt_s)


def chunk_tasks(chunk: EstimateChunk) -> list[EstimateTask]:
    """The chunk cut into its wagons' tasks, each wagon's samples sorted as the per-wagon
    query sorts them (:func:`fleetbrake.simulation.store.wagon_parts`)."""
    ids = [wagon.wagon_id for wagon, _, _ in chunk.wagons]
    samples = sample_parts(chunk.samples, ids)
    return [
        EstimateTask(
            wagon,
            samples[wagon.wagon_id],
            chunk.rev,
            chunk.config,
            chunk.power_noise_w_per_sqrt_s,
            data_key,
            model_key,
        )
        for wagon, data_key, model_key in chunk.wagons
    ]


def estimate_chunk(chunk: EstimateChunk) -> list[EstimateResult]:
    """Each wagon of the chunk estimated (:func:`estimate_wagon`), in order: a pure function
    of the chunk, so an engine can run it in a worker process."""
    return [estimate_wagon(task) for task in chunk_tasks(chunk)]


# --------------------------------------------------------------------------------------------
# The noise: σ_v the wagon's, σ_w the revision's


def wagon_noise(
    series: EstimatorSeries, config: EstimationConfig, power_noise_w_per_sqrt_s: float
) -> EstimatorNoise:
    """The noise a wagon is estimated with: ``config.noise`` when given; else σ_v from the
    wagon's own readings (:func:`~fleetbrake.model.estimator.measurement_noise`, at least
    ``min_measurement_noise_k``; the estimator's default with fewer than 10 second
    differences) and the revision's σ_w, the rest (σ_q, the manoeuvre test's) ``config.
    estimator.noise``'s. A function of the wagon's data alone."""
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


def stored_noise(wh: Warehouse, revision: str) -> StoredNoise | None:
    """The σ_w fitted for ``revision`` (None: none was, the default applies)."""
    rows = wh.con.execute(sql("q_estimates_noise"), {"revision": revision}).fetchall()
    if not rows:
        return None
    v, w, method, wagons, readings, loglik, at_floor, _ = rows[0]
    return StoredNoise(
        EstimatorNoise(float(v), float(w)), method, wagons, readings, loglik, at_floor
    )


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
    samples = _frame(task.samples).filter(pl.col("time_utc").dt.date().is_in(list(task.days)))
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
        first = _estimate(wagon, series, rev, config, start, smooth=False)
        contact = None if first is None else first.contact_mean_c
    problem = prepare(
        _rom(wagon, rev.refinement),
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
        engine=config.kernel,  # type: ignore[arg-type]  # checked in EstimationConfig
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
    wh.con.execute(
        sql("q_estimates_insert_noise"),
        {
            "revision": rev.name,
            "measurement_k": noise.measurement_k,
            "power_w_per_sqrt_s": noise.power_w_per_sqrt_s,
            "method": stored.method,
            "fit_wagons": stored.fit_wagons,
            "fit_readings": stored.fit_readings,
            "log_likelihood": stored.log_likelihood,
            "at_floor": stored.at_floor,
            "created_utc": utc_now(),
        },
    )
    return stored


# --------------------------------------------------------------------------------------------
# The stage


def estimation_data_keys(wh: Warehouse) -> dict[str, str]:
    """Each wagon with samples: a key of its files and samples as they are now."""
    rows = wh.con.execute(sql("q_estimates_wagon_data")).fetchall()
    return {str(wagon_id): str(key) for wagon_id, key in rows}


def estimated_wagons(wh: Warehouse, revision: str) -> dict[str, EstimatedWagon]:
    """The wagons estimated with ``revision``, and from what."""
    rows = wh.con.execute(sql("q_estimates_estimated_wagons"), {"revision": revision}).fetchall()
    return {
        str(r[0]): EstimatedWagon(str(r[0]), r[1], r[2], int(r[3]), r[4], r[5], r[6]) for r in rows
    }


def estimated_wagon_ids(wh: Warehouse, revision: str) -> set[str]:
    """The wagons holding rows of ``revision`` in ``contact_estimates`` or
    ``estimated_wagons``: the ones :func:`replace_estimates` must delete before it inserts."""
    rows = wh.con.execute(sql("q_estimates_stored_wagon_ids"), {"revision": revision}).fetchall()
    return {str(r[0]) for r in rows}


def replace_estimates(
    wh: Warehouse, revision: str, results: Sequence[EstimateResult], *, delete: bool = True
) -> None:
    """Replace the rows of ``revision`` of every wagon of ``results``, all in one transaction
    (each wagon whole-old or whole-new whatever happens), one bulk insert per table (Arrow
    in), recording the keys of each.

    ``delete=False``: none of the wagons holds rows of ``revision``
    (:func:`estimated_wagon_ids`), so the deletes, each a scan of its whole table (which grows
    with the fleet), are skipped."""
    if not results:
        return
    if len({r.wagon_id for r in results}) != len(results):
        raise ValueError("replace_estimates: a wagon given twice")
    key = {"wagon_ids": [r.wagon_id for r in results], "revision": revision}
    tables = [r.rows for r in results if r.rows.num_rows]
    stamps = pa.table(
        {
            "wagon_id": pa.array([r.wagon_id for r in results], pa.string()),
            "model_revision": pa.array([revision] * len(results), pa.string()),
            "data_key": pa.array([r.data_key for r in results], pa.string()),
            "model_key": pa.array([r.model_key for r in results], pa.string()),
            "seconds": pa.array([r.seconds for r in results], pa.int64()),
            "measurement_k": pa.array(
                [None if r.noise is None else r.noise.measurement_k for r in results],
                pa.float64(),
            ),
            "power_w_per_sqrt_s": pa.array(
                [None if r.noise is None else r.noise.power_w_per_sqrt_s for r in results],
                pa.float64(),
            ),
            "created_utc": pa.array([utc_now()] * len(results), pa.timestamp("us")),
        }
    )
    with wh.transaction() as con:
        if delete:
            con.execute(sql("q_estimates_delete_wagons"), key)
            con.execute(sql("q_estimates_delete_estimated_wagons"), key)
        batches = [("estimated_batch", stamps, "q_estimates_insert_estimated_wagons")]
        if tables:
            rows = tables[0] if len(tables) == 1 else pa.concat_tables(tables)
            batches.insert(0, ("estimate_batch", rows, "q_estimates_insert"))
        for name, table, statement in batches:
            con.register(name, table)
            try:
                con.execute(sql(statement))
            finally:
                con.unregister(name)


def _forget(wh: Warehouse, wagon_id: str) -> None:
    with wh.transaction() as con:
        con.execute(sql("q_estimates_forget_wagon"), {"wagon_id": wagon_id})
        con.execute(sql("q_estimates_forget_estimated_wagon"), {"wagon_id": wagon_id})


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
            _forget(wh, wagon_id)
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
        model_key = _model_key(wagons_by_id[wagon_id], rev, config, power)
        stored = done.get(wagon_id)
        if (
            wagon_id in forced
            or stored is None
            or (stored.data_key, stored.model_key) != (keys[wagon_id], model_key)
        ):
            todo.append((wagons_by_id[wagon_id], keys[wagon_id], model_key))
    if not todo:
        return report
    holding = estimated_wagon_ids(wh, rev.name)  # the others' rows are only inserted
    by_id = {wagon.wagon_id: (wagon, data_key, model_key) for wagon, data_key, model_key in todo}

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


def wagon_estimates(wh: Warehouse, wagon_id: str, revision: str) -> pl.DataFrame:
    """One wagon's stored estimates of ``revision`` by time, every column of
    ``contact_estimates`` (:data:`ESTIMATE_SCHEMA`; empty if none)."""
    frame = wh.con.sql(
        sql("q_estimates_wagon"), params={"wagon_id": wagon_id, "revision": revision}
    ).pl()
    if frame.height == 0:
        return pl.DataFrame(schema=ESTIMATE_SCHEMA)
    return frame.select(list(ESTIMATE_SCHEMA)).cast(dict(ESTIMATE_SCHEMA))
