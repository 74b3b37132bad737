"""One wagon's time series in, block temperatures out: the one simulation of the pipeline.

::

    from fleetbrake.model.effects import EffectSet, SensorLag
    from fleetbrake.model.rom import ReducedModel
    from fleetbrake.model.timeline import simulate_timeline

    rom = ReducedModel.for_wagon(wagon)
    result = simulate_timeline(
        rom, wagon, dt_s=1.0, p_bar=p, speed_kmh=v, ambient_c=10.0, initial_c=23.0,
        effects=EffectSet((SensorLag(tau_s=40.0),)),
    )
    result.sensor_c, result.contact_mean_c, result.contact_max_c   # N values, at the samples

What it does, from N samples at ``t_k = k dt``:

1. **Force.** The block force of the declared chain (``physics.block_force_n``) at each
   sample, times ``brake_efficiency`` (a weak brake: < 1), plus ``drag_force_n`` (a dragging
   brake: force with no cylinder pressure). Scalars or per-sample series.
2. **Heat input.** ``Phi_b(t_k) = (1 - alpha) mu F(t_k) v(t_k) / A_contact`` (block-model.md,
   time-resolved), the declared convection (nominal, or ``h_w_m2k``) and the ambient, at the
   samples; the effects change them where they act (:class:`fleetbrake.model.effects.DriveInputs`).
3. **Steps.** Step n (on [t_n, t_n+1]) takes the mean of its two bounding samples: for the
   flux this is the trapezoid of ``physics.time_resolved_flux_series_w_m2``, so with no
   effect the model is driven by exactly that series. A convection coefficient that varies
   in time is rounded to ``H_QUANTUM_W_M2K`` (the reduced model computes one propagator per
   distinct value).
4. **Integration.** The reduced model, exact for inputs held over each step; the sensor
   output passes through the sensor effects (a lag).
5. **State-dependent effects** (friction fade with the face temperature): fixed-point
   iteration, the face temperature of one pass feeding the heat input of the next, until the
   sensor series changes by less than ``tol_k`` (``iterations`` says how many passes).

Nothing is guessed: a NaN or negative speed, a NaN pressure or ambient is an error (fill
short gaps first, e.g. with ``physics.fill_short_gaps``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake.errors import FleetbrakeError
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import DriveInputs, EffectSet
from fleetbrake.model.physics import (
    KMH_TO_M_S,
    block_flux_w_m2,
    block_force_n,
    frictional_flux_w_m2,
    heat_partition_alpha,
)
from fleetbrake.model.rom import ReducedModel

__all__ = [
    "H_QUANTUM_W_M2K",
    "FixedPointError",
    "TimelineResult",
    "drive_inputs",
    "simulate_timeline",
]

FloatArray = NDArray[np.float64]

H_QUANTUM_W_M2K = 0.25
"""Resolution to which a time-varying convection coefficient is rounded: the reduced model
diagonalises its operator once per distinct value (a few hundred at most this way). The
rounding is unbiased; it changes temperatures by far less than the sensor's noise, but makes a
result a step function of a convection parameter on this scale (mind it when fitting with
finite differences: use steps that move h by more than this)."""


class FixedPointError(FleetbrakeError, RuntimeError):
    """A state-dependent effect whose fixed-point iteration did not converge."""


@dataclass(frozen=True)
class TimelineResult:
    """The simulated block: N values at the sample instants unless said otherwise."""

    time_s: FloatArray
    sensor_c: FloatArray
    """What the thermistor reads (noise-free): the seat temperature after sensor effects."""
    seat_c: FloatArray
    """Block temperature at the sensor seat."""
    contact_mean_c: FloatArray
    """Mean temperature of the friction face (the wheel-block interface)."""
    contact_max_c: FloatArray
    """Maximum temperature over the friction face."""
    sample_flux_w_m2: FloatArray
    """Heat flux into the block at each sample, effects included."""
    flux_w_m2: FloatArray
    """Heat flux of each step (N - 1 values, step n on [t_n, t_n+1]) as integrated."""
    block_force_n: FloatArray
    """Normal force of one block on the wheel (anomalies included)."""
    final_state: FloatArray | None
    """The reduced model's state after the last step (``initial_state`` of a continuation
    with the same ``initial_c``); None when ``keep_state=False`` took the batch kernel."""
    iterations: int
    """Simulation passes (1 unless an effect depends on the state)."""
    contact_area_m2: float

    @property
    def heat_input_j(self) -> float:
        """Heat that entered the block's friction face: sum of step flux x area x dt."""
        dt_s = float(self.time_s[1] - self.time_s[0]) if self.time_s.size > 1 else 0.0
        return float(np.sum(self.flux_w_m2) * self.contact_area_m2 * dt_s)


