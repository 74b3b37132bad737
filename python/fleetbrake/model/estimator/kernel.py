"""The Rust kernel of the filter and smoother: the call (:func:`run_kernel`, wagons in
parallel), its arguments (a problem's arrays as the extension takes them) and its outputs
(:class:`KernelOutputs`). :class:`Kernel` is the shape of the call, which the tests' numpy
reference of the same algorithm has too."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from fleetbrake import _ext
from fleetbrake.model.estimator.config import EstimatorConfig, EstimatorNoise
from fleetbrake.model.estimator.problem import EstimatorInputError, EstimatorProblem, FloatArray

__all__ = ["Kernel", "KernelOutputs", "run_kernel", "rust_available"]


@dataclass(frozen=True)
class KernelOutputs:
    """What a kernel returns, on the problem's time grid (N rows). ``smoothed_*`` are None
    when the smoother did not run. Standard deviations, not bounds."""

    mean_c: FloatArray
    mean_sd_k: FloatArray
    max_c: FloatArray
    max_sd_k: FloatArray
    power_w: FloatArray
    power_sd_w: FloatArray
    innovation_k: FloatArray
    innovation_var_k2: FloatArray
    predicted_reading_c: FloatArray
    log_likelihood: float
    updates: int
    frozen_steps: int
    """Seconds at which the filter's covariance was steady (only the mean stepped)."""
    final_state: FloatArray
    final_cov: FloatArray
    smoothed_mean_c: FloatArray | None = None
    smoothed_mean_sd_k: FloatArray | None = None
    smoothed_max_c: FloatArray | None = None
    smoothed_max_sd_k: FloatArray | None = None
    smoothed_power_w: FloatArray | None = None
    smoothed_power_sd_w: FloatArray | None = None
    smoother_frozen_steps: int = 0
    """Seconds at which the smoother's information matrix was steady."""
    memo_steps: int = 0
    """Seconds whose covariance step replayed a recorded excursion from a steady state (the
    same numbers as computing it)."""
    manoeuvre: NDArray[np.bool_] | None = None
    """Whether the step into each second used the manoeuvre mode's σ_w."""
    manoeuvre_steps: int = 0


class Kernel(Protocol):
    """Filter (and smooth) problems with ``noise``: one :class:`KernelOutputs` per problem.
    ``outputs=False``: the likelihood and the final state only (the noise fit's passes)."""

    def __call__(
        self,
        problems: Sequence[EstimatorProblem],
        noise: EstimatorNoise,
        *,
        smooth: bool,
        config: EstimatorConfig,
        outputs: bool = True,
    ) -> list[KernelOutputs]: ...


def rust_available() -> bool:
    """Whether the extension has the estimator kernel."""
    return hasattr(_ext, "estimator_run")


def run_kernel(
    problems: Sequence[EstimatorProblem],
    noise: EstimatorNoise,
    *,
    smooth: bool,
    config: EstimatorConfig,
    outputs: bool = True,
) -> list[KernelOutputs]:
    """The Rust kernel on ``problems`` (wagons in parallel on Rayon's threads)."""
    if not rust_available():
        raise EstimatorInputError("this build of fleetbrake._ext has no estimator kernel")
    raw = _ext.estimator_run(
        [_as_kernel_args(p) for p in problems],
        float(noise.measurement_k),
        float(noise.power_w_per_sqrt_s),
        bool(smooth),
        float(config.steady_tolerance),
        float(config.smoother_tolerance),
        int(config.checkpoint_steps),
        bool(outputs),
        config.manoeuvre.kernel_args(noise, config.dt_s),
        config.manoeuvre_tolerances,
    )
    return [KernelOutputs(**item) for item in raw]


def _as_kernel_args(p: EstimatorProblem) -> dict[str, object]:
    """The problem as the extension takes it: contiguous arrays, flattened."""
    c = np.ascontiguousarray
    return {
        "order": p.order,
        "lag": p.lag,
        "t_ref_c": p.t_ref_c,
        "reading_c": c(p.reading_c),
        "index": c(p.index.astype(np.uint32)),
        "w": c(p.w.reshape(-1)),
        "a": c(p.a.reshape(-1)),
        "diagonal": [bool(v) for v in p.diagonal],
        "gamma": c(p.gamma.reshape(-1)),
        "phi": c(p.phi),
        "q_unit": c(p.q_unit),
        "lag_a": c(p.lag_a),
        "lag_b1": c(p.lag_b1),
        "lag_row": c(p.lag_row.reshape(-1)),
        "lag_power": c(p.lag_power),
        "c_probe": c(p.c_probe),
        "c_mean": c(p.c_mean),
        "c_nodes": c(p.c_nodes.reshape(-1)),
        "x0": c(p.x0),
        "cov0": c(p.cov0.reshape(-1)),
        "p_prior_unit": float(p.p_prior_unit),
        "q_gap": c(p.gap_noise()[0], dtype=np.float64),
        "gap_dir": c(p.gap_noise()[1], dtype=np.float64),
        "q_modes": c(p.mode_noise().reshape(-1), dtype=np.float64),
        "applied": [bool(v) for v in p.applied_transitions()],
        "power_noise": None if p.power_noise is None else c(p.power_noise, dtype=np.float64),
        "brake_phi": None if p.brake_phi is None else c(p.brake_phi, dtype=np.float64),
        "brake_q": None if p.brake_q is None else c(p.brake_q, dtype=np.float64),
        "eigenvectors": None if p.eigenvectors is None else c(p.eigenvectors.reshape(-1)),
        "eigenvalues": None if p.eigenvalues is None else c(p.eigenvalues.reshape(-1)),
    }
