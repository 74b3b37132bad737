"""The estimator's noise: σ_v and σ_w by maximum likelihood on the innovations
(:func:`fit_noise`), and the thermistor's white noise from its own readings
(:func:`measurement_noise`, :func:`noise_from_second_differences`)."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fleetbrake.model.estimator.config import EstimatorConfig, EstimatorNoise
from fleetbrake.model.estimator.kernel import Kernel, run_kernel
from fleetbrake.model.estimator.problem import EstimatorInputError, EstimatorProblem, FloatArray

__all__ = ["NoiseFit", "fit_noise", "measurement_noise", "noise_from_second_differences"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class NoiseFit:
    """The maximum-likelihood noise parameters and how they were found."""

    noise: EstimatorNoise
    log_likelihood: float
    evaluations: int
    readings: int
    power_noise_at_floor: bool
    """σ_w ended at its floor: the data held nothing the floor could not follow."""


def fit_noise(
    problems: Sequence[EstimatorProblem],
    *,
    config: EstimatorConfig = EstimatorConfig(),  # noqa: B008 (immutable)
    min_power_noise_w_per_sqrt_s: float = 3.0,
    max_power_noise_w_per_sqrt_s: float = 1.0e4,
    measurement_range_k: tuple[float, float] = (1e-3, 10.0),
    kernel: Kernel | None = None,
    tolerance: float = 0.005,
    measurement_k: float | None = None,
) -> NoiseFit:
    """σ_v and σ_w maximising the likelihood of the innovations of ``problems`` (the fit
    data: filter only, all wagons together), by Nelder-Mead on ``(log σ_v, log σ_w)`` within
    the bounds, to ``tolerance`` in the logarithms (0.5 %). Starts from ``config.noise``.

    ``measurement_k`` given: σ_v is that (e.g. the wagon's own, :func:`measurement_noise`) and
    only σ_w is fitted, by a bounded scalar search on ``log σ_w`` (about 15 filter passes; 2
    when the floor is the likeliest, :func:`_fit_power_noise`)."""
    from scipy.optimize import minimize

    readings = int(sum(np.isfinite(p.reading_c).sum() for p in problems))
    if readings < 10:
        raise EstimatorInputError(
            f"fit_noise: {readings} valid readings in the fit data; need at least 10"
        )
    lo = np.log([measurement_range_k[0], min_power_noise_w_per_sqrt_s])
    hi = np.log([measurement_range_k[1], max_power_noise_w_per_sqrt_s])
    if measurement_k is not None:
        return _fit_power_noise(
            problems,
            config,
            float(measurement_k),
            float(lo[1]),
            float(hi[1]),
            kernel,
            tolerance,
            readings,
        )
    start = np.clip(np.log([config.noise.measurement_k, config.noise.power_w_per_sqrt_s]), lo, hi)
    evaluations = 0

    def negative_loglik(z: FloatArray) -> float:
        nonlocal evaluations
        evaluations += 1
        zc = np.clip(z, lo, hi)
        noise = EstimatorNoise(float(np.exp(zc[0])), float(np.exp(zc[1])), None)
        raws = (kernel or run_kernel)(problems, noise, smooth=False, config=config, outputs=False)
        return -float(sum(raw.log_likelihood for raw in raws))

    result = minimize(
        negative_loglik,
        start,
        method="Nelder-Mead",
        bounds=list(zip(lo, hi, strict=True)),
        options={"xatol": tolerance, "fatol": 1e-3, "initial_simplex": _simplex(start, lo, hi)},
    )
    z = np.clip(result.x, lo, hi)
    quiet = config.noise.quiet_power_w_per_sqrt_s
    noise = EstimatorNoise(float(np.exp(z[0])), float(np.exp(z[1])), quiet)
    at_floor = bool(z[1] <= lo[1] + 2 * tolerance)
    logger.info(
        "noise by maximum likelihood over %d readings: sigma_v %.4g K, sigma_w %.4g W/sqrt(s)%s "
        "(%d evaluations)",
        readings,
        noise.measurement_k,
        noise.power_w_per_sqrt_s,
        " (at its floor)" if at_floor else "",
        evaluations,
    )
    return NoiseFit(
        noise=noise,
        log_likelihood=-float(result.fun),
        evaluations=evaluations,
        readings=readings,
        power_noise_at_floor=at_floor,
    )


def _fit_power_noise(
    problems: Sequence[EstimatorProblem],
    config: EstimatorConfig,
    measurement_k: float,
    lo: float,
    hi: float,
    kernel: Kernel | None,
    tolerance: float,
    readings: int,
) -> NoiseFit:
    """σ_w alone by maximum likelihood, σ_v fixed (:func:`fit_noise`).

    The likelihood is taken as unimodal in ``log σ_w`` (the bounded search assumes it too):
    the floor ``lo`` and one ``tolerance`` above it are evaluated first, and when the floor
    is at least as likely the maximum lies within that step of it, so the floor is the
    answer to the search's own tolerance (two filter passes instead of the search's ~17;
    the revisions the close loop makes end there). Otherwise the bounded search over
    ``lo`` .. ``hi``, and the floor when it is as likely as the search's best (the search
    never evaluates the bound itself)."""
    from scipy.optimize import minimize_scalar

    if not (math.isfinite(measurement_k) and measurement_k > 0):
        raise ValueError(f"fit_noise: measurement_k must be positive, got {measurement_k!r}")
    evaluations = 0

    def negative_loglik(z: float) -> float:
        nonlocal evaluations
        evaluations += 1
        noise = EstimatorNoise(measurement_k, float(np.exp(np.clip(z, lo, hi))), None)
        raws = (kernel or run_kernel)(problems, noise, smooth=False, config=config, outputs=False)
        return -float(sum(raw.log_likelihood for raw in raws))

    floor = negative_loglik(lo)
    if floor <= negative_loglik(min(lo + tolerance, hi)):
        z, best = lo, floor
    else:
        result = minimize_scalar(
            negative_loglik, bounds=(lo, hi), method="bounded", options={"xatol": tolerance}
        )
        z = float(np.clip(result.x, lo, hi))
        if floor <= float(result.fun):
            z, best = lo, floor
        else:
            best = float(result.fun)
    noise = EstimatorNoise(measurement_k, float(np.exp(z)), config.noise.quiet_power_w_per_sqrt_s)
    at_floor = bool(z <= lo + 2 * tolerance)
    logger.info(
        "sigma_w by maximum likelihood over %d readings (sigma_v %.4g K given): %.4g W/sqrt(s)%s "
        "(%d evaluations)",
        readings,
        measurement_k,
        noise.power_w_per_sqrt_s,
        " (at its floor)" if at_floor else "",
        evaluations,
    )
    return NoiseFit(
        noise=noise,
        log_likelihood=-best,
        evaluations=evaluations,
        readings=readings,
        power_noise_at_floor=at_floor,
    )


def measurement_noise(
    time_s: FloatArray, reading_c: FloatArray, *, min_differences: int = 10
) -> float | None:
    """The thermistor's white noise σ_v (K) from its own readings: the median absolute
    deviation (x 1.4826) of the second differences ``y[t+1] - 2 y[t] + y[t-1]`` over three
    consecutive seconds with valid readings, divided by √6 (white noise's second difference
    has variance 6 σ²; the block's temperature, smooth at 1 Hz, adds only its curvature, and
    the median ignores the few seconds where that is sharp). The idea of
    ``fleetbrake.closeloop.stats.noise_from_residual``, on the reading instead of a residual. None
    with fewer than ``min_differences`` such triples."""
    t = np.asarray(time_s, dtype=np.float64)
    y = np.asarray(reading_c, dtype=np.float64)
    if y.size < 3:
        return None
    ok = np.isfinite(y)
    same = (
        ok[2:]
        & ok[1:-1]
        & ok[:-2]
        & np.isclose(t[2:] - t[1:-1], 1.0)
        & np.isclose(t[1:-1] - t[:-2], 1.0)
    )
    d2 = (y[2:] - 2.0 * y[1:-1] + y[:-2])[same]
    if d2.size < min_differences:
        return None
    return noise_from_second_differences(d2)


def noise_from_second_differences(d2: FloatArray) -> float:
    """White noise's σ from its second differences ``x[t+1] - 2 x[t] + x[t-1]`` (variance
    6 σ²), scaled robustly: the median absolute deviation x 1.4826, divided by √6. Shared by
    the estimator's σ_v (:func:`measurement_noise`, on readings) and the close loop's
    ``noise_from_residual`` (on residuals)."""
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return 1.4826 * mad / math.sqrt(6.0)


def _simplex(start: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """A first simplex a factor of 2 wide in each noise (inside the bounds)."""
    step = math.log(2.0)
    vertices = [start.copy()]
    for i in range(start.size):
        v = start.copy()
        v[i] = v[i] + step if v[i] + step <= hi[i] else v[i] - step
        vertices.append(np.clip(v, lo, hi))
    return np.array(vertices)
