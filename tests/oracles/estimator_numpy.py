"""The estimator's reference: the filter and smoother in plain numpy (:func:`run_numpy`),
dense matrices, one step at a time, the same algorithm as the Rust kernel (the same
steady-state freezing, the same test between the power noise's modes, the same second pass
for the smoother on the led modes). The tests compare the kernel to it; :func:`numpy_kernel`
has the shape of :class:`fleetbrake.model.estimator.Kernel`, so that
``estimate(..., kernel=numpy_kernel)`` gives the reference's estimates."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fleetbrake.model.estimator import (
    EstimatorConfig,
    EstimatorNoise,
    EstimatorProblem,
    KernelOutputs,
    ManoeuvreTest,
)

__all__ = ["SMOOTHED_OUTPUTS", "led_modes", "numpy_kernel", "run_numpy"]

FloatArray = NDArray[np.float64]


SMOOTHED_OUTPUTS = (
    "smoothed_mean_c",
    "smoothed_mean_sd_k",
    "smoothed_max_c",
    "smoothed_max_sd_k",
    "smoothed_power_w",
    "smoothed_power_sd_w",
)
"""The smoother's outputs, per second (the kernel's names)."""


def led_modes(manoeuvre: NDArray[np.bool_], lead_steps: int) -> NDArray[np.bool_] | None:
    """The filter's mode sequence with the manoeuvre mode begun ``lead_steps`` before each
    switch-on (never at the prior, index 0); None when that changes nothing (the Rust
    kernel's ``led_modes``)."""
    if lead_steps <= 0:
        return None
    led = manoeuvre.copy()
    ons = np.flatnonzero(manoeuvre[1:] & ~manoeuvre[:-1]) + 1
    for t in ons:
        led[max(int(t) - lead_steps, 1) : t] = True
    return None if np.array_equal(led, manoeuvre) else led


def _converged(new: FloatArray, old: FloatArray, tol: float) -> bool:
    """Every element changed by at most ``tol sqrt(d_i d_j)`` (d the new diagonal)."""
    d = np.sqrt(np.abs(np.diag(new)))
    return bool(np.all(np.abs(new - old) <= tol * np.outer(d, d)))


@dataclass
class _Steady:
    """The filter's covariance quantities while they are steady for one key."""

    key: tuple[int, bool, bool]
    cov: FloatArray
    gain: FloatArray
    s_var: float
    mean_var: float
    node_var: FloatArray
    power_var: float


def run_numpy(
    problem: EstimatorProblem,
    noise: EstimatorNoise,
    *,
    smooth: bool = True,
    steady_tolerance: float = 1e-8,
    smoother_tolerance: float = 1e-6,
    outputs: bool = True,
    manoeuvre: ManoeuvreTest = ManoeuvreTest(),  # noqa: B008 (immutable)
    dt_s: float = 1.0,
    forced_modes: NDArray[np.bool_] | None = None,
    manoeuvre_tolerances: tuple[float, float] | None = None,
) -> KernelOutputs:
    """The filter (and smoother) in plain numpy, the Rust kernel's reference (see the module
    docstring). ``forced_modes``: the power noise's mode of each step, instead of the test's.
    ``manoeuvre_tolerances``: the filter's and the smoother's steady tolerances for the steps
    in the manoeuvre mode (the step's key's mode; the smoother's, the mode of the filter's
    steady state it is inside), as the kernel's; None: ``steady_tolerance`` and
    ``smoother_tolerance`` there too."""
    p = problem
    r, n = p.order, p.n_state
    ip = r
    tol_manoeuvre, tol_back_manoeuvre = (
        (steady_tolerance, smoother_tolerance)
        if manoeuvre_tolerances is None
        else manoeuvre_tolerances
    )
    ib = p.brake_index  # the braking's power P_b, reported with P as their sum
    e_power = p.power_row()
    brake_q = np.zeros(p.phi.size) if p.brake_q is None else p.brake_q
    h = p.measurement_row()
    var_v = noise.measurement_k**2
    switching = manoeuvre.kernel_args(noise, dt_s)
    sw2_of = (
        (noise.power_w_per_sqrt_s**2, noise.power_w_per_sqrt_s**2)
        if switching is None
        else (switching[0] ** 2, noise.power_w_per_sqrt_s**2)
    )
    # the quiet mode's σ² over a step with the cylinder applied
    sw2_applied = sw2_of[0] if switching is None else switching[6] ** 2
    applied = p.applied_transitions()
    power_noise = p.step_power_noise()
    beta = 0.0 if switching is None else min(1.0 / switching[1], 1.0)
    m_sd = math.sqrt(beta / (2.0 - beta)) if switching is not None else 1.0
    mode = switching is None  # True: the manoeuvre mode
    m_z = 0.0
    mode_of = np.zeros(p.reading_c.size, dtype=bool)
    mats = [p.transition_matrix(k) for k in range(p.phi.size)]
    q_gap, gap_dir = p.gap_noise()
    gap_cov = np.outer(gap_dir, gap_dir)
    q_modes = p.mode_noise()
    modal = np.arange(r)
    cm = np.zeros(n)
    cm[:r] = p.c_mean
    cn = np.zeros((p.c_nodes.shape[0], n))
    cn[:, :r] = p.c_nodes
    y = p.reading_c
    n_t = y.size
    x = p.x0.copy()
    cov = p.cov0.copy()
    cov[ip, ip] += sw2_of[int(mode)] * p.p_prior_unit
    out = {
        name: np.full(n_t, np.nan)
        for name in (
            "mean_c",
            "mean_sd_k",
            "max_c",
            "max_sd_k",
            "power_w",
            "power_sd_w",
            "innovation_k",
            "innovation_var_k2",
            "predicted_reading_c",
        )
    }
    keep = smooth
    xs = np.empty((n_t, n)) if keep else np.empty((0, n))
    gains = np.zeros((n_t, n)) if keep else np.empty((0, n))
    s_vars = np.zeros(n_t)
    nus = np.zeros(n_t)
    cov_of: list[FloatArray] = []  # filtered covariance of each step (shared while steady)
    cache_of = np.full(n_t, -1, dtype=np.int64)
    caches: list[_Steady] = []
    steady: _Steady | None = None
    steady_id = -1
    prev_key: tuple[int, bool, bool] | None = None
    prev_cov = cov
    loglik = 0.0
    updates = 0
    frozen_steps = 0
    for t in range(n_t):
        if forced_modes is not None:
            mode = bool(forced_modes[t])
        measured = bool(np.isfinite(y[t]))
        k = int(p.index[t - 1]) if t > 0 else -1  # the transition into t
        # a step whose noise follows the declared power is never steady
        key = (k, measured, mode) if t > 0 and power_noise[t - 1] == 0.0 else None
        mode_of[t] = mode
        if t > 0:
            x_prior = mats[k] @ x
            x_prior[:r] += p.w[t - 1]
            if p.lag:
                x_prior[r + 1] += p.lag_b1[k] * (p.c_probe @ p.w[t - 1])
        else:
            x_prior = x
        if steady is not None and steady.key == key:
            frozen_steps += 1
            cov_f, gain, s_var = steady.cov, steady.gain, steady.s_var
            mean_var, node_var, power_var = steady.mean_var, steady.node_var, steady.power_var
            cache_of[t] = steady_id
        else:
            steady = None
            if t > 0:
                f = mats[k]
                cov_pred = f @ cov @ f.T
                cov_pred = 0.5 * (cov_pred + cov_pred.T)
                sw2 = sw2_applied if (applied[k] and not mode) else sw2_of[int(mode)]
                cov_pred[ip, ip] += p.q_unit[k] * (sw2 + power_noise[t - 1])
                cov_pred[modal, modal] += q_modes[k]
                if ib is not None:
                    cov_pred[ib, ib] += brake_q[k]
                if q_gap[k] > 0:
                    cov_pred += q_gap[k] * gap_cov
            else:
                cov_pred = cov
            s_var = float(h @ cov_pred @ h) + var_v
            if measured:
                gain = cov_pred @ h / s_var
                cov_f = cov_pred - np.outer(gain, gain) * s_var
            else:
                gain = np.zeros(n)
                cov_f = cov_pred
            mean_var = float(cm @ cov_f @ cm)
            node_var = np.einsum("ij,jk,ik->i", cn, cov_f, cn)
            power_var = float(cov_f[ip, ip] if ib is None else e_power @ cov_f @ e_power)
            tol = tol_manoeuvre if key is not None and key[2] else steady_tolerance
            if key is not None and key == prev_key and _converged(cov_f, prev_cov, tol):
                # a steady state met before for this key, within the tolerance, is taken
                # again (the Rust kernel records the excursions from it once)
                steady_id = next(
                    (
                        i
                        for i, c in enumerate(caches)
                        if c.key == key and _converged(cov_f, c.cov, tol)
                    ),
                    -1,
                )
                if steady_id < 0:
                    caches.append(_Steady(key, cov_f, gain, s_var, mean_var, node_var, power_var))
                    steady_id = len(caches) - 1
                steady = caches[steady_id]
        predicted = float(h @ x_prior) + p.t_ref_c
        if measured:
            nu = float(y[t]) - predicted
            x = x_prior + gain * nu
            loglik -= 0.5 * (math.log(2.0 * math.pi * s_var) + nu * nu / s_var)
            updates += 1
            m_z += beta * (nu / math.sqrt(s_var) - m_z)
        else:
            nu = 0.0
            x = x_prior
        if switching is not None:
            z = abs(m_z) / m_sd
            if mode:
                # P's own (not P_b's): the mode sets P's noise
                hold = abs(float(x[ip])) > switching[4] * math.sqrt(max(float(cov_f[ip, ip]), 0.0))
                mode = z > switching[3] or hold
            else:
                mode = z > switching[2]
        cov = cov_f
        prev_cov = cov_f
        prev_key = key
        if outputs:
            nodes = cn @ x
            j = int(np.argmax(nodes))
            out["mean_c"][t] = cm @ x + p.t_ref_c
            out["mean_sd_k"][t] = math.sqrt(max(mean_var, 0.0))
            out["max_c"][t] = nodes[j] + p.t_ref_c
            out["max_sd_k"][t] = math.sqrt(max(float(node_var[j]), 0.0))
            out["power_w"][t] = x[ip] if ib is None else x[ip] + x[ib]
            out["power_sd_w"][t] = math.sqrt(max(power_var, 0.0))
            out["innovation_k"][t] = nu if measured else np.nan
            out["innovation_var_k2"][t] = s_var
            out["predicted_reading_c"][t] = predicted
        if keep:
            xs[t] = x
            gains[t] = gain
            s_vars[t] = s_var
            nus[t] = nu
            cov_of.append(cov_f)
    result: dict[str, object] = dict(out)
    led = (
        led_modes(mode_of, switching[5])
        if keep and switching is not None and forced_modes is None
        else None
    )
    if led is not None:
        second = run_numpy(
            p,
            noise,
            smooth=True,
            steady_tolerance=steady_tolerance,
            smoother_tolerance=smoother_tolerance,
            outputs=False,
            manoeuvre=manoeuvre,
            dt_s=dt_s,
            forced_modes=led,
            manoeuvre_tolerances=manoeuvre_tolerances,
        )
        result.update(
            {name: getattr(second, name) for name in (*SMOOTHED_OUTPUTS, "smoother_frozen_steps")}
        )
    elif keep:
        # the smoother's tolerance inside each of the filter's steady states, by its mode
        tols = [tol_back_manoeuvre if c.key[2] else smoother_tolerance for c in caches]
        result.update(
            _smooth_numpy(p, mats, h, cm, cn, xs, gains, s_vars, nus, cov_of, cache_of, tols)
        )
    return KernelOutputs(
        **result,  # type: ignore[arg-type]  # arrays by field name: checked by the dataclass
        log_likelihood=loglik,
        updates=updates,
        frozen_steps=frozen_steps,
        final_state=x.copy(),
        final_cov=cov.copy(),
        manoeuvre=mode_of,
        manoeuvre_steps=int(mode_of.sum()),
    )


def _smooth_numpy(
    p: EstimatorProblem,
    mats: Sequence[FloatArray],
    h: FloatArray,
    cm: FloatArray,
    cn: FloatArray,
    xs: FloatArray,
    gains: FloatArray,
    s_vars: FloatArray,
    nus: FloatArray,
    cov_of: Sequence[FloatArray],
    cache_of: NDArray[np.int64],
    tols: Sequence[float],
) -> dict[str, object]:
    """The modified Bryson-Frazier smoother (the RTS smoother without inverses):
    ``x_n|N = x_n|n - Σ_n|n λ_n``, ``Σ_n|N = Σ_n|n - Σ_n|n Λ_n Σ_n|n``, with
    ``λ̃ = Ĉᵀ λ - hν/S``, ``Λ̃ = Ĉᵀ Λ Ĉ + hhᵀ/S`` (``Ĉ = I - K h``) at a reading and
    ``λ_n-1 = Fᵀ λ̃``, ``Λ_n-1 = Fᵀ Λ̃ F``. ``tols``: the steady test's tolerance inside each
    of the filter's steady states (``cache_of``'s indices)."""
    n_t, n = xs.shape
    ip = p.order
    ib = p.brake_index
    y = p.reading_c

    def power_column(cov: FloatArray) -> FloatArray:
        """``Σ eᵀ``: the covariance with the reported power (``P`` + ``P_b``)."""
        return cov[:, ip] if ib is None else cov[:, ip] + cov[:, ib]

    lam = np.zeros(n)
    big = np.zeros((n, n))
    frozen: tuple[int, FloatArray, float, FloatArray, float] | None = None
    frozen_steps = 0
    out: dict[str, FloatArray] = {name: np.empty(n_t) for name in SMOOTHED_OUTPUTS}
    for t in range(n_t - 1, -1, -1):
        cov = cov_of[t]
        cache = int(cache_of[t])
        xs_t = xs[t] - cov @ lam
        nodes = cn @ xs_t
        j = int(np.argmax(nodes))
        if frozen is not None and frozen[0] == cache:
            frozen_steps += 1
            mean_var, node_var, power_var = frozen[2], frozen[3], frozen[4]
        else:
            sc = cov @ cm
            mean_var = float(cm @ cov @ cm - sc @ big @ sc)
            snode = cov @ cn[j]
            node_var_j = float(cn[j] @ cov @ cn[j] - snode @ big @ snode)
            node_var = np.full(cn.shape[0], np.nan)
            node_var[j] = node_var_j
            sp = power_column(cov)
            power_var = float(sp[ip] + (0.0 if ib is None else sp[ib]) - sp @ big @ sp)
        out["smoothed_mean_c"][t] = cm @ xs_t + p.t_ref_c
        out["smoothed_mean_sd_k"][t] = math.sqrt(max(mean_var, 0.0))
        out["smoothed_max_c"][t] = nodes[j] + p.t_ref_c
        out["smoothed_max_sd_k"][t] = math.sqrt(max(float(node_var[j]), 0.0))
        out["smoothed_power_w"][t] = xs_t[ip] if ib is None else xs_t[ip] + xs_t[ib]
        out["smoothed_power_sd_w"][t] = math.sqrt(max(power_var, 0.0))
        if t == 0:
            break
        if np.isfinite(y[t]):
            k, s_var = gains[t], s_vars[t]
            lam_t = lam - h * (k @ lam) - h * (nus[t] / s_var)
            u = big @ k
            big_t = big - np.outer(h, u) - np.outer(u, h) + (k @ u + 1.0 / s_var) * np.outer(h, h)
        else:
            lam_t, big_t = lam, big
        f = mats[int(p.index[t - 1])]
        lam = f.T @ lam_t
        if frozen is not None and frozen[0] == cache:
            continue  # big stays the steady one
        frozen = None
        new = f.T @ big_t @ f
        new = 0.5 * (new + new.T)
        if cache >= 0 and _converged(new, big, tols[cache]):
            cov_c = cov_of[t]
            sc = cov_c @ cm
            sn = cn @ cov_c  # (m, n)
            sp = power_column(cov_c)
            frozen = (
                cache,
                new,
                float(cm @ cov_c @ cm - sc @ new @ sc),
                np.einsum("ij,ij->i", sn, cn) - np.einsum("ij,jk,ik->i", sn, new, sn),
                float(sp[ip] + (0.0 if ib is None else sp[ib]) - sp @ new @ sp),
            )
        big = new
    return {**out, "smoother_frozen_steps": frozen_steps}


def numpy_kernel(
    problems: Sequence[EstimatorProblem],
    noise: EstimatorNoise,
    *,
    smooth: bool,
    config: EstimatorConfig,
    outputs: bool = True,
) -> list[KernelOutputs]:
    """:func:`run_numpy` on each problem with ``config``'s settings (a
    :class:`fleetbrake.model.estimator.Kernel`)."""
    return [
        run_numpy(
            p,
            noise,
            smooth=smooth,
            steady_tolerance=config.steady_tolerance,
            smoother_tolerance=config.smoother_tolerance,
            outputs=outputs,
            manoeuvre=config.manoeuvre,
            dt_s=config.dt_s,
            manoeuvre_tolerances=config.manoeuvre_tolerances,
        )
        for p in problems
    ]
