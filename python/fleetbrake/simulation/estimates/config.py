"""The estimation stage's settings (:class:`EstimationConfig`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from fleetbrake.model.estimator import EstimatorConfig, EstimatorNoise
from fleetbrake.simulation.chains import ChainParams

__all__ = ["DEFAULT_POWER_NOISE_W_PER_SQRT_S", "EstimationConfig"]


DEFAULT_POWER_NOISE_W_PER_SQRT_S = 3.0
"""σ_w of a revision the close loop did not fit (``docs/estimator.md``: the evidence)."""


@dataclass(frozen=True)
class EstimationConfig:
    """How the estimation stage estimates (everything it is set with; the estimator's own
    numbers in ``estimator``, whose ``noise`` is replaced by the wagon's and the revision's).

    Read by: ``fleetbrake run``, ``fleetbrake watch``, ``fleetbrake close-loop``."""

    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    """The virtual sensor's own settings
    (:class:`~fleetbrake.model.estimator.config.EstimatorConfig`)."""
    chain: ChainParams = field(default_factory=ChainParams)
    """The simulation's numbers the declared inputs are built with (the speed's running
    median, the spans): pass the simulation's, so the estimate is driven as the prediction."""
    noise: EstimatorNoise | None = None
    """None: σ_v per wagon from its readings, σ_w the revision's (stored by
    :func:`~fleetbrake.simulation.estimates.noise.fit_revision_noise`, else
    ``power_noise_w_per_sqrt_s``); else these for every wagon (method ``given``)."""
    power_noise_w_per_sqrt_s: float = DEFAULT_POWER_NOISE_W_PER_SQRT_S
    """σ_w of a revision without a fitted one (the declared revision): the documented default
    (``docs/estimator.md``: the maximum-likelihood fits on generated fleets behind it)."""
    min_measurement_noise_k: float = 0.02
    """σ_v's floor (a sensor whose log is rounded, or nearly noise-free, still has this)."""
    frozen_min_s: int = 120
    """s: readings unchanged (to within ``frozen_resolution_k``) this long are a frozen
    sensor's and skip the update
    (:func:`~fleetbrake.simulation.estimates.wagon.frozen_readings`; the flags'
    ``frozen_min_s``)."""
    frozen_resolution_k: float = 0.01
    """K: the resolution a frozen reading repeats to (the flags' ``frozen_resolution_k``)."""
    frozen_noise_k: float = 0.03
    """K: ... when the sensor's noise outside such runs is at least this (a noisy sensor
    cannot repeat itself that long; a near noise-free one can: its runs are kept; the flags'
    ``frozen_noise_k``)."""
    noise_fit_wagons: int = 5
    """How many wagons σ_w is fitted on
    (:func:`~fleetbrake.simulation.estimates.noise.fit_revision_noise`; spread over the sorted
    ids of the wagons with fit days), each on its own; the revision's is the median."""
    noise_fit_s: float = 21_600.0
    """s: the noise fit (:func:`~fleetbrake.simulation.estimates.noise.fit_revision_noise`)
    takes the first this many seconds of each fit wagon's fit days."""
    min_power_noise_w_per_sqrt_s: float = 3.0
    """σ_w's floor in the fit (``docs/estimator.md``: why)."""
    batch_rows: int = 1_000_000
    """Several wagons per transaction, up to about this many rows (a wagon never split; the
    simulation's transactions: DuckDB's insert costs about half the processor time per row
    at 1 M rows that it does at 0.2 M,
    ``docs/decisions/0007-reading-and-writing-in-chunks.md``). Changes no row."""
    chunk_rows: int = 200_000
    """The parent reads the wagons' samples a chunk of whole wagons at a time, about this
    many samples (one query, :func:`~fleetbrake.simulation.estimates.store.estimation_chunk`),
    and a worker estimates the chunk's wagons one by one (the simulation's ``chunk_rows``).
    Changes no row."""

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
