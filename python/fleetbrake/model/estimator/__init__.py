"""The virtual sensor: the wheel-block contact temperature every second, with its uncertainty.

A Kalman filter and a Rauch-Tung-Striebel smoother (in the modified Bryson-Frazier form,
which needs no matrix inverse) on the reduced model's state, fed with the declared heat input
of each second and updated with each valid thermistor reading; the heat that the declared inputs do not explain is estimated as
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
* Options (off by default: they cost speed,
  ``docs/decisions/0002-estimator-noise.md``): ``P`` held at standstill, friction
  heating only while the wheel turns (``standstill_speed_kmh``: over such a step and over an
  unlogged standstill ``γ = 0``, ``φ = 1``, no noise, and 0 W reported);
  ``b' = φ_b b + η``, the reduced model's own error at the sensor seat (``seat_error_sd_k``,
  a Gauss-Markov process, a coordinate appended to ``ξ`` that the face does not see).

**Measurement.** ``y = T_seat (+ b) + v`` (or ``s + v`` with a lag, ``s`` lagging
``T_seat (+ b)``), ``var v = σ_v²``; a missing or faulty reading (NaN) skips the update.

**Noise.** ``σ_v`` and ``σ_w`` are estimated together by maximum likelihood on the
innovations (:func:`fit_noise`): ``log L = -1/2 Σ (log 2π S_n + ν_n²/S_n)`` over the readings
of the fit data, maximised over ``(log σ_v, log σ_w)`` by Nelder-Mead. ``σ_w`` has a floor
(``min_power_noise_w_per_sqrt_s``, 3 W/√s by default): on data where nothing unexplained
happens the likelihood keeps rising as ``σ_w`` falls, and a filter tuned that way is
overconfident when a dragging brake comes (at 1 W/√s the band holds the truth for 81-91 % of
a day with drags, at 3 W/√s for 90-96 %; ``docs/estimator.md``, "How each noise is set").

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
"How each noise is set", and ``docs/decisions/0002-estimator-noise.md``).

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
state found again for the same key within the tolerance is the one found before, and the
kernel replays a recorded excursion from it (a missing reading and the seconds after) instead
of computing it again: the same numbers. The Rust kernel does this with structured
(diagonal-plus-border) propagators and bounded memory; the tests hold a plain numpy
implementation of the same algorithm (dense matrices, one step at a time) as its reference.

**Modules.** :mod:`~fleetbrake.model.estimator.config` (the settings),
:mod:`~fleetbrake.model.estimator.problem` (the series and the problem's arrays),
:mod:`~fleetbrake.model.estimator.grid` (the series on its time grid),
:mod:`~fleetbrake.model.estimator.transitions` (the distinct transitions and the declared
inputs' response), :mod:`~fleetbrake.model.estimator.prepare` (the problem of a series),
:mod:`~fleetbrake.model.estimator.kernel` (the Rust kernel's call),
:mod:`~fleetbrake.model.estimator.estimates` (the estimates per logged second) and
:mod:`~fleetbrake.model.estimator.noise` (the noise by maximum likelihood).
"""

from fleetbrake.model.estimator.config import EstimatorConfig, EstimatorNoise, ManoeuvreTest
from fleetbrake.model.estimator.estimates import ContactEstimate, estimate, estimate_contact
from fleetbrake.model.estimator.kernel import Kernel, KernelOutputs, run_kernel, rust_available
from fleetbrake.model.estimator.noise import (
    NoiseFit,
    fit_noise,
    measurement_noise,
    noise_from_second_differences,
)
from fleetbrake.model.estimator.prepare import prepare
from fleetbrake.model.estimator.problem import (
    Z95,
    EstimatorInputError,
    EstimatorProblem,
    WagonSeries,
)

__all__ = [
    "Z95",
    "ContactEstimate",
    "EstimatorConfig",
    "EstimatorInputError",
    "EstimatorNoise",
    "EstimatorProblem",
    "Kernel",
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
    "run_kernel",
    "rust_available",
]