def _samples(name: str, value: ArrayLike, n: int) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        return np.full(n, float(arr))
    arr = arr.reshape(-1)
    if arr.size != n:
        raise ValueError(f"{name} has {arr.size} values, expected {n} (one per sample)")
    return arr


def _step_mean(samples: FloatArray) -> FloatArray:
    return 0.5 * (samples[:-1] + samples[1:])


def _check_finite(name: str, values: FloatArray) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{name}: {int(bad.sum())} missing or non-finite value(s), the first at sample "
            f"{first}; fill gaps before simulating"
        )


def simulate_timeline(
    rom: ReducedModel,
    wagon: WagonConfig,
    *,
    dt_s: float,
    p_bar: ArrayLike,
    speed_kmh: ArrayLike,
    ambient_c: float | ArrayLike,
    initial_c: float,
    effects: EffectSet = EffectSet(),  # noqa: B008 (immutable)
    drag_force_n: float | ArrayLike | None = None,
    brake_efficiency: float | ArrayLike = 1.0,
    initial_state: ArrayLike | None = None,
    h_w_m2k: Mapping[str, float | ArrayLike] | None = None,
    keep_state: bool = True,
    tol_k: float = 1.0e-4,
    max_iterations: int = 30,
) -> TimelineResult:
    """Simulate a wagon's block over N samples (see the module docstring).

    ``p_bar`` (gauge) and ``speed_kmh`` are N-long series; ``ambient_c``, ``drag_force_n``
    and ``brake_efficiency`` a number or N-long; ``h_w_m2k`` the declared convection per face
    set, numbers or N-long (None: the reduced model's nominal; a mapping replaces it whole, as
    in ``ReducedModel.simulate``: a face set it does not name has none). ``initial_c`` is the uniform
    starting temperature (and the reference of ``initial_state``). ``keep_state=False`` lets a
    run at constant nominal convection from a uniform start use the reduced model's batch
    kernel (faster; no ``final_state``).
    """
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt_s must be positive and finite, got {dt_s!r}")
    pressure = np.asarray(p_bar, dtype=np.float64).reshape(-1)
    n = pressure.size
    if n < 2:
        raise ValueError(f"need at least two samples, got {n}")
    speed = _samples("speed_kmh", speed_kmh, n)
    _check_finite("p_bar", pressure)
    _check_finite("speed_kmh", speed)
    if np.any(speed < 0):
        raise ValueError("speed_kmh must be >= 0")
    if not np.isfinite(initial_c):
        raise ValueError(f"initial_c must be finite, got {initial_c!r}")
    ambient = _samples("ambient_c", ambient_c, n)
    _check_finite("ambient_c", ambient)

    base = drive_inputs(
        rom,
        wagon,
        dt_s=dt_s,
        p_bar=pressure,
        speed_kmh=speed,
        ambient_c=ambient,
        drag_force_n=drag_force_n,
        brake_efficiency=brake_efficiency,
        h_w_m2k=h_w_m2k,
    )
    force = base.block_force_n

    contact: FloatArray | None = None
    previous: FloatArray | None = None
    iterations = 0
    while True:
        iterations += 1
        inputs = effects.apply_to_inputs(base.replace(contact_c=contact))
        sim = _integrate(rom, inputs, initial_c, initial_state, keep_state)
        seat = sim[0]
        sensor = effects.apply_to_sensor(seat, float(dt_s))
        if not effects.state_dependent:
            break
        if previous is not None and float(np.max(np.abs(sensor - previous))) < tol_k:
            break
        if iterations >= max_iterations:
            change = float(np.max(np.abs(sensor - previous))) if previous is not None else np.inf
            raise FixedPointError(
                f"{effects}: the sensor series still changed by {change:.3g} K after "
                f"{iterations} passes (tolerance {tol_k} K)"
            )
        previous = sensor
        contact = sim[1]
    _, face_mean, face_max, step_flux, final_state = sim
    return TimelineResult(
        time_s=np.arange(n, dtype=np.float64) * float(dt_s),
        sensor_c=sensor,
        seat_c=seat,
        contact_mean_c=face_mean,
        contact_max_c=face_max,
        sample_flux_w_m2=inputs.flux_w_m2,
        flux_w_m2=step_flux,
        block_force_n=force,
        final_state=final_state,
        iterations=iterations,
        contact_area_m2=wagon.geometry.contact_area_m2,
    )


