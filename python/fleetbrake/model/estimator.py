"""The virtual sensor: the wheel-block contact temperature every second, with its uncertainty.

A Kalman filter and a Rauch-Tung-Striebel smoother (in the modified Bryson-Frazier form,
which needs no matrix inverse) on the reduced model's state, fed with the declared heat input of each second and updated with each
valid thermistor reading; the heat that the declared inputs do not explain is estimated as
an unknown input.

::

    from fleetbrake.model.estimator import EstimatorConfig, WagonSeries, estimate_contact

    series = WagonSeries.of(time_s=t, p_bar=p, speed_kmh=v, ambient_c=air, reading_c=block)
    est = estimate_contact(rom, wagon, series)       # filtered and smoothed, per logged second
    est.contact_mean_c, est.contact_mean_lo_c, est.contact_mean_hi_c
    est.smoothed_contact_max_c, est.unexplained_power_w, est.innovation_k

    # many wagons (the Rust kernel runs them in parallel), the noise from fit days:
    fit = fit_noise([prepare(rom, wagon, s) for s in fit_days])
    config = EstimatorConfig(noise=fit.noise)
    estimates = estimate([prepare(rom, wagon, s, config=config) for s in days], config=config)

The outputs are the columns of ``v_contact_estimates`` (``shared/spec/interface.md``, v2):
``contact_mean_c`` and its bounds, ``contact_max_c``/``contact_max_hi_c``, the smoothed
mean and bounds, ``unexplained_power_w`` and bounds, ``innovation_k``.

**State.** ``x = (ξ, P[, s], P_b)``: the reduced model's modal state ``ξ`` (``θ = T - T_ref``
in modal coordinates, r values, ``T_ref`` the first valid reading; with ``seat_error_sd_k``
the seat's model error ``b`` as one coordinate more), the unexplained heat power
``P`` (W) entering the block through its friction face, when the revision has a
``sensor_lag`` the thermistor's lagged reading ``s``, and the braking's unexplained power
``P_b`` (W, by default; ``brake_power_w_per_sqrt_s=None`` leaves it out).

**Process model** of one step ``t_n -> t_n+1``:

* ``ξ' = A ξ + γ P + w``: ``A``, the reduced model's exact propagator at the step's
  convection (diagonal at the nominal convection; one tabulated propagator per distinct,
  quantised convection value and step length otherwise); ``w``, the response to the declared
  inputs held over the step (the mean of the two bounding samples, exactly as
  :func:`fleetbrake.model.timeline.simulate_timeline` drives the model: the declared force
  chain and heat partition of ``model.physics``, the revision's effects, the ambient); ``γ``,
  the response to 1 W of unexplained power on the friction face.
* ``P' = φ P + ω``: a Gauss-Markov process (Ornstein-Uhlenbeck, ``dP = -P/τ dt + σ_w dW``)
  with time constant ``τ = power_time_constant_s`` (1 h by default: a dragging or weak brake
  persists for hours; without evidence the estimate returns to zero over an hour), discretised
  exactly: ``φ = exp(-dt/τ)``, ``var ω = σ_w² τ/2 (1 - φ²)`` (≈ ``σ_w² dt`` per second).
* ``s' = a s + (1 - a - c) T_seat' + c T_seat`` (the exact ramp response of
  :func:`fleetbrake.model.rom.first_order_lag`) when the revision has a sensor lag.
* Unlogged intervals longer than ``max_interpolated_gap_s``: the unit sleeps only when the
  wagon stands (``fleet-data.md``), so the block cools at standstill with no friction heat,
  declared or not: one exact step of the whole length, ``γ = 0``, ``P`` decaying by ``φ``
  (its variance growing towards the stationary ``σ_w² τ/2``). Shorter gaps are filled by
  linear interpolation of the inputs, second by second, with no reading.
* ``P_b' = P_b + ω_b`` (``var ω_b = σ_b² L``, ``brake_power_w_per_sqrt_s`` 0.3 W/√s) over a
  step with declared friction heat, ``P_b' = φ_b P_b`` with no noise over any other
  (``brake_power_time_constant_s`` τ_b 0 s: forgotten at the first such step): the
  braking's unexplained power (an input error of the logged pressure heats only while the
  declared inputs brake), heating the face as ``P`` does; the reported power is
  ``P + P_b``.
* Options (off by default: they cost speed, ``docs/estimator.md``): ``P`` held at
  standstill, friction heating only while the wheel turns (``standstill_speed_kmh``: over
  such a step and over an unlogged standstill ``γ = 0``, ``φ = 1``, no noise, and 0 W
  reported); ``b' = φ_b b + η``, the reduced model's own error at the sensor seat
  (``seat_error_sd_k``, a Gauss-Markov process, a coordinate appended to ``ξ`` that the
  face does not see).

**Measurement.** ``y = T_seat (+ b) + v`` (or ``s + v`` with a lag, ``s`` lagging
``T_seat (+ b)``), ``var v = σ_v²``; a missing or faulty reading (NaN) skips the update.

**Noise.** ``σ_v`` and ``σ_w`` are estimated together by maximum likelihood on the
innovations (:func:`fit_noise`): ``log L = -1/2 Σ (log 2π S_n + ν_n²/S_n)`` over the readings
of the fit data, maximised over ``(log σ_v, log σ_w)`` by Nelder-Mead. ``σ_w`` has a floor
(``min_power_noise_w_per_sqrt_s``, 3 W/√s by default): on data where nothing unexplained
happens the likelihood keeps rising as ``σ_w`` falls, and a filter tuned that way is
overconfident when a dragging brake comes (at 1 W/√s the band held the truth for 81-91 % of
a day with drags, at 3 W/√s for 90-96 %; ``docs/estimator.md`` has the evidence).

**Two modes of the power's noise.** The likelihood's ``σ_w`` is the manoeuvre mode's: the
filter runs in a quiet mode (``σ_q``, ``EstimatorNoise.quiet_power_w_per_sqrt_s``, 0.03 W/√s)
while a windowed normalised-innovation test (:class:`ManoeuvreTest`) says the declared
model explains the readings, and in the manoeuvre mode (``σ_w``) while it says heat is
missing or the estimated power is clearly not zero. The mode sequence is the forward pass's;
the smoother replays it with the manoeuvre mode begun ``smoother_lead_s`` (120 s) before each
switch-on. The declared model's own error is a random walk of the block's uniform offset
(``model_offset_sd_k_per_sqrt_s``, 1.5 mK/√s). ``fit_noise`` fits σ_v and σ_w with one mode.
σ_q, σ_b, τ_b, σ_o and the test's settings are a documented tuning (chosen on two full-FE
acceptance fleets against their truth, checked on a held-out third; ``docs/estimator.md``,
"The defaults: a documented tuning").

**Prior.** ``θ`` uniform with standard deviation ``initial_temperature_sd_k`` around the first
valid reading; ``P`` at its stationary distribution ``N(0, σ_w² τ/2)``; ``P_b`` exactly 0.

**Outputs** per logged second: filtered (live) and smoothed (after the fact) friction-face
mean and maximum with their standard deviations and 95 % bounds, the unexplained power with
its bounds, the innovation, its variance and the predicted reading. The face maximum is the
largest of the reduced model's face-maximum nodes; its band is that node's.

**Speed.** The covariance recursion depends only on the sequence of (propagator, reading or
not): where that stays the same and the covariance has stopped changing (elementwise, relative
to ``sqrt(Σ_ii Σ_jj)``, below ``steady_tolerance``), the filter keeps the steady-state gain and
covariance and only the mean is stepped (standing, cruising, braking alike at the nominal
convection); the smoother's backward information matrix is frozen the same way. A steady
state found again for the same key within the tolerance is the one found before (both
engines), and the Rust kernel replays a recorded excursion from it (a missing reading and
the seconds after) instead of computing it again: the same numbers. The Rust
kernel (``engine="rust"``) does this with structured (diagonal-plus-border) propagators and
bounded memory; :func:`run_numpy` is the plain numpy implementation of the same algorithm,
its reference in the tests and its peer in ``bench estimator``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake import _ext
from fleetbrake.errors import FleetbrakeError
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import DriveInputs, EffectSet, SensorLag
from fleetbrake.model.rom import ReducedModel
from fleetbrake.model.timeline import H_QUANTUM_W_M2K, drive_inputs

__all__ = [
    "Z95",
    "ContactEstimate",
    "EstimatorConfig",
    "EstimatorInputError",
    "EstimatorNoise",
    "EstimatorProblem",
    "KernelOutputs",
    "ManoeuvreTest",
    "NoiseFit",
    "WagonSeries",
    "estimate",
    "estimate_contact",
    "fit_noise",
    "measurement_noise",
    "noise_from_second_differences",
    "prepare",
    "run_numpy",
    "rust_available",
]

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
Engine = Literal["rust", "numpy"]

Z95 = 1.959963984540054
"""The two-sided 95 % quantile of the standard normal: bounds are mean ± Z95 sd."""


class EstimatorInputError(FleetbrakeError, ValueError):
    """A wagon's series the estimator cannot take (exit 1); the message names the wagon, the
    column and the first row concerned."""


# --------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class EstimatorNoise:
    """The two noise parameters that :func:`fit_noise` estimates."""

    measurement_k: float = 0.1
    """σ_v: standard deviation of the thermistor's reading noise, K."""
    power_w_per_sqrt_s: float = 3.0
    """σ_w: diffusion of the unexplained power in the manoeuvre mode (while the innovations say
    the declared model is missing heat; at every second if ``quiet_power_w_per_sqrt_s`` is
    None), W/√s (its standard deviation grows by σ_w √t over t seconds, for t well below the
    time constant). The default is the floor of :func:`fit_noise`."""
    quiet_power_w_per_sqrt_s: float | None = 0.03
    """σ_q: the quiet mode's diffusion, where the declared model explains the readings (most
    of the time). A documented tuning with the braking's power ``P_b`` and σ_o
    (``docs/estimator.md``, "The defaults: a documented tuning"; 0.3 until then); None: one
    mode, σ_w at every second."""

    def __post_init__(self) -> None:
        for name in ("measurement_k", "power_w_per_sqrt_s", "quiet_power_w_per_sqrt_s"):
            value = getattr(self, name)
            if value is None and name == "quiet_power_w_per_sqrt_s":
                continue
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(
                    f"EstimatorNoise.{name} must be positive and finite, got {value!r}"
                )

    @property
    def single_mode(self) -> EstimatorNoise:
        """The same σ_v and σ_w with one mode (σ_w at every second)."""
        return dataclasses.replace(self, quiet_power_w_per_sqrt_s=None)


