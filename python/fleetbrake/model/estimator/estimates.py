"""The virtual sensor's estimates per logged second of a wagon (:class:`ContactEstimate`): the
kernel's outputs on the logged seconds, with their 95 % bounds; :func:`estimate` for prepared
problems, :func:`estimate_contact` for one wagon's series (iterating a state-dependent
effect)."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import EffectSet
from fleetbrake.model.estimator.config import EstimatorConfig, EstimatorNoise
from fleetbrake.model.estimator.kernel import Kernel, KernelOutputs, run_kernel
from fleetbrake.model.estimator.prepare import prepare
from fleetbrake.model.estimator.problem import Z95, EstimatorProblem, FloatArray, WagonSeries
from fleetbrake.model.rom import ReducedModel

__all__ = ["ContactEstimate", "estimate", "estimate_contact"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ContactEstimate:
    """The virtual sensor's estimate at each logged second of one wagon (N rows): filtered
    (what was known at that second) and smoothed (knowing the whole series; None when not
    smoothed). Temperatures in °C, standard deviations in K, power in W into the block's
    friction face; ``*_lo_*``/``*_hi_*`` are the 95 % bounds."""

    wagon_id: str
    time_s: FloatArray
    contact_mean_c: FloatArray
    contact_mean_sd_k: FloatArray
    contact_max_c: FloatArray
    contact_max_sd_k: FloatArray
    unexplained_power_w: FloatArray
    unexplained_power_sd_w: FloatArray
    innovation_k: FloatArray
    """Reading minus predicted reading before the update; NaN without a valid reading."""
    innovation_var_k2: FloatArray
    predicted_reading_c: FloatArray
    log_likelihood: float
    noise: EstimatorNoise
    frozen_fraction: float
    """Share of the seconds at which the covariance was steady (the fast path)."""
    final_state: FloatArray
    final_cov: FloatArray
    replayed_fraction: float = 0.0
    """Share of the seconds whose covariance step replayed a recorded excursion from a steady
    state (the second fast path)."""
    smoothed_contact_mean_c: FloatArray | None = None
    smoothed_contact_mean_sd_k: FloatArray | None = None
    smoothed_contact_max_c: FloatArray | None = None
    smoothed_contact_max_sd_k: FloatArray | None = None
    smoothed_unexplained_power_w: FloatArray | None = None
    smoothed_unexplained_power_sd_w: FloatArray | None = None
    manoeuvre: NDArray[np.bool_] | None = None
    """Whether the power's noise was in the manoeuvre mode (σ_w) into each second (else the
    quiet σ_q)."""

    @property
    def contact_mean_lo_c(self) -> FloatArray:
        return self.contact_mean_c - Z95 * self.contact_mean_sd_k

    @property
    def contact_mean_hi_c(self) -> FloatArray:
        return self.contact_mean_c + Z95 * self.contact_mean_sd_k

    @property
    def contact_max_hi_c(self) -> FloatArray:
        return self.contact_max_c + Z95 * self.contact_max_sd_k

    @property
    def unexplained_power_lo_w(self) -> FloatArray:
        return self.unexplained_power_w - Z95 * self.unexplained_power_sd_w

    @property
    def unexplained_power_hi_w(self) -> FloatArray:
        return self.unexplained_power_w + Z95 * self.unexplained_power_sd_w

    @property
    def innovation_normalised(self) -> FloatArray:
        """ν / √S: standard normal while the model and the sensor behave."""
        return self.innovation_k / np.sqrt(self.innovation_var_k2)

    @property
    def smoothed_contact_mean_lo_c(self) -> FloatArray | None:
        return _bound(self.smoothed_contact_mean_c, self.smoothed_contact_mean_sd_k, -Z95)

    @property
    def smoothed_contact_mean_hi_c(self) -> FloatArray | None:
        return _bound(self.smoothed_contact_mean_c, self.smoothed_contact_mean_sd_k, Z95)

    @property
    def smoothed_contact_max_hi_c(self) -> FloatArray | None:
        return _bound(self.smoothed_contact_max_c, self.smoothed_contact_max_sd_k, Z95)

    @property
    def smoothed_unexplained_power_lo_w(self) -> FloatArray | None:
        return _bound(self.smoothed_unexplained_power_w, self.smoothed_unexplained_power_sd_w, -Z95)

    @property
    def smoothed_unexplained_power_hi_w(self) -> FloatArray | None:
        return _bound(self.smoothed_unexplained_power_w, self.smoothed_unexplained_power_sd_w, Z95)


def _bound(mean: FloatArray | None, sd: FloatArray | None, z: float) -> FloatArray | None:
    return None if mean is None or sd is None else mean + z * sd


def _estimate_of(
    problem: EstimatorProblem, raw: KernelOutputs, noise: EstimatorNoise
) -> ContactEstimate:
    rows = problem.logged

    def pick(values: FloatArray | None) -> FloatArray | None:
        return None if values is None else np.ascontiguousarray(values[rows])

    steps = max(problem.n_samples, 1)
    # no friction heat where the wheel stood over the step into the second: P is held there
    still = np.zeros(problem.n_samples, dtype=bool)
    if problem.held is not None:
        still[1:] = problem.held

    def heat(values: FloatArray | None) -> FloatArray | None:
        return None if values is None else np.where(still, 0.0, values)

    return ContactEstimate(
        wagon_id=problem.wagon_id,
        time_s=problem.time_s[rows],
        contact_mean_c=raw.mean_c[rows],
        contact_mean_sd_k=raw.mean_sd_k[rows],
        contact_max_c=raw.max_c[rows],
        contact_max_sd_k=raw.max_sd_k[rows],
        unexplained_power_w=np.where(still, 0.0, raw.power_w)[rows],
        unexplained_power_sd_w=np.where(still, 0.0, raw.power_sd_w)[rows],
        innovation_k=raw.innovation_k[rows],
        innovation_var_k2=raw.innovation_var_k2[rows],
        predicted_reading_c=raw.predicted_reading_c[rows],
        log_likelihood=raw.log_likelihood,
        noise=noise,
        frozen_fraction=raw.frozen_steps / steps,
        final_state=raw.final_state,
        final_cov=raw.final_cov,
        replayed_fraction=raw.memo_steps / steps,
        smoothed_contact_mean_c=pick(raw.smoothed_mean_c),
        smoothed_contact_mean_sd_k=pick(raw.smoothed_mean_sd_k),
        smoothed_contact_max_c=pick(raw.smoothed_max_c),
        smoothed_contact_max_sd_k=pick(raw.smoothed_max_sd_k),
        smoothed_unexplained_power_w=pick(heat(raw.smoothed_power_w)),
        smoothed_unexplained_power_sd_w=pick(heat(raw.smoothed_power_sd_w)),
        manoeuvre=None if raw.manoeuvre is None or raw.manoeuvre.size == 0 else raw.manoeuvre[rows],
    )


def estimate(
    problems: Sequence[EstimatorProblem],
    *,
    config: EstimatorConfig = EstimatorConfig(),  # noqa: B008 (immutable)
    smooth: bool = True,
    kernel: Kernel | None = None,
) -> list[ContactEstimate]:
    """Filter (and smooth) prepared problems with ``config.noise``: the Rust kernel (wagons
    in parallel; ``kernel``: another with its shape, the tests' reference)."""
    raws = (kernel or run_kernel)(problems, config.noise, smooth=smooth, config=config)
    return [_estimate_of(p, raw, config.noise) for p, raw in zip(problems, raws, strict=True)]


def estimate_contact(
    rom: ReducedModel,
    wagon: WagonConfig,
    series: WagonSeries,
    *,
    effects: EffectSet = EffectSet(),  # noqa: B008 (immutable)
    config: EstimatorConfig = EstimatorConfig(),  # noqa: B008 (immutable)
    h_w_m2k: Mapping[str, float | ArrayLike] | None = None,
    smooth: bool = True,
    kernel: Kernel | None = None,
    tol_k: float = 1e-3,
    max_iterations: int = 10,
) -> ContactEstimate:
    """The estimate of one wagon's series under a model revision. A state-dependent effect
    (friction fade) is evaluated on the filtered contact temperature of the previous pass,
    until that changes by less than ``tol_k`` (at most ``max_iterations`` passes): those
    passes filter only (the smoother changes no filtered value), and the last one's problem
    is smoothed once at the end."""
    contact: FloatArray | None = None
    iterate = effects.state_dependent
    for _ in range(max_iterations if iterate else 1):
        problem = prepare(
            rom, wagon, series, effects=effects, config=config, h_w_m2k=h_w_m2k, contact_c=contact
        )
        result = estimate([problem], config=config, smooth=smooth and not iterate, kernel=kernel)[0]
        if not iterate:
            return result
        if contact is not None and float(np.max(np.abs(result.contact_mean_c - contact))) < tol_k:
            break
        contact = result.contact_mean_c
    else:
        logger.warning(
            "wagon %s: the state-dependent effects' estimate still moved by more than %g K "
            "after %d passes",
            series.wagon_id,
            tol_k,
            max_iterations,
        )
    return estimate([problem], config=config, smooth=True, kernel=kernel)[0] if smooth else result
