"""Blocks of correlated seconds: how many independent residuals a residual holds, the
criterion on that count, the sensor noise from its second differences, and the events whose
residual is far above the bulk (outliers)."""

from __future__ import annotations

import math

import numpy as np

from fleetbrake.errors import FleetbrakeError
from fleetbrake.model.estimator import noise_from_second_differences

OUTLIER_NOISE_FACTOR = 5.0
"""An event is an outlier only when its residual RMS is above this many times the noise..."""

OUTLIER_Z = 5.0
"""... and this many robust standard deviations (1.4826 MAD) above the events' median RMS."""

MAX_OUTLIER_FRACTION = 0.05
"""At most this share of the events is left out as outliers (the worst ones): more is a
misfit of the model, not bad data."""


class SelectionError(FleetbrakeError, ValueError):
    """The residual cannot support the statistic asked for (too few seconds or blocks, arrays
    of different lengths); the message says which and how many."""


def root_mean_square(r: np.ndarray) -> float:
    """Root mean square of ``r`` (NaN when empty)."""
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")


# ---------------------------------------------------------------------------- blocks
def as_arrays(residual: np.ndarray, blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r = np.asarray(residual, dtype=np.float64).ravel()
    b = np.asarray(blocks).ravel()
    if r.shape != b.shape:
        raise SelectionError(
            f"residual has {r.size} seconds but blocks has {b.size} block ids: one id per second"
        )
    return r, b


def block_slices(blocks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(order, starts, lengths): ``order`` sorts the seconds by block keeping their order
    within a block; block ``i`` is ``order[starts[i]:starts[i] + lengths[i]]``."""
    order = np.argsort(blocks, kind="stable")
    sorted_ids = blocks[order]
    if sorted_ids.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return order, empty, empty
    change = np.flatnonzero(sorted_ids[1:] != sorted_ids[:-1]) + 1
    starts = np.concatenate(([0], change)).astype(np.int64)
    lengths = np.diff(np.concatenate((starts, [sorted_ids.size]))).astype(np.int64)
    return order, starts, lengths


def _autocovariance_sums(values: np.ndarray, blocks: np.ndarray, max_lag: int) -> np.ndarray:
    """``C[k] = sum over blocks, sum_t v[t] v[t+k]`` (both seconds in the block), k = 0..max_lag,
    by FFT: blocks grouped by length (powers of two), each group zero-padded to twice its
    longest and transformed at once, so that no product spans two blocks."""
    order, starts, lengths = block_slices(blocks)
    v = values[order]
    out = np.zeros(max_lag + 1)
    if lengths.size == 0:
        return out
    group = np.ceil(np.log2(np.maximum(lengths, 1))).astype(np.int64)
    for g in np.unique(group):
        members = np.flatnonzero(group == g)
        longest = int(lengths[members].max())
        size = 1 << math.ceil(math.log2(max(2 * longest, 2)))
        # at most ~4 M values per transform
        per_batch = max(1, (1 << 22) // size)
        for first in range(0, members.size, per_batch):
            batch = members[first : first + per_batch]
            padded = np.zeros((batch.size, size))
            for row, i in enumerate(batch):
                padded[row, : lengths[i]] = v[starts[i] : starts[i] + lengths[i]]
            spectrum = np.fft.rfft(padded, axis=1)
            acov = np.fft.irfft(spectrum * np.conj(spectrum), n=size, axis=1).sum(axis=0)
            upto = min(max_lag + 1, longest)
            out[:upto] += acov[:upto]
    return out


def autocorrelation(residual: np.ndarray, blocks: np.ndarray, max_lag: int) -> np.ndarray:
    """The residual's autocorrelation ``rho_0..rho_max_lag`` pooled over blocks (products only
    within a block, about the residual's overall mean, divided by the pooled variance: the
    biased, positive-definite estimator). A constant offset that differs between blocks counts
    as correlation within each block, as it should: it is not noise."""
    r, b = as_arrays(residual, blocks)
    if r.size < 2:
        raise SelectionError(f"autocorrelation needs at least 2 seconds, got {r.size}")
    d = r - r.mean()
    c = _autocovariance_sums(d, b, max_lag)
    if c[0] <= 0.0:
        rho = np.zeros(max_lag + 1)
        rho[0] = 1.0
        return rho
    return c / c[0]


def _geyer_tau(rho: np.ndarray) -> float:
    """Integrated autocorrelation time ``1 + 2 sum_{k>=1} rho_k`` truncated by Geyer's
    initial monotone positive sequence: pair sums ``G_m = rho_2m + rho_2m+1`` are added while
    positive, each capped at the previous one (the true sequence is positive and decreasing for
    a reversible process; the estimated tail is noise)."""
    pairs = rho[: 2 * (rho.size // 2)].reshape(-1, 2).sum(axis=1)
    total = 0.0
    previous = math.inf
    for g in pairs:
        if g <= 0.0:
            break
        g = min(float(g), previous)
        total += g
        previous = g
    return max(2.0 * total - 1.0, 0.0)


def effective_sample_size(residual: np.ndarray, blocks: np.ndarray) -> float:
    """How many independent residuals the seconds are worth: ``n / tau``, ``tau`` the
    integrated autocorrelation time of the residual pooled over blocks (lags up to the longest
    block, within blocks only), truncated by Geyer's initial monotone positive sequence.
    Bounded by ``[n_blocks, n]``: blocks are independent, and a residual is never worth more
    than one sample per second. White noise gives about ``n``; AR(1) with coefficient ``rho``
    about ``n (1 - rho) / (1 + rho)``."""
    r, b = as_arrays(residual, blocks)
    n = r.size
    if n == 0:
        raise SelectionError("effective_sample_size: an empty residual")
    n_blocks = int(np.unique(b).size)
    if n < 4:
        return float(n)
    _, _, lengths = block_slices(b)
    max_lag = int(min(lengths.max() - 1, n - 1))
    if max_lag < 1:
        return float(n)
    tau = _geyer_tau(autocorrelation(r, b, max_lag))
    if tau <= 0.0:
        return float(n)
    return float(min(max(n / tau, n_blocks), n))


def information_criterion(residual: np.ndarray, n_parameters: int, n_eff: float) -> float:
    """The Bayesian information criterion of a Gaussian residual on ``n_eff`` independent
    samples: ``n_eff log(mean r^2) + p log(n_eff)`` (lower is better). Compare candidates on
    one ``n_eff`` (the smallest of theirs: the most correlated residual sets how many
    independent samples the comparison has)."""
    r = np.asarray(residual, dtype=np.float64)
    if r.size == 0:
        raise SelectionError("information_criterion: an empty residual")
    n = max(float(n_eff), n_parameters + 2.0)
    mse = max(float(np.mean(r * r)), 1e-12)
    return n * math.log(mse) + n_parameters * math.log(n)


def noise_from_residual(
    residual: np.ndarray, blocks: np.ndarray, time_s: np.ndarray | None = None
) -> float:
    """White sensor noise (K, one sigma) from the residual's second differences within blocks:
    ``r[t+1] - 2 r[t] + r[t-1]`` of white noise has variance ``6 sigma^2``, a smooth model
    error contributes only its curvature (far less than to first differences, which carry its
    slope), and the scale is the median absolute deviation (x 1.4826), so that the few seconds
    where the model error turns sharply (a braking's onset) do not count. ``time_s`` (optional,
    seconds): differences only over three equally spaced seconds (a gap is not a step)."""
    r, b = as_arrays(residual, blocks)
    order = np.argsort(b, kind="stable")
    rs, bs = r[order], b[order]
    same = (bs[2:] == bs[1:-1]) & (bs[1:-1] == bs[:-2])
    if time_s is not None:
        ts = np.asarray(time_s, dtype=np.float64).ravel()[order]
        h1, h2 = ts[1:-1] - ts[:-2], ts[2:] - ts[1:-1]
        step = np.nanmin(np.where(same, h1, np.inf)) if same.any() else np.inf
        same &= np.isclose(h1, step) & np.isclose(h2, step)
    d2 = (rs[2:] - 2.0 * rs[1:-1] + rs[:-2])[same] if rs.size >= 3 else np.zeros(0)
    d2 = d2[np.isfinite(d2)]
    if d2.size < 10:
        raise SelectionError(
            f"noise_from_residual: {d2.size} second differences within blocks; need 10"
        )
    return noise_from_second_differences(d2)


# ---------------------------------------------------------------------------- outliers
def event_rms(residual: np.ndarray, event: np.ndarray, n_events: int) -> np.ndarray:
    """(n_events) RMS of the finite ``residual`` of each event (``event``: each second's
    index into the events); NaN for an event with no finite second."""
    r = np.asarray(residual, dtype=np.float64).ravel()
    e = np.asarray(event).ravel()
    if r.size != e.size:
        raise SelectionError(f"event_rms: {r.size} residuals but {e.size} event indices")
    ok = np.isfinite(r)
    sums = np.bincount(e[ok], weights=r[ok] * r[ok], minlength=n_events)
    counts = np.bincount(e[ok], minlength=n_events).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.where(counts > 0, sums / np.maximum(counts, 1.0), np.nan))


def outlier_events(
    rms_k: np.ndarray,
    noise_k: float,
    *,
    noise_factor: float = OUTLIER_NOISE_FACTOR,
    z: float = OUTLIER_Z,
    max_fraction: float = MAX_OUTLIER_FRACTION,
) -> tuple[np.ndarray, float]:
    """Which events' residual RMS (``rms_k``, one per event, from :func:`event_rms`) is far
    above the bulk: above ``noise_factor`` x the sensor noise and above the median by ``z``
    robust standard deviations (1.4826 x the median absolute deviation). Data the flags did
    not catch (a reading gone wild, an unlogged braking) then leaves the fit instead of
    biasing it; a model that misfits every event leaves none out (the bulk moves with it).
    At most ``max_fraction`` of the events, the worst. Returns the outliers' indices, worst
    first, and the threshold (K)."""
    rms = np.asarray(rms_k, dtype=np.float64).ravel()
    finite = np.isfinite(rms)
    if finite.sum() < 3:
        return np.zeros(0, dtype=np.int64), math.inf
    median = float(np.median(rms[finite]))
    spread = 1.4826 * float(np.median(np.abs(rms[finite] - median)))
    threshold = max(noise_factor * noise_k if math.isfinite(noise_k) else 0.0, median + z * spread)
    above = np.flatnonzero(finite & (rms > threshold))
    worst = above[np.argsort(-rms[above], kind="stable")]
    return worst[: int(max_fraction * int(finite.sum()))].astype(np.int64), threshold