@dataclass(frozen=True)
class ManoeuvreTest:
    """The windowed normalised-innovation test that moves the unexplained power's noise from
    the quiet mode (σ_q) to the manoeuvre mode (σ_w) and back. ``m``, the exponentially
    weighted mean of ``ν/√S`` over ``window_s`` (β = dt/window), has the standard deviation
    ``√(β/(2-β))`` while the declared model and the sensor hold; the manoeuvre mode starts
    where ``|m|`` exceeds ``on_sigma`` of those, and holds while ``|m|`` exceeds
    ``off_sigma`` or the estimated power is more than ``hold_power_sigma`` of its standard
    deviations from zero (a drag, once followed, explains the readings: the innovations are
    white again, the power is not zero). ``docs/estimator.md`` has the evidence."""

    window_s: float = 120.0
    on_sigma: float = 5.0
    off_sigma: float = 1.0
    """1 σ (2 until the σ_q 0.03 defaults): with σ_q 0.03 the band shrinks to ±0.05 K within a
    minute of the switch-off, so the mode holds until the innovations are whiter
    (``docs/estimator.md``, session 12 (third))."""
    hold_power_sigma: float = 2.0
    smoother_lead_s: float = 120.0
    """The smoother's mode sequence: the filter's, with the manoeuvre mode begun this long
    before each switch-on (the test switches a window or so after a step of the power; the
    smoother, which sees the whole series, lets the power step where it did). Where that
    changes the sequence, the smoother runs on a second forward pass with it; the filter and
    its reported modes are unchanged. Counted in steps (``smoother_lead_s / dt_s``), as the
    window is. 0: the filter's sequence. 120 s by default: with σ_q 0.03 the smoother without
    it spreads a drag's onset over the half hour before it (``docs/estimator.md``, session 8
    (second))."""
    applied_quiet_w_per_sqrt_s: float | None = None
    """The quiet mode's diffusion over a step with the cylinder applied
    (:attr:`EstimatorConfig.applied_pressure_bar`), W/√s: a braking's heat depends on the
    logged pressure's scale, whose error (0.4 % on the synthetic fleets) acts only while the
    cylinder is applied. None: σ_q there as elsewhere. ``docs/estimator.md`` (session 9)."""

    def __post_init__(self) -> None:
        applied = self.applied_quiet_w_per_sqrt_s
        if applied is not None and not (math.isfinite(applied) and applied > 0):
            raise ValueError(
                f"ManoeuvreTest.applied_quiet_w_per_sqrt_s must be positive and finite, "
                f"got {applied!r}"
            )
        if not (math.isfinite(self.window_s) and self.window_s > 0):
            raise ValueError(f"ManoeuvreTest.window_s must be positive, got {self.window_s!r}")
        if not (math.isfinite(self.smoother_lead_s) and self.smoother_lead_s >= 0):
            raise ValueError(
                f"ManoeuvreTest.smoother_lead_s must be >= 0 and finite, got {self.smoother_lead_s!r}"
            )
        for name in ("on_sigma", "off_sigma", "hold_power_sigma"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"ManoeuvreTest.{name} must be >= 0 and finite, got {value!r}")

    def kernel_args(
        self, noise: EstimatorNoise, dt_s: float
    ) -> tuple[float, float, float, float, float, int, float] | None:
        """(σ_q, window in steps, on, off, hold, the smoother's lead in steps, σ_q with the
        cylinder applied) for the kernels; None with one mode."""
        quiet = noise.quiet_power_w_per_sqrt_s
        if quiet is None:
            return None
        applied = self.applied_quiet_w_per_sqrt_s
        return (
            float(quiet),
            float(self.window_s / dt_s),
            float(self.on_sigma),
            float(self.off_sigma),
            float(self.hold_power_sigma),
            round(self.smoother_lead_s / dt_s),
            float(quiet if applied is None else applied),
        )


