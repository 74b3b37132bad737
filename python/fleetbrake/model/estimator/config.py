"""The estimator's settings: the noise (:class:`EstimatorNoise`), the test between the
power noise's quiet and manoeuvre modes (:class:`ManoeuvreTest`) and everything else the
filter and smoother are set with (:class:`EstimatorConfig`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

__all__ = ["EstimatorConfig", "EstimatorNoise", "ManoeuvreTest"]


@dataclass(frozen=True)
class EstimatorNoise:
    """The noise of the virtual sensor's filter: σ_v and σ_w, which :func:`fit_noise`
    estimates, and the quiet mode's σ_q.

    Read by: ``fleetbrake run``, ``fleetbrake watch``, ``fleetbrake close-loop``."""

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
    (``docs/estimator.md``, "How each noise is set"; the sweep behind it:
    ``docs/decisions/0002-estimator-noise.md``); None: one mode, σ_w at every second."""

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
    white again, the power is not zero). ``docs/estimator.md``, "Two modes of the power's
    noise", has the evidence.

    Read by: ``fleetbrake run``, ``fleetbrake watch``, ``fleetbrake close-loop``."""

    window_s: float = 120.0
    """The window of the innovations' exponentially weighted mean ``m``, s."""
    on_sigma: float = 5.0
    """The manoeuvre mode starts where ``|m|`` exceeds this many of its standard deviations."""
    off_sigma: float = 1.0
    """The manoeuvre mode holds while ``|m|`` exceeds this many of its standard deviations: with
    σ_q 0.03 the band shrinks to ±0.05 K within a minute of the switch-off, so the mode holds
    until the innovations are white (0.823 of the truth in the filtered band after a drag,
    0.784 at 2 σ: ``docs/decisions/0002-estimator-noise.md``)."""
    hold_power_sigma: float = 2.0
    """... or while the estimated power is more than this many of its standard deviations from
    zero."""
    smoother_lead_s: float = 120.0
    """The smoother's mode sequence: the filter's, with the manoeuvre mode begun this long
    before each switch-on (the test switches a window or so after a step of the power; the
    smoother, which sees the whole series, lets the power step where it did). Where that
    changes the sequence, the smoother runs on a second forward pass with it; the filter and
    its reported modes are unchanged. Counted in steps (``smoother_lead_s / dt_s``), as the
    window is. 0: the filter's sequence. 120 s by default: with σ_q 0.03 the smoother without
    it spreads a drag's onset over the half hour before it (``docs/estimator.md``, "Two modes
    of the power's noise")."""
    applied_quiet_w_per_sqrt_s: float | None = None
    """The quiet mode's diffusion over a step with the cylinder applied
    (:attr:`EstimatorConfig.applied_pressure_bar`), W/√s: a braking's heat depends on the
    logged pressure's scale, whose error (0.4 % on the synthetic fleets) acts only while the
    cylinder is applied. None: σ_q there as elsewhere (why it is off:
    ``docs/decisions/0002-estimator-noise.md``)."""

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


@dataclass(frozen=True)
class EstimatorConfig:
    """Everything the estimator is set with (the noise usually from :func:`fit_noise`).

    Read by: ``fleetbrake run``, ``fleetbrake watch``, ``fleetbrake close-loop``."""

    noise: EstimatorNoise = field(default_factory=EstimatorNoise)
    """σ_v, σ_w and σ_q (the estimation stage replaces σ_v and σ_w with the wagon's and the
    revision's)."""
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
    smoothed band is narrower than that error (``docs/estimator.md``, "The state-space
    model"). 1.5 mK/√s with the
    other defaults; 0: the model is exact."""
    steady_tolerance: float = 1e-3
    """The filter's covariance counts as steady when no element changed in a step by more
    than this times ``sqrt(Σ_ii Σ_jj)`` (0: only when unchanged), in the quiet mode (the
    manoeuvre mode's: ``manoeuvre_steady_tolerance``). After each braking's release the
    covariance settles at the closed loop's slowest rate (the slowest modes' variances;
    median 1,212 s to pass 1e-7, 361 s to pass 1e-3, on 95 releases of 4 bench wagon-days),
    so 1e-3 keeps about two thirds of the seconds steady where 1e-7 keeps one in seven. At
    1e-3 (with ``smoother_tolerance`` 1e-3) against 1e-7 / 1e-5, on 8 bench wagon-days: the
    filtered mean moves by at most 4.2 mK, its sd by 2.2 mK, the power by 71 mW, the smoothed
    by 2.2 mK, 1.5 mK and 53 mW; every acceptance bar is met on seeds 3, 4 and 5
    (``docs/decisions/0001-estimator-covariance-path.md``)."""
    smoother_tolerance: float = 1e-3
    """The same for the smoother's information matrix, which only the smoothed standard
    deviations use (the smoothed means do not depend on it), in the quiet mode (the manoeuvre
    mode's: ``manoeuvre_smoother_tolerance``). At 1e-3 the smoother's matrix is frozen in
    54 % of the seconds, at 1e-5 in 5 % (figures at ``steady_tolerance``)."""
    manoeuvre_steady_tolerance: float | None = 1e-7
    """``steady_tolerance`` for the steps in the manoeuvre mode (their keys and steady states
    are their own); None: ``steady_tolerance`` there too. In the manoeuvre mode the power's
    variance moves fast and the estimates follow it: on 4 bench wagon-days with an unexplained
    2 K rise of the reading, 1e-3 there moves the filtered mean by up to 0.103 K and the
    smoothed by 68 mK against 1e-7 / 1e-5, while 1e-7 / 1e-5 there (the quiet mode at 1e-3)
    moves the smoothed mean by at most 3.3 mK, at the same speed (1.3 % of those seconds are
    in the manoeuvre mode; ``docs/decisions/0001-estimator-covariance-path.md``). An exact
    recursion sets it, ``manoeuvre_smoother_tolerance`` and the two quiet ones to 0."""
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
    default: it costs speed (stops break the steady state) and does not meet every
    acceptance bar alone (``docs/decisions/0002-estimator-noise.md``)."""
    seat_error_sd_k: float = 0.0
    """The reduced model's error at the sensor seat as a coordinate of its own (``b``, a
    Gauss-Markov process of this stationary standard deviation, K, read as
    ``y = T_seat + b + v``): the reduced model is not the block, and where the two differ at
    the seat (0.1-0.2 K in a hard braking on the full-FE fleets) they need not differ on the
    face; without ``b`` such a mismatch moves the face's estimate (through ``P`` and the
    offset) where the open-loop prediction is right. 0 (the default): no such coordinate.
    0.05 K with ``seat_error_time_constant_s`` 600 s meets the smoothed-RMSE bar on the
    full-FE acceptance fleets, but the covariance then settles about half as often (the
    kernel 45 % slower per CPU-second; ``docs/decisions/0002-estimator-noise.md``)."""
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
    0: none (why it is off: ``docs/decisions/0002-estimator-noise.md``)."""
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
    sensor's error followed within 20 %; below 0.2 it is not); None: no such state (faster;
    ``docs/estimator.md``, "The state-space model"; the choice:
    ``docs/decisions/0002-estimator-noise.md``)."""
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