def drive_inputs(
    rom: ReducedModel,
    wagon: WagonConfig,
    *,
    dt_s: float,
    p_bar: FloatArray,
    speed_kmh: FloatArray,
    ambient_c: FloatArray,
    drag_force_n: float | ArrayLike | None = None,
    brake_efficiency: float | ArrayLike = 1.0,
    h_w_m2k: Mapping[str, float | ArrayLike] | None = None,
) -> DriveInputs:
    """Steps 1 and 2 of the module docstring: the declared loading at the N samples, before
    the effects (``p_bar``, ``speed_kmh`` and ``ambient_c`` checked N-long series), as
    :func:`simulate_timeline` builds it; pointwise in the samples, so a run's inputs are
    those of any stretch of it."""
    pressure, speed, ambient = p_bar, speed_kmh, ambient_c
    n = pressure.size
    # 1. force, 2. heat input at the samples (physics.py's operations, in its order)
    force = np.asarray(block_force_n(wagon, pressure), dtype=np.float64)
    efficiency = np.asarray(brake_efficiency, dtype=np.float64)
    if efficiency.ndim or float(efficiency) != 1.0:
        efficiency = _samples("brake_efficiency", efficiency, n)
        if np.any(~np.isfinite(efficiency) | (efficiency < 0)):
            raise ValueError("brake_efficiency must be finite and >= 0")
        force = force * efficiency
    if drag_force_n is not None:
        drag = _samples("drag_force_n", drag_force_n, n)
        if np.any(~np.isfinite(drag) | (drag < 0)):
            raise ValueError("drag_force_n must be finite and >= 0")
        force = force + drag
    alpha = heat_partition_alpha(wagon)
    power_w = wagon.friction_coefficient * force * speed * KMH_TO_M_S
    flux = np.asarray(
        block_flux_w_m2(wagon, frictional_flux_w_m2(wagon, power_w), alpha=alpha),
        dtype=np.float64,
    )
    base_h = dict(rom.h_nominal if h_w_m2k is None else h_w_m2k)
    h = {face: _samples(f"h_w_m2k[{face!r}]", value, n) for face, value in base_h.items()}
    base = DriveInputs(
        dt_s=float(dt_s),
        speed_kmh=speed,
        block_force_n=force,
        flux_w_m2=flux,
        alpha=alpha,
        ambient_c=ambient,
        h_w_m2k=h,
        friction_coefficient=float(wagon.friction_coefficient),
    )
    return base


def _integrate(
    rom: ReducedModel,
    inputs: DriveInputs,
    initial_c: float,
    initial_state: ArrayLike | None,
    keep_state: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray | None]:
    """(seat, face mean, face max, step flux, final state) of the reduced model."""
    dt_s = inputs.dt_s
    step_flux = _step_mean(inputs.flux_w_m2)
    step_ambient = _step_mean(inputs.ambient_c)
    _check_finite("flux_w_m2 (after the effects)", step_flux)
    step_h: dict[str, FloatArray | float] = {}
    for face, values in inputs.h_w_m2k.items():
        steps = _step_mean(np.asarray(values, dtype=np.float64))
        if np.all(steps == steps[0]):
            step_h[face] = float(steps[0])
        else:
            step_h[face] = np.round(steps / H_QUANTUM_W_M2K) * H_QUANTUM_W_M2K
    nominal = set(step_h) == set(rom.h_nominal) and all(
        isinstance(value, float) and value == rom.h_nominal[face] for face, value in step_h.items()
    )
    if not keep_state and initial_state is None and nominal:
        batch = rom.simulate_batch(
            dt_s=dt_s,
            flux_w_m2=step_flux[None, :],
            initial_c=np.array([float(initial_c)]),
            ambient_c=step_ambient[None, :],
        )
        return (
            batch.probe_c[0, :, 0],
            batch.face_mean_c[0],
            batch.face_max_c[0],
            step_flux,
            None,
        )
    sim = rom.simulate(
        dt_s=dt_s,
        flux_w_m2=step_flux,
        initial_c=float(initial_c),
        ambient_c=step_ambient,
        h_w_m2k=step_h,
        initial_state=initial_state,
    )
    return sim.probe_c[:, 0], sim.face_mean_c, sim.face_max_c, step_flux, sim.final_state