SMOOTHED_OUTPUTS = (
    "smoothed_mean_c",
    "smoothed_mean_sd_k",
    "smoothed_max_c",
    "smoothed_max_sd_k",
    "smoothed_power_w",
    "smoothed_power_sd_w",
)
"""The smoother's outputs, per second (the numpy reference's names, as the kernel's)."""


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


@dataclass(frozen=True)
class EstimatorConfig:
    """Everything the estimator is set with (the noise usually from :func:`fit_noise`)."""

    noise: EstimatorNoise = field(default_factory=EstimatorNoise)
    power_time_constant_s: float = 3600.0
    """τ of the unexplained power's Gauss-Markov process."""
    initial_temperature_sd_k: float = 5.0
    """Prior standard deviation of the block's (uniform) temperature at the first sample
    around the first valid reading."""
    dt_s: float = 1.0
    """Sample period of the logs."""
    max_interpolated_gap_s: float = 15.0
    """Unlogged intervals up to this long are filled by interpolation (the wagon may be
    moving); longer ones are a standstill (the unit sleeps only when the wagon stands)."""
    gap_offset_sd_k: float = 20.0
    """What a longer unlogged interval may have done to the block that the model does not
    know (a lost or quarantined file while the wagon ran, an ambient unlike the logged one):
    the block's uniform offset gets a variance of ``gap_offset_sd_k² (1 - exp(-L/τ_gap))``
    over an interval of L seconds, so the first readings after it re-anchor the estimate (as
    the simulation's chain re-anchors), instead of being explained as unexplained power.
    0: the standstill model is trusted."""
    gap_offset_time_constant_s: float = 1800.0
    """τ_gap of ``gap_offset_sd_k``: a 60 s hole adds about 3.6 K of offset sd, an hour 18.6 K."""
    model_offset_sd_k_per_sqrt_s: float = 0.0015
    """σ_o: the declared model's own error as a random walk of the block's uniform offset
    (variance ``σ_o² L`` over a step of L seconds, along the gap's direction): the reduced
    model is not the block (another mesh, another integrator, the face's law); without it the
    smoothed band is narrower than that error (``docs/estimator.md``). 1.5 mK/√s with the
    other defaults (3 with σ_q 0.3 until then, tuned on fleets written at a coarser mesh);
    0: the model is exact."""
    steady_tolerance: float = 1e-3
    """The filter's covariance counts as steady when no element changed in a step by more
    than this times ``sqrt(Σ_ii Σ_jj)`` (0: only when unchanged), in the quiet mode (the
    manoeuvre mode's: ``manoeuvre_steady_tolerance``). 1e-3 (1e-7 until session 15): after
    each braking's release the covariance settles at the closed loop's slowest rate (the
    slowest modes' variances; median 1,212 s to pass 1e-7, 361 s to pass 1e-3, on 95 releases
    of 4 bench wagon-days), so at 1e-7 only 14.5 % of the seconds were steady and the kernel
    ran at 0.35-0.39x session 6's speed. At 1e-3 (with ``smoother_tolerance`` 1e-3) against
    1e-7 / 1e-5, on 8 bench wagon-days: the filtered mean moves by at most 4.2 mK, its sd by
    2.2 mK, the power by 71 mW, the smoothed by 2.2 mK, 1.5 mK and 53 mW; 66.5 % of the seconds
    steady, 0.67-0.77x the former defaults' kernel speed; every acceptance bar still met on
    seeds 3, 4 and 5 (``docs/estimator.md``, session 15)."""
    smoother_tolerance: float = 1e-3
    """The same for the smoother's information matrix, which only the smoothed standard
    deviations use (the smoothed means do not depend on it), in the quiet mode (the manoeuvre
    mode's: ``manoeuvre_smoother_tolerance``). 1e-3 (1e-5 until session 15; figures at
    ``steady_tolerance``): the smoother's matrix is frozen in 54 % of the seconds instead of
    5 %."""
    manoeuvre_steady_tolerance: float | None = 1e-7
    """``steady_tolerance`` for the steps in the manoeuvre mode (their keys and steady states
    are their own); None: ``steady_tolerance`` there too. In the manoeuvre mode the power's
    variance moves fast and the estimates follow it: on 4 bench wagon-days with an unexplained
    2 K rise of the reading, 1e-3 there moved the filtered mean by up to 0.103 K and the
    smoothed by 68 mK against 1e-7 / 1e-5, while 1e-7 / 1e-5 there (the quiet mode at 1e-3)
    moved the smoothed mean by at most 3.3 mK, at the same speed (1.3 % of those seconds are
    in the manoeuvre mode; ``docs/estimator.md``, session 15). An exact recursion sets it,
    ``manoeuvre_smoother_tolerance`` and the two quiet ones to 0."""
    manoeuvre_smoother_tolerance: float | None = 1e-5
    """``smoother_tolerance`` for the smoother's steps inside the filter's steady states of
    the manoeuvre mode; None: ``smoother_tolerance`` there too (evidence at
    ``manoeuvre_steady_tolerance``)."""
    checkpoint_steps: int = 256
    """Rust kernel: seconds between the filter's checkpoints, which the smoother replays."""
    manoeuvre: ManoeuvreTest = field(default_factory=ManoeuvreTest)
    """The test between the power noise's quiet and manoeuvre modes."""
    standstill_speed_kmh: float | None = None
    """The unexplained power is friction the declared inputs do not explain (a dragging
    brake, a weak one), and friction heats only while the wheel turns (``μ F v``): over a
    step whose bounding samples both read at most this speed (0.5 km/h: the running median
    of a standing wagon's GPS speed reads 0.0-0.3 km/h on the synthetic fleets), and over
    every unlogged standstill, ``P`` neither heats the block nor diffuses (``γ = 0``,
    ``φ = 1``, no noise; the readings there may still revise it through its correlation
    with the block's state), and the power reported for such a second is 0 (no friction
    heat). None (the default): ``P`` heats and diffuses at every step. An option, not the
    default, because it costs speed (stops break the steady state); ``docs/estimator.md``
    has the figures, and why the cylinder's pressure does not count as turning."""
    seat_error_sd_k: float = 0.0
    """The reduced model's error at the sensor seat as a coordinate of its own (``b``, a
    Gauss-Markov process of this stationary standard deviation, K, read as
    ``y = T_seat + b + v``): the reduced model is not the block, and where the two differ at
    the seat (0.1-0.2 K in a hard braking on the full-FE fleets) they need not differ on the
    face; without ``b`` such a mismatch moved the face's estimate (through ``P`` and the
    offset) where the open-loop prediction was right. 0 (the default): no such coordinate.
    0.05 K with ``seat_error_time_constant_s`` 600 s met the issue's smoothed-RMSE bar on the
    full-FE acceptance fleets, but the covariance then settles about half as often (the
    kernel 45 % slower per CPU-second); ``docs/estimator.md`` has the figures."""
    seat_error_time_constant_s: float = 600.0
    """τ_b of ``seat_error_sd_k``: how long the seat's model error persists."""
    applied_pressure_bar: float | None = None
    """A step has the cylinder applied where either bounding sample's logged pressure exceeds
    this (bar; the flags' release threshold is 0.05); over such a step (not a standstill, not
    held) the quiet mode diffuses with ``manoeuvre.applied_quiet_w_per_sqrt_s``. None: no step
    is told apart (one quiet σ_q)."""
    declared_power_noise_per_sqrt_s: float = 0.0
    """g: a share of the unexplained power's diffusion in proportion to the declared braking
    power of the step (the friction heat into the block that the logged pressure and speed
    give), ``σ² = σ_q² + (g P_declared)²`` per second (σ_w² + ... in the manoeuvre mode),
    1/√s: the declared input's own error (a scale error of the logged pressure, 0.4 % on the
    synthetic fleets) is in proportion to it, so the filter is loose where, and as much as,
    the declared heat can be wrong, and tight while released (where the steady path stays).
    0: none. ``docs/estimator.md`` (session 10)."""
    brake_power_w_per_sqrt_s: float | None = 0.3
    """σ_b: the braking's unexplained power as a state of its own, ``P_b`` (W into the block
    through the friction face, the same ``γ`` as ``P``): over a step whose declared friction
    heat is not zero (the logged pressure above the cylinder's spring and the regulator's
    thresholds, the wheel turning; not a standstill gap, not held) it diffuses with σ_b
    (W/√s); over any other step it decays with ``brake_power_time_constant_s`` and gets no
    noise. A braking's input error (the logged pressure's scale or offset: heat only where
    the declared force is not zero) is followed while it brakes and forgotten within a minute
    of the release, instead of persisting in ``P`` (τ 1 h) into the released seconds. The
    reported unexplained power is ``P + P_b``. 0.3 W/√s by default (the 7 mbar pressure
    sensor's error followed within 20 %; below 0.2 it is not); None: no such state (the
    filter before; faster, ``docs/estimator.md``). ``docs/estimator.md`` (session 12, and
    "The defaults: a documented tuning")."""
    brake_power_time_constant_s: float = 0.0
    """τ_b of ``brake_power_w_per_sqrt_s``: how fast ``P_b`` decays once released, s; 0 (the
    default): it is forgotten at the first step without declared heat (its variance exactly
    0 there, so the covariance can be steady again; with τ_b > 0 ``P_b``'s variance decays
    geometrically and the relative steady test never passes until it underflows)."""

    def __post_init__(self) -> None:
        for name in (
            "power_time_constant_s",
            "initial_temperature_sd_k",
            "dt_s",
            "gap_offset_time_constant_s",
            "seat_error_time_constant_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(
                    f"EstimatorConfig.{name} must be positive and finite, got {value!r}"
                )
        if not (math.isfinite(self.max_interpolated_gap_s) and self.max_interpolated_gap_s >= 0):
            raise ValueError("EstimatorConfig.max_interpolated_gap_s must be >= 0 and finite")
        for name in (
            "steady_tolerance",
            "smoother_tolerance",
            "gap_offset_sd_k",
            "model_offset_sd_k_per_sqrt_s",
            "seat_error_sd_k",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"EstimatorConfig.{name} must be >= 0 and finite")
        for name in ("manoeuvre_steady_tolerance", "manoeuvre_smoother_tolerance"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ValueError(f"EstimatorConfig.{name} must be None or >= 0 and finite")
        if self.checkpoint_steps < 1:
            raise ValueError("EstimatorConfig.checkpoint_steps must be >= 1")
        gain = self.declared_power_noise_per_sqrt_s
        if not (math.isfinite(gain) and gain >= 0):
            raise ValueError(
                f"EstimatorConfig.declared_power_noise_per_sqrt_s must be >= 0 and finite, "
                f"got {gain!r}"
            )
        bar = self.applied_pressure_bar
        if bar is not None and not (math.isfinite(bar) and bar >= 0):
            raise ValueError(
                f"EstimatorConfig.applied_pressure_bar must be >= 0 and finite, got {bar!r}"
            )
        speed = self.standstill_speed_kmh
        if speed is not None and not (math.isfinite(speed) and speed >= 0):
            raise ValueError(
                f"EstimatorConfig.standstill_speed_kmh must be >= 0 and finite, got {speed!r}"
            )
        if not (
            math.isfinite(self.brake_power_time_constant_s)
            and self.brake_power_time_constant_s >= 0
        ):
            raise ValueError("EstimatorConfig.brake_power_time_constant_s must be >= 0 and finite")
        brake = self.brake_power_w_per_sqrt_s
        if brake is not None:
            if not (math.isfinite(brake) and brake > 0):
                raise ValueError(
                    f"EstimatorConfig.brake_power_w_per_sqrt_s must be positive and finite, "
                    f"got {brake!r}"
                )

    @property
    def manoeuvre_tolerances(self) -> tuple[float, float]:
        """The filter's and the smoother's steady tolerances in the manoeuvre mode, the
        quiet mode's where not set (the kernel's ``manoeuvre_tolerances``)."""
        return (
            self.steady_tolerance
            if self.manoeuvre_steady_tolerance is None
            else self.manoeuvre_steady_tolerance,
            self.smoother_tolerance
            if self.manoeuvre_smoother_tolerance is None
            else self.manoeuvre_smoother_tolerance,
        )


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


# --------------------------------------------------------------------------------------------
# The problem in arrays: what both kernels take


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


def _check_series(series: WagonSeries) -> None:
    who = f"wagon {series.wagon_id!r}" if series.wagon_id else "the series"
    n = series.time_s.size
    if n < 1:
        raise EstimatorInputError(f"{who}: no samples to estimate from")
    for name in ("p_bar", "speed_kmh", "ambient_c", "reading_c"):
        values = getattr(series, name)
        if values.shape != (n,):
            raise EstimatorInputError(
                f"{who}: {name} has {values.size} values, time_s has {n} (one per sample)"
            )
    for name in ("time_s", "p_bar", "speed_kmh", "ambient_c"):
        bad = np.flatnonzero(~np.isfinite(getattr(series, name)))
        if bad.size:
            raise EstimatorInputError(
                f"{who}: {name} is missing or not finite in {bad.size} row(s), the first at "
                f"row {int(bad[0])}; fill gaps in the inputs first"
            )
    negative = np.flatnonzero(series.speed_kmh < 0)
    if negative.size:
        raise EstimatorInputError(
            f"{who}: speed_kmh is negative in row {int(negative[0])} "
            f"({series.speed_kmh[negative[0]]!r})"
        )
    infinite = np.flatnonzero(np.isinf(series.reading_c))
    if infinite.size:
        raise EstimatorInputError(
            f"{who}: reading_c is infinite in row {int(infinite[0])} (NaN marks no reading)"
        )
    steps = np.diff(series.time_s)
    back = np.flatnonzero(steps <= 0)
    if back.size:
        raise EstimatorInputError(
            f"{who}: time_s does not increase at row {int(back[0]) + 1} "
            f"({series.time_s[back[0]]!r} then {series.time_s[back[0] + 1]!r})"
        )


def _grid(
    series: WagonSeries, config: EstimatorConfig
) -> tuple[FloatArray, NDArray[np.bool_], NDArray[np.bool_], dict[str, FloatArray]]:
    """The time grid: logged samples plus the seconds filled into short gaps. Returns the
    grid's times, which rows are logged, which steps are standstill gaps (N-1), and p,
    speed, ambient, reading on the grid (inputs interpolated, readings NaN in the fills)."""
    dt = config.dt_s
    who = f"wagon {series.wagon_id!r}" if series.wagon_id else "the series"
    ticks = (series.time_s - series.time_s[0]) / dt
    whole = np.rint(ticks)
    off = np.flatnonzero(np.abs(ticks - whole) > 1e-6)
    if off.size:
        raise EstimatorInputError(
            f"{who}: time_s at row {int(off[0])} is not a whole number of {dt} s steps from "
            "the first sample"
        )
    tick = whole.astype(np.int64)
    jump = np.diff(tick)
    fill = (jump > 1) & (jump * dt <= config.max_interpolated_gap_s)
    # grid: each logged sample, then the filled seconds after it
    extra = np.where(fill, jump - 1, 0)
    n_grid = tick.size + int(extra.sum())
    pos = np.arange(tick.size) + np.concatenate(([0], np.cumsum(extra)))
    grid_tick = np.empty(n_grid, dtype=np.int64)
    logged = np.zeros(n_grid, dtype=bool)
    logged[pos] = True
    grid_tick[pos] = tick
    for i in np.flatnonzero(fill):
        grid_tick[pos[i] + 1 : pos[i + 1]] = tick[i] + np.arange(1, jump[i])
    values: dict[str, FloatArray] = {}
    for name in ("p_bar", "speed_kmh", "ambient_c"):
        values[name] = np.interp(grid_tick, tick, getattr(series, name))
    reading = np.full(n_grid, np.nan)
    reading[pos] = series.reading_c
    values["reading_c"] = reading
    gap = np.diff(grid_tick) > 1
    return series.time_s[0] + grid_tick * dt, logged, gap, values


def _drive_inputs(
    wagon: WagonConfig,
    rom: ReducedModel,
    dt_s: float,
    p_bar: FloatArray,
    speed_kmh: FloatArray,
    ambient_c: FloatArray,
    h_w_m2k: Mapping[str, float | ArrayLike] | None,
    effects: EffectSet,
    contact_c: FloatArray | None,
) -> DriveInputs:
    """The declared loading at the samples (:func:`fleetbrake.model.timeline.drive_inputs`,
    as ``simulate_timeline`` builds it), the effects applied with the friction face at
    ``contact_c`` (a state-dependent effect's temperature)."""
    base = drive_inputs(
        rom,
        wagon,
        dt_s=dt_s,
        p_bar=p_bar,
        speed_kmh=speed_kmh,
        ambient_c=ambient_c,
        h_w_m2k=h_w_m2k,
    )
    return effects.apply_to_inputs(dataclasses.replace(base, contact_c=contact_c))


@dataclass
class _Transitions:
    """The table of distinct transitions being built (keyed by convection and length)."""

    rom: ReducedModel
    c_probe: FloatArray
    lag_tau_s: float
    tau_p_s: float
    area_m2: float
    gap_sd_k: float = 0.0
    gap_tau_s: float = 1800.0
    offset_var_per_s: float = 0.0
    seat_sd_k: float = 0.0
    seat_tau_s: float = 600.0
    keys: dict[tuple[bytes, int, bool, bool, bool, bool], int] = field(default_factory=dict)
    a: list[FloatArray] = field(default_factory=list)
    gmat: list[FloatArray | None] = field(default_factory=list)
    g: list[FloatArray] = field(default_factory=list)
    diagonal: list[bool] = field(default_factory=list)
    gamma: list[FloatArray] = field(default_factory=list)
    phi: list[float] = field(default_factory=list)
    q_unit: list[float] = field(default_factory=list)
    lag: list[tuple[float, float, FloatArray, float]] = field(default_factory=list)
    q_gap: list[float] = field(default_factory=list)
    q_modes: list[FloatArray] = field(default_factory=list)
    applied: list[bool] = field(default_factory=list)
    braking: list[bool] = field(default_factory=list)
    length_s: list[float] = field(default_factory=list)
    eigen: list[tuple[FloatArray, FloatArray] | None] = field(default_factory=list)
    """Per transition, where it is dense, ``(Q, e)`` with ``a = (Q e) Qᵀ`` as made (the
    convection's operator's ``eigh``); None where it is diagonal."""

    @property
    def seat_error(self) -> bool:
        """Whether the modal state carries the seat's model error as its last coordinate."""
        return self.seat_sd_k > 0

    def get(
        self,
        dh: FloatArray,
        steps: int,
        dt_s: float,
        gap: bool,
        held: bool,
        applied: bool,
        braking: bool = False,
    ) -> int:
        """The transition of a step of ``steps`` samples at convection ``h_nominal + dh``;
        ``gap``: an unlogged standstill; ``held``: the unexplained power neither heats nor
        diffuses over the step (the wheel stands); ``applied``: the cylinder is applied (the
        quiet mode's noise is ``ManoeuvreTest.applied_quiet_w_per_sqrt_s``); ``braking``: the
        declared inputs heat the friction face over the step (the braking's power ``P_b``
        diffuses instead of decaying)."""
        key = (np.ascontiguousarray(dh).tobytes(), steps, gap, held, applied, braking)
        found = self.keys.get(key)
        if found is not None:
            return found
        rom = self.rom
        length_s = steps * dt_s
        r = rom.order
        if np.any(dh != 0.0):
            op = np.diag(rom.lam) + np.tensordot(dh, rom.h_faces, axes=1)
            lam, q = np.linalg.eigh(0.5 * (op + op.T))
            e, g = _ext.rom_exact_propagator(np.ascontiguousarray(lam), float(length_s))
            a = (q * e) @ q.T
            gmat: FloatArray | None = (q * g) @ q.T
            eigen: tuple[FloatArray, FloatArray] | None = (q, e)
            diagonal = False
        else:
            e, g = _ext.rom_exact_propagator(np.ascontiguousarray(rom.lam), float(length_s))
            a = np.diag(e)
            gmat = None
            eigen = None
            diagonal = True
        q_modes = np.zeros(r + int(self.seat_error))
        if self.seat_error:  # the seat error's coordinate: decays, no input, its own noise
            e_b = math.exp(-length_s / self.seat_tau_s)
            a = _pad(a, e_b)
            gmat = None if gmat is None else _pad(gmat, 0.0)
            eigen = None if eigen is None else (_pad(eigen[0], 1.0), np.append(eigen[1], e_b))
            g = np.append(g, 0.0)
            q_modes[r] = self.seat_sd_k**2 * -math.expm1(-2.0 * length_s / self.seat_tau_s)
            r += 1
        if gap or held:
            gamma = np.zeros(r)
        else:
            unit = _modal(rom.b_flux / self.area_m2, r)  # 1 W over the face, modal load
            gamma = unit * g if gmat is None else gmat @ unit
        if held:
            phi, q_unit = 1.0, 0.0
        else:
            phi = math.exp(-length_s / self.tau_p_s)
            q_unit = 0.5 * self.tau_p_s * (1.0 - phi * phi)
        if self.lag_tau_s > 0:
            la = math.exp(-length_s / self.lag_tau_s)
            c = self.lag_tau_s / length_s * (1.0 - la) - la
            b1 = 1.0 - la - c
            lag_row = b1 * (a.T @ self.c_probe) + c * self.c_probe
            lag = (la, b1, lag_row, float(b1 * (self.c_probe @ gamma)))
        else:
            lag = (0.0, 0.0, np.zeros(r), 0.0)
        self.keys[key] = len(self.a)
        self.a.append(a)
        self.gmat.append(gmat)
        self.g.append(np.asarray(g, dtype=np.float64))
        self.diagonal.append(diagonal)
        self.gamma.append(gamma)
        self.phi.append(phi)
        self.q_unit.append(q_unit)
        self.q_gap.append(
            (self.gap_sd_k**2 * -math.expm1(-length_s / self.gap_tau_s) if gap else 0.0)
            + self.offset_var_per_s * length_s
        )
        self.lag.append(lag)
        self.q_modes.append(q_modes)
        self.applied.append(applied)
        self.braking.append(braking)
        self.length_s.append(length_s)
        self.eigen.append(eigen)
        return self.keys[key]

    def eigen_arrays(self) -> tuple[FloatArray, FloatArray] | None:
        """``EstimatorProblem.eigenvectors`` and ``eigenvalues`` of the table (None without a
        dense transition): each dense transition's ``(Q, e)``, a diagonal one's the identity
        and its diagonal."""
        if all(v is None for v in self.eigen):
            return None
        r = self.a[0].shape[0]
        q = np.stack([np.eye(r) if v is None else v[0] for v in self.eigen])
        e = np.stack(
            [np.diag(a) if v is None else v[1] for a, v in zip(self.a, self.eigen, strict=True)]
        )
        return q, e


def _pad(a: FloatArray, corner: float) -> FloatArray:
    """``a`` (r, r) with a row and a column more, ``corner`` where they meet."""
    r = a.shape[0]
    out = np.zeros((r + 1, r + 1))
    out[:r, :r] = a
    out[r, r] = corner
    return out


def _modal(v: FloatArray, r: int) -> FloatArray:
    """A vector over the reduced model's modes as one over ``r`` coordinates (zeros for the
    seat error's)."""
    return v if v.size == r else np.concatenate([v, np.zeros(r - v.size)])


def _held_steps(
    speed_kmh: FloatArray, gap: NDArray[np.bool_], config: EstimatorConfig
) -> NDArray[np.bool_]:
    """Per step (N-1): whether the wheel stands over it, so that the unexplained power
    (friction) is held (:attr:`EstimatorConfig.standstill_speed_kmh`): both bounding samples
    at most that speed, or an unlogged standstill."""
    if config.standstill_speed_kmh is None:
        return np.zeros(gap.size, dtype=bool)
    still = speed_kmh <= config.standstill_speed_kmh
    return gap | (still[:-1] & still[1:])


def _applied_steps(
    p_bar: FloatArray, excluded: NDArray[np.bool_], config: EstimatorConfig
) -> NDArray[np.bool_]:
    """Per step (N-1): whether the cylinder is applied over it
    (:attr:`EstimatorConfig.applied_pressure_bar`): either bounding sample's logged pressure
    above the threshold, and not ``excluded`` (a standstill gap, a held step)."""
    if config.applied_pressure_bar is None:
        return np.zeros(excluded.size, dtype=bool)
    above = p_bar > config.applied_pressure_bar
    return (above[:-1] | above[1:]) & ~excluded


_RESPONSE_BLOCK_STEPS = 1024
"""Steps per block of :func:`_modal_response` on a diagonal problem (a block's two work
arrays stay in the cache: 2 x 1024 x 38 doubles, 0.6 MB; 512-2,048 measured alike)."""


def _modal_response(
    rom: ReducedModel,
    table: _Transitions,
    index: NDArray[np.int64],
    step_flux: FloatArray,
    drive: FloatArray,
    r: int,
) -> FloatArray:
    """The modal response to the declared inputs of each step (N-1, r): the modal load
    ``u = flux b_flux + drive b_faces`` (``drive``: each face's convection times the air's
    offset from ``T_ref``; a zero for the seat error's coordinate) through the step's
    transition, ``g u`` where it is diagonal, ``G u`` where dense.

    With every transition diagonal (``run``'s declared revision) it is computed in blocks
    of :data:`_RESPONSE_BLOCK_STEPS` steps, the same operations on the same numbers row by
    row (the same bits: a test compares), without the four (N-1, r) temporaries of the
    whole series (their memory traffic cost more than the arithmetic)."""
    steps = step_flux.size
    seat = r - rom.order  # 1: the seat error's coordinate (no input), else 0
    g_all = np.stack(table.g) if table.g else np.zeros((0, r))
    if steps == 0:
        return np.zeros((0, r))
    if all(table.diagonal):
        w = np.empty((steps, r))
        block = min(steps, _RESPONSE_BLOCK_STEPS)
        u = np.empty((block, r))
        g = np.empty((block, r))
        if seat:
            u[:, rom.order :] = 0.0
        for a in range(0, steps, block):
            b = min(a + block, steps)
            m = b - a
            load = u[:m, : rom.order]
            np.multiply(step_flux[a:b, None], rom.b_flux[None, :], out=load)
            load += drive[a:b] @ rom.b_faces
            np.take(g_all, index[a:b], axis=0, out=g[:m])
            np.multiply(u[:m], g[:m], out=w[a:b])
        return w
    u = step_flux[:, None] * rom.b_flux[None, :] + drive @ rom.b_faces
    if seat:
        u = np.concatenate([u, np.zeros((u.shape[0], 1))], axis=1)
    w = u * g_all[index]
    dense = np.flatnonzero(~np.array(table.diagonal, dtype=bool))
    if dense.size:
        # each dense transition's steps, ascending (a stable sort of the steps by transition,
        # cut where the transition changes): the rows ``index == k`` selects, found once
        # instead of a scan of the whole series per transition (a speed-varying convection
        # has a hundred and more)
        order = np.argsort(index, kind="stable")
        bounds = np.searchsorted(index[order], np.arange(len(table.diagonal) + 1))
        for k in dense:
            gmat = table.gmat[k]
            rows = order[bounds[k] : bounds[k + 1]]
            assert gmat is not None
            w[rows] = u[rows] @ gmat.T
    return w


def _codes(column: FloatArray) -> tuple[FloatArray, NDArray[np.int64]]:
    """``np.unique(column, return_inverse=True)``, without its sort for a constant column
    (a face's convection at its nominal value throughout: every step of ``run``'s declared
    revision)."""
    if column.size and bool(np.all(column == column[0])):
        return column[:1].copy(), np.zeros(column.size, dtype=np.int64)
    return np.unique(column, return_inverse=True)


def prepare(
    rom: ReducedModel,
    wagon: WagonConfig,
    series: WagonSeries,
    *,
    effects: EffectSet = EffectSet(),  # noqa: B008 (immutable)
    config: EstimatorConfig = EstimatorConfig(),
    h_w_m2k: Mapping[str, float | ArrayLike] | None = None,
    contact_c: ArrayLike | None = None,
) -> EstimatorProblem:
    """The filtering problem of one wagon's series under a model revision (``rom`` and
    ``effects``; ``h_w_m2k`` the declared convection, None: the reduced model's nominal, as
    in ``simulate_timeline``). ``contact_c`` (one per logged sample) feeds state-dependent
    effects (:func:`estimate_contact` iterates on it)."""
    _check_series(series)
    dt = config.dt_s
    grid_t, logged, gap, values = _grid(series, config)
    n = grid_t.size
    contact: FloatArray | None = None
    if contact_c is not None:
        logged_contact = np.asarray(contact_c, dtype=np.float64).reshape(-1)
        if logged_contact.size != series.time_s.size:
            raise EstimatorInputError(
                f"wagon {series.wagon_id!r}: contact_c has {logged_contact.size} values, "
                f"expected {series.time_s.size}"
            )
        contact = np.interp(grid_t, grid_t[logged], logged_contact)
    inputs = _drive_inputs(
        wagon,
        rom,
        dt,
        values["p_bar"],
        values["speed_kmh"],
        values["ambient_c"],
        h_w_m2k,
        effects,
        contact,
    )
    # the same samples at standstill (what a sleeping unit's wagon does in a long gap)
    still = _drive_inputs(
        wagon,
        rom,
        dt,
        np.zeros(n),
        np.zeros(n),
        values["ambient_c"],
        h_w_m2k,
        effects,
        contact,
    )
    reading = values["reading_c"]
    valid = np.flatnonzero(np.isfinite(reading))
    t_ref = float(reading[valid[0]]) if valid.size else float(values["ambient_c"][0])
    faces = rom.face_names
    unknown = set(inputs.h_w_m2k) - set(faces)
    if unknown:
        raise EstimatorInputError(
            f"wagon {series.wagon_id!r}: convection for unknown face set(s) {sorted(unknown)}; "
            f"the reduced model has {faces}"
        )

    def per_face(drive: DriveInputs) -> FloatArray:
        return np.stack(
            [np.asarray(drive.h_w_m2k.get(f, np.zeros(n)), dtype=np.float64) for f in faces],
            axis=1,
        )

    h_samples = per_face(inputs)
    h_still = per_face(still)
    if np.any(~np.isfinite(h_samples)) or np.any(h_samples < 0):
        raise EstimatorInputError(
            f"wagon {series.wagon_id!r}: convection coefficients must be finite and >= 0"
        )
    # per step: the mean of the two bounding samples; at standstill gaps the still inputs
    step_flux = 0.5 * (inputs.flux_w_m2[:-1] + inputs.flux_w_m2[1:])
    step_amb = 0.5 * (inputs.ambient_c[:-1] + inputs.ambient_c[1:])
    step_h = 0.5 * (h_samples[:-1] + h_samples[1:])
    still_amb = 0.5 * (still.ambient_c[:-1] + still.ambient_c[1:])
    still_h = 0.5 * (h_still[:-1] + h_still[1:])
    step_flux = np.where(gap, 0.0, step_flux)
    step_amb = np.where(gap, still_amb, step_amb)
    step_h = np.where(gap[:, None], still_h, step_h)
    for j in range(len(faces)):  # a varying coefficient is quantised (as the timeline does)
        column = step_h[:, j]
        if column.size and np.any(column != column[0]):
            step_h[:, j] = np.round(column / H_QUANTUM_W_M2K) * H_QUANTUM_W_M2K
    if not np.all(np.isfinite(step_flux)) or not np.all(np.isfinite(step_amb)):
        raise EstimatorInputError(f"wagon {series.wagon_id!r}: heat input or ambient not finite")
    h_nom = np.array([rom.h_nominal.get(f, 0.0) for f in faces])
    dh = np.round(step_h - h_nom, 12)
    steps_of = np.rint(np.diff(grid_t) / dt).astype(np.int64)
    lag_effect = effects.get("sensor_lag")
    lag_tau = lag_effect.tau_s if isinstance(lag_effect, SensorLag) else 0.0
    seat_error = config.seat_error_sd_k > 0
    r = rom.order + int(seat_error)  # the modal coordinates: the modes, the seat's error
    # the sensor seat: the first probe (output rows: probes, mean, nodes), plus its error
    c_probe = np.append(rom.c_out[0], 1.0) if seat_error else rom.c_out[0]
    table = _Transitions(
        rom=rom,
        c_probe=c_probe,
        lag_tau_s=float(lag_tau),
        tau_p_s=config.power_time_constant_s,
        area_m2=wagon.geometry.contact_area_m2,
        gap_sd_k=config.gap_offset_sd_k,
        gap_tau_s=config.gap_offset_time_constant_s,
        offset_var_per_s=config.model_offset_sd_k_per_sqrt_s**2,
        seat_sd_k=config.seat_error_sd_k,
        seat_tau_s=config.seat_error_time_constant_s,
    )
    held = _held_steps(values["speed_kmh"], gap, config)
    applied = _applied_steps(values["p_bar"], gap | held, config)
    # the steps whose declared friction heat is not zero (where the braking's power P_b lives)
    braking = (
        (step_flux > 0.0) & ~(gap | held)
        if config.brake_power_w_per_sqrt_s is not None
        else np.zeros(gap.size, dtype=bool)
    )
    # one transition per distinct (convection, length, standstill gap, power held, cylinder
    # applied): integer codes per column, then one key per step (sorting floats row by row
    # is slow)
    codes = [_codes(column) for column in dh.T]
    key = (((np.rint(steps_of).astype(np.int64) * 2 + gap) * 2 + held) * 2 + applied) * 2 + braking
    for distinct, inverse_f in codes:
        key = key * max(distinct.size, 1) + inverse_f.reshape(-1)
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    ids = np.array(
        [
            table.get(
                dh[i],
                int(steps_of[i]),
                dt,
                bool(gap[i]),
                bool(held[i]),
                bool(applied[i]),
                bool(braking[i]),
            )
            for i in first
        ],
        dtype=np.int64,
    )
    index = ids[inverse.reshape(-1)] if n > 1 else np.zeros(0, dtype=np.int64)
    w = _modal_response(rom, table, index, step_flux, step_h * (step_amb - t_ref)[:, None], r)
    lag = lag_tau > 0
    brake = config.brake_power_w_per_sqrt_s is not None
    n_state = r + 1 + int(lag) + int(brake)
    # prior: a uniform offset of the whole block (and of the lagged reading); the seat's
    # error at its stationary distribution
    b_air = h_nom @ rom.b_faces
    uniform = np.zeros(n_state)
    uniform[: rom.order] = np.divide(b_air, rom.lam, out=np.zeros(rom.order), where=rom.lam > 0)
    if lag:
        uniform[r + 1] = 1.0
    sd0 = config.initial_temperature_sd_k
    cov0 = sd0 * sd0 * np.outer(uniform, uniform)
    if seat_error:
        cov0[r - 1, r - 1] = config.seat_error_sd_k**2
    lag_rows = table.lag
    eigen = table.eigen_arrays()
    # the declared braking power of each step (W into the block), its share of the noise
    # (none at all with the option off: no array of zeros per wagon-second to build and ship)
    gain = config.declared_power_noise_per_sqrt_s
    power_noise = (
        np.where(held | gap, 0.0, (gain * step_flux * wagon.geometry.contact_area_m2) ** 2)
        if gain > 0.0
        else None
    )
    # the braking's power P_b: a random walk while braking, decaying otherwise
    brake_phi: FloatArray | None = None
    brake_q: FloatArray | None = None
    if config.brake_power_w_per_sqrt_s is not None:
        on = np.array(table.braking, dtype=bool)
        length = np.array(table.length_s, dtype=np.float64)
        tau_b = config.brake_power_time_constant_s
        brake_phi = np.where(on, 1.0, np.exp(-length / tau_b) if tau_b > 0 else 0.0)
        brake_q = np.where(on, config.brake_power_w_per_sqrt_s**2 * length, 0.0)
    return EstimatorProblem(
        wagon_id=series.wagon_id,
        order=r,
        lag=lag,
        t_ref_c=t_ref,
        time_s=grid_t,
        logged=logged,
        reading_c=reading,
        index=index,
        w=np.ascontiguousarray(w),
        a=np.stack(table.a) if table.a else np.zeros((0, r, r)),
        diagonal=np.array(table.diagonal, dtype=bool),
        gamma=np.stack(table.gamma) if table.gamma else np.zeros((0, r)),
        phi=np.array(table.phi),
        q_unit=np.array(table.q_unit),
        lag_a=np.array([v[0] for v in lag_rows]),
        lag_b1=np.array([v[1] for v in lag_rows]),
        lag_row=np.stack([v[2] for v in lag_rows]) if lag_rows else np.zeros((0, r)),
        lag_power=np.array([v[3] for v in lag_rows]),
        c_probe=np.ascontiguousarray(c_probe),
        c_mean=np.ascontiguousarray(_modal(rom.c_out[rom.n_probes], r)),
        c_nodes=np.ascontiguousarray(
            np.pad(rom.c_out[rom.n_probes + 1 :], ((0, 0), (0, r - rom.order)))
        ),
        x0=np.zeros(n_state),
        cov0=cov0,
        p_prior_unit=0.5 * config.power_time_constant_s,
        q_gap=np.array(table.q_gap, dtype=np.float64),
        gap_dir=uniform,
        held=held,
        q_modes=np.stack(table.q_modes) if table.q_modes else np.zeros((0, r)),
        applied=np.array(table.applied, dtype=bool),
        power_noise=power_noise,
        brake_phi=brake_phi,
        brake_q=brake_q,
        eigenvectors=None if eigen is None else eigen[0],
        eigenvalues=None if eigen is None else eigen[1],
    )


# --------------------------------------------------------------------------------------------
# The kernels' outputs


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
    """Rust kernel: seconds whose covariance step replayed a recorded excursion from a steady
    state (the same numbers as computing it; the numpy reference computes every one)."""
    manoeuvre: NDArray[np.bool_] | None = None
    """Whether the step into each second used the manoeuvre mode's σ_w."""
    manoeuvre_steps: int = 0


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
    manoeuvre: ManoeuvreTest = ManoeuvreTest(),
    dt_s: float = 1.0,
    forced_modes: NDArray[np.bool_] | None = None,
    manoeuvre_tolerances: tuple[float, float] | None = None,
) -> KernelOutputs:
    """The filter (and smoother) in plain numpy: dense matrices, one step at a time, the
    same algorithm as the Rust kernel (the same steady-state freezing, the same test between
    the power noise's modes, the same second pass for the smoother on the led modes), its
    reference. ``forced_modes``: the power noise's mode of each step, instead of the test's.
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


# --------------------------------------------------------------------------------------------
# The Rust kernel


def rust_available() -> bool:
    """Whether the extension has the estimator kernel (``engine="rust"``)."""
    return hasattr(_ext, "estimator_run")


def _run_rust(
    problems: Sequence[EstimatorProblem],
    noise: EstimatorNoise,
    *,
    smooth: bool,
    config: EstimatorConfig,
    outputs: bool,
) -> list[KernelOutputs]:
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


def _run(
    problems: Sequence[EstimatorProblem],
    noise: EstimatorNoise,
    *,
    smooth: bool,
    config: EstimatorConfig,
    engine: Engine | None,
    outputs: bool = True,
) -> list[KernelOutputs]:
    chosen = engine or ("rust" if rust_available() else "numpy")
    if chosen == "rust":
        if not rust_available():
            raise EstimatorInputError(
                "engine 'rust': this build of fleetbrake._ext has no estimator kernel"
            )
        return _run_rust(problems, noise, smooth=smooth, config=config, outputs=outputs)
    if chosen != "numpy":
        raise EstimatorInputError(f"unknown engine {chosen!r}; use 'rust' or 'numpy'")
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


# --------------------------------------------------------------------------------------------
# Estimates per logged second


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
    """Rust kernel: share of the seconds whose covariance step replayed a recorded excursion
    from a steady state (the second fast path; numpy: 0)."""
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
    config: EstimatorConfig = EstimatorConfig(),
    smooth: bool = True,
    engine: Engine | None = None,
) -> list[ContactEstimate]:
    """Filter (and smooth) prepared problems with ``config.noise``: the Rust kernel (wagons
    in parallel) when the extension has it, else (or with ``engine="numpy"``) numpy."""
    raws = _run(problems, config.noise, smooth=smooth, config=config, engine=engine)
    return [_estimate_of(p, raw, config.noise) for p, raw in zip(problems, raws, strict=True)]


def estimate_contact(
    rom: ReducedModel,
    wagon: WagonConfig,
    series: WagonSeries,
    *,
    effects: EffectSet = EffectSet(),  # noqa: B008 (immutable)
    config: EstimatorConfig = EstimatorConfig(),
    h_w_m2k: Mapping[str, float | ArrayLike] | None = None,
    smooth: bool = True,
    engine: Engine | None = None,
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
        result = estimate([problem], config=config, smooth=smooth and not iterate, engine=engine)[0]
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
    return estimate([problem], config=config, smooth=True, engine=engine)[0] if smooth else result


# --------------------------------------------------------------------------------------------
# Noise by maximum likelihood


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
    config: EstimatorConfig = EstimatorConfig(),
    min_power_noise_w_per_sqrt_s: float = 3.0,
    max_power_noise_w_per_sqrt_s: float = 1.0e4,
    measurement_range_k: tuple[float, float] = (1e-3, 10.0),
    engine: Engine | None = None,
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
            engine,
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
        raws = _run(problems, noise, smooth=False, config=config, engine=engine, outputs=False)
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
    engine: Engine | None,
    tolerance: float,
    readings: int,
) -> NoiseFit:
    """σ_w alone by maximum likelihood, σ_v fixed (:func:`fit_noise`).

    The likelihood is taken as unimodal in ``log σ_w`` (the bounded search assumes it too):
    the floor ``lo`` and one ``tolerance`` above it are evaluated first, and when the floor
    is at least as likely the maximum lies within that step of it, so the floor is the
    answer to the search's own tolerance (two filter passes instead of the search's ~17;
    the revisions the close loop makes end there). Otherwise the bounded search over
    ``lo`` .. ``hi``, as before, and the floor when it is as likely as the search's best
    (the search never evaluates the bound itself)."""
    from scipy.optimize import minimize_scalar

    if not (math.isfinite(measurement_k) and measurement_k > 0):
        raise ValueError(f"fit_noise: measurement_k must be positive, got {measurement_k!r}")
    evaluations = 0

    def negative_loglik(z: float) -> float:
        nonlocal evaluations
        evaluations += 1
        noise = EstimatorNoise(measurement_k, float(np.exp(np.clip(z, lo, hi))), None)
        raws = _run(problems, noise, smooth=False, config=config, engine=engine, outputs=False)
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
    ``closeloop.selection.noise_from_residual``, on the reading instead of a residual. None
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
