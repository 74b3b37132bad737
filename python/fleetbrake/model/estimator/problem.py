"""The estimator's problem: one wagon's logged seconds (:class:`WagonSeries`, what a caller
gives) and its filtering problem as arrays (:class:`EstimatorProblem`, what
:func:`~fleetbrake.model.estimator.prepare.prepare` makes of them and the kernel takes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake.errors import FleetbrakeError

__all__ = ["Z95", "EstimatorInputError", "EstimatorProblem", "FloatArray", "WagonSeries"]

FloatArray = NDArray[np.float64]

Z95 = 1.959963984540054
"""The two-sided 95 % quantile of the standard normal: bounds are mean ± Z95 sd."""


class EstimatorInputError(FleetbrakeError, ValueError):
    """A wagon's series the estimator cannot take (exit 1); the message names the wagon, the
    column and the first row concerned."""


@dataclass(frozen=True)
class WagonSeries:
    """One wagon's logged seconds, in time order: N samples. ``time_s`` in seconds (any
    origin; steps of ``dt_s``, or gaps of whole multiples of it); ``reading_c`` NaN where the
    reading is missing or faulty. Pressure, speed and ambient must be present (fill short gaps
    first, e.g. with ``physics.fill_short_gaps``)."""

    time_s: FloatArray
    p_bar: FloatArray
    speed_kmh: FloatArray
    ambient_c: FloatArray
    reading_c: FloatArray
    wagon_id: str = ""

    @classmethod
    def of(
        cls,
        *,
        time_s: ArrayLike,
        p_bar: ArrayLike,
        speed_kmh: ArrayLike,
        ambient_c: float | ArrayLike,
        reading_c: ArrayLike,
        wagon_id: str = "",
    ) -> WagonSeries:
        """A series from array-likes (a number for a constant ambient)."""
        t = np.asarray(time_s, dtype=np.float64).reshape(-1)
        amb = np.asarray(ambient_c, dtype=np.float64)
        return cls(
            time_s=t,
            p_bar=np.asarray(p_bar, dtype=np.float64).reshape(-1),
            speed_kmh=np.asarray(speed_kmh, dtype=np.float64).reshape(-1),
            ambient_c=np.full(t.size, float(amb)) if amb.ndim == 0 else amb.reshape(-1),
            reading_c=np.asarray(reading_c, dtype=np.float64).reshape(-1),
            wagon_id=wagon_id,
        )


@dataclass(frozen=True)
class EstimatorProblem:
    """One wagon's filtering problem as arrays, independent of the noise parameters.

    The state has ``n = r + 1 (+ 1) (+ 1)`` entries: r modes, the unexplained power ``P``, the
    lagged reading ``s`` if ``lag``, the braking's power ``P_b`` if ``brake``. The time grid has N samples (the logged seconds and the
    seconds filled into short gaps; ``logged`` marks the former); step n (n = 1 .. N-1) goes
    from sample n-1 to n by transition ``index[n-1]``.

    Transition k: modal propagator ``a[k]`` (r, r; diagonal where ``diagonal[k]``), the
    power's column ``gamma[k]`` (r), its decay ``phi[k]`` and noise ``q_unit[k]`` (× σ_w²),
    and for the lag, ``lag_a[k]``, ``lag_b1[k]`` (weight of the seat at the step's end),
    ``lag_row[k]`` (r) and ``lag_power[k]`` (the lag's row of the transition matrix).
    """

    wagon_id: str
    order: int
    lag: bool
    t_ref_c: float
    time_s: FloatArray
    logged: NDArray[np.bool_]
    reading_c: FloatArray
    index: NDArray[np.int64]
    w: FloatArray
    """(N-1, r): the modal response to the declared inputs of each step."""
    a: FloatArray
    diagonal: NDArray[np.bool_]
    gamma: FloatArray
    phi: FloatArray
    q_unit: FloatArray
    lag_a: FloatArray
    lag_b1: FloatArray
    lag_row: FloatArray
    lag_power: FloatArray
    c_probe: FloatArray
    c_mean: FloatArray
    c_nodes: FloatArray
    """(m, r): the friction-face nodes whose maximum stands for the face's."""
    x0: FloatArray
    cov0: FloatArray
    """Prior covariance without the power's share (added from σ_w: ``p_prior_unit``)."""
    p_prior_unit: float
    """The prior variance of P is σ_w² times this (τ/2: the stationary variance)."""
    q_gap: FloatArray | None = None
    """(K): variance added by transition k to the block's uniform offset ``gap_dir`` (K²;
    non-zero only over unlogged intervals). None: zeros."""
    gap_dir: FloatArray | None = None
    """(n): the state of a uniform 1 K offset of the block (and of the lagged reading)."""
    held: NDArray[np.bool_] | None = None
    """(N-1): the steps over which the wheel stands, the unexplained power held (it neither
    heats nor diffuses; :attr:`EstimatorConfig.standstill_speed_kmh`). None: none."""
    q_modes: FloatArray | None = None
    """(K, r): variance added by transition k to each modal coordinate (K²): the seat
    error's coordinate (the last, when the problem has one). None: zeros."""
    applied: NDArray[np.bool_] | None = None
    """(K): whether transition k is a step with the cylinder applied (its quiet-mode noise
    ``ManoeuvreTest.applied_quiet_w_per_sqrt_s``). None: none is."""

    power_noise: FloatArray | None = None
    """(N-1): ``(g P_declared)²`` of each step, W²/s: the power's diffusion over the step in
    proportion to the declared braking power
    (:attr:`EstimatorConfig.declared_power_noise_per_sqrt_s`), added to σ² (times
    ``q_unit``); such a step is never steady. None: zeros."""
    brake_phi: FloatArray | None = None
    """(K): the braking power ``P_b``'s factor over transition k (1 where the declared heat is
    not zero, ``exp(-L/τ_b)`` otherwise; :attr:`EstimatorConfig.brake_power_w_per_sqrt_s`). None: the
    state has no ``P_b``. With it, ``P_b`` is the state's last entry, heating the modes
    through ``gamma[k]`` as ``P`` does."""
    brake_q: FloatArray | None = None
    """(K): the variance transition k adds to ``P_b``, W² (``σ_b² L`` braking, 0 otherwise)."""
    eigenvectors: FloatArray | None = None
    """(K, r, r): ``a[k] = Q diag(eigenvalues[k]) Qᵀ`` with Q this (its columns the
    eigenvectors): a dense transition's from ``prepare``'s own ``eigh`` of the convection's
    operator (what ``a[k]`` is made of), a diagonal one's the identity. The Rust kernel steps
    a dense transition as a diagonal one in this basis. None: no dense transition, or none
    given (the Rust kernel then steps a dense one dense)."""
    eigenvalues: FloatArray | None = None
    """(K, r): the eigenvalues that go with ``eigenvectors`` (None with it)."""

    @property
    def brake(self) -> bool:
        """Whether the state carries the braking's power ``P_b`` (its last entry)."""
        return self.brake_phi is not None

    @property
    def brake_index(self) -> int | None:
        """``P_b``'s index in the state, None without it."""
        return self.n_state - 1 if self.brake else None

    def step_power_noise(self) -> FloatArray:
        """``power_noise``, zeros where not given."""
        if self.power_noise is None:
            return np.zeros(self.index.size)
        return self.power_noise

    def applied_transitions(self) -> NDArray[np.bool_]:
        """``applied``, False where not given."""
        return np.zeros(self.phi.size, dtype=bool) if self.applied is None else self.applied

    def mode_noise(self) -> FloatArray:
        """``q_modes``, zeros where not given."""
        if self.q_modes is None:
            return np.zeros((self.phi.size, self.order))
        return self.q_modes

    def gap_noise(self) -> tuple[FloatArray, FloatArray]:
        """``q_gap`` and ``gap_dir``, zeros where not given."""
        q = np.zeros(self.phi.size) if self.q_gap is None else self.q_gap
        u = np.zeros(self.n_state) if self.gap_dir is None else self.gap_dir
        return q, u

    @property
    def n_state(self) -> int:
        return self.order + 1 + int(self.lag) + int(self.brake_phi is not None)

    @property
    def n_samples(self) -> int:
        return int(self.reading_c.size)

    def transition_matrix(self, k: int) -> FloatArray:
        """The dense transition matrix F of transition ``k`` (n, n)."""
        r, n = self.order, self.n_state
        f = np.zeros((n, n))
        f[:r, :r] = self.a[k]
        f[:r, r] = self.gamma[k]
        f[r, r] = self.phi[k]
        if self.lag:
            f[r + 1, :r] = self.lag_row[k]
            f[r + 1, r] = self.lag_power[k]
            f[r + 1, r + 1] = self.lag_a[k]
        if self.brake_phi is not None:
            ib = n - 1
            f[:r, ib] = self.gamma[k]
            f[ib, ib] = self.brake_phi[k]
            if self.lag:
                f[r + 1, ib] = self.lag_power[k]
        return f

    def power_row(self) -> FloatArray:
        """The reported unexplained power is ``e x``: ``P`` (+ ``P_b``)."""
        e = np.zeros(self.n_state)
        e[self.order] = 1.0
        if self.brake_phi is not None:
            e[self.n_state - 1] = 1.0
        return e

    def measurement_row(self) -> FloatArray:
        """h: the reading is ``h x + T_ref``."""
        h = np.zeros(self.n_state)
        if self.lag:
            h[self.order + 1] = 1.0
        else:
            h[: self.order] = self.c_probe
        return h
