"""Heat input into a brake block: the paper's eqs. 1-12 as ``shared/spec/block-model.md`` has them.

Usage::

    from fleetbrake.model.physics import (
        PAPER_MANOEUVRES, event_flux_series_w_m2, event_heat_input, force_chain,
        time_resolved_flux_series_w_m2,
    )
    from fleetbrake.fleet.registry import WagonConfig

    wagon = WagonConfig(wagon_id="SGG-0001")            # or load_registry(...).wagon(...)
    print(force_chain(wagon, 1.12))                      # every force of eqs. 2-5, with units
    heat = event_heat_input(wagon, PAPER_MANOEUVRES["A"])
    heat.block_flux_w_m2                                 # Phi_b, W/m^2, constant for 47 s
    flux = event_flux_series_w_m2(wagon, PAPER_MANOEUVRES["A"], n_steps=600)   # 1 Hz input
    flux_t = time_resolved_flux_series_w_m2(wagon, p_bar, speed_kmh, n_steps=600)

The chain (UIC 544-1), per block, with pressure in bar gauge (x 1e5 Pa):

* F_cyl = p A_cyl - F_s,cyl, A_cyl = pi d^2 / 4 (eq. 4);
* F_bogie = (F_cyl i_tot - F_s,rig i_II) eta (eq. 3);
* F_block = F_bogie / blocks_per_bogie (eq. 2);
* F_t = mu F_block (eq. 5).

A negative force means no braking force: each of F_cyl, F_bogie, F_block is clipped at zero
(the piston does not pull; the regulator and the springs hold the blocks off the wheel), so
the block force is zero below both thresholds and never negative.

Two forms of heat input, the same model at two resolutions:

(a) event mean (the paper's): p_mean = time-average of p over the manoeuvre (eq. 1);
    P = F_t(p_mean) d_f / Delta t (W per block; eq. 6 as block-model.md corrects it: the paper
    prints the normal force F_block where the friction force F_t belongs);
    Phi_th = P / A_contact (eq. 7); Phi_b = (1 - alpha) Phi_th (eq. 8), constant for the
    manoeuvre's duration, then zero;
(b) time-resolved: P(t) = F_t(p(t)) v(t), Phi_b(t) = (1 - alpha) P(t) / A_contact, from 1 Hz
    samples of pressure and speed.

Missing samples: a NaN pressure or speed gives a NaN force, power and flux (nothing is
guessed here). Fill short gaps first with :func:`fill_short_gaps` if that is what you want;
a NaN left in a flux series is for the caller to deal with before simulating.

Time convention of the flux series (docs/dev/thermal-api.md): value ``n`` holds on the
interval [n dt, (n + 1) dt]. Series from samples take the interval mean (trapezoid), so the
energy they carry is the trapezoid integral of the sampled power.

Alpha (eqs. 9-12): alpha = beta_w S_w / (beta_w S_w + beta_s S_s), beta = sqrt(k rho c),
S_w = 2 pi R_w H_b, S_s = L_b H_b N_bw, L_b = R_w theta_c; with the defaults alpha = 0.7455.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from types import MappingProxyType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake.fleet.block import BLOCK_MATERIAL, WHEEL_MATERIAL, BlockGeometry, Material
from fleetbrake.fleet.registry import WagonConfig, check_value

__all__ = [
    "BAR_TO_PA",
    "KMH_TO_M_S",
    "PAPER_MANOEUVRES",
    "EventHeatInput",
    "ForceChain",
    "Manoeuvre",
    "block_flux_w_m2",
    "block_force_n",
    "bogie_force_n",
    "cylinder_area_m2",
    "cylinder_force_n",
    "event_flux_series_w_m2",
    "event_heat_input",
    "event_mean_flux_w_m2",
    "event_power_w",
    "fill_short_gaps",
    "force_chain",
    "friction_force_n",
    "friction_power_series_w",
    "frictional_flux_w_m2",
    "heat_partition_alpha",
    "mean_pressure_bar",
    "pulse_flux_series_w_m2",
    "time_resolved_flux_series_w_m2",
]

BAR_TO_PA = 1.0e5
"""Pascal per bar (the logs give gauge pressure in bar)."""

KMH_TO_M_S = 1.0 / 3.6
"""Metres per second per kilometre per hour."""

FloatArray = NDArray[np.float64]


# --------------------------------------------------------------------------------------------
# Helpers


def _params(
    wagon: WagonConfig | None, function: str, given: Mapping[str, float | int | None]
) -> dict[str, float]:
    """Each parameter: the explicit number if given (checked as in the registry), or the wagon's."""
    out: dict[str, float] = {}
    missing = []
    for key, value in given.items():
        if value is None:
            if wagon is None:
                missing.append(key)
            else:
                out[key] = float(getattr(wagon, key))
            continue
        problem = check_value(key, value)
        if problem is not None:
            raise ValueError(f"{function}: {key} {problem}")
        out[key] = float(value)
    if missing:
        raise TypeError(f"{function}: no wagon given, so give {', '.join(missing)} explicitly")
    return out


def _check_positive(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if value <= 0:
        raise ValueError(f"{name} must be positive, got {value!r}")


def _check_not_negative(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if value < 0:
        raise ValueError(f"{name} must be >= 0, got {value!r}")


def _as_float_array(name: str, values: ArrayLike) -> FloatArray:
    array = np.asarray(values)
    if array.dtype == np.bool_ or not (
        np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)
    ):
        raise TypeError(f"{name} must be numbers, got an array of {array.dtype}")
    return array.astype(np.float64)


def _out(array: FloatArray, scalar: bool) -> float | FloatArray:
    return float(array) if scalar else array


def _series(name: str, values: ArrayLike) -> FloatArray:
    array = _as_float_array(name, values)
    if array.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional (a 1 Hz series), got shape {array.shape}")
    return array


# --------------------------------------------------------------------------------------------
# Force chain, eqs. 2-5


def cylinder_area_m2(
    wagon: WagonConfig | None, *, cylinder_diameter_m: float | None = None
) -> float:
    """A_cyl = pi d^2 / 4, the brake cylinder's piston area."""
    p = _params(wagon, "cylinder_area_m2", {"cylinder_diameter_m": cylinder_diameter_m})
    return math.pi * p["cylinder_diameter_m"] ** 2 / 4.0


def _pressure_pa(p_bar: ArrayLike) -> tuple[FloatArray, bool]:
    """Gauge pressure in Pa, and whether the input was a scalar."""
    pressure_bar = _as_float_array("p_bar", p_bar)
    return pressure_bar * BAR_TO_PA, pressure_bar.ndim == 0


def _cylinder_n(p: Mapping[str, float], pressure_pa: FloatArray) -> FloatArray:
    area_m2 = math.pi * p["cylinder_diameter_m"] ** 2 / 4.0
    return np.maximum(pressure_pa * area_m2 - p["cylinder_spring_force_n"], 0.0)


def _bogie_n(p: Mapping[str, float], cylinder_n: FloatArray) -> FloatArray:
    rigging_n = (
        cylinder_n * p["rigging_ratio_total"]
        - p["regulator_force_n"] * p["rigging_ratio_after_central"]
    )
    return np.maximum(rigging_n * p["rigging_efficiency"], 0.0)


def _block_n(p: Mapping[str, float], bogie_n: FloatArray) -> FloatArray:
    return bogie_n / p["blocks_per_bogie"]


def _friction_n(p: Mapping[str, float], block_n: FloatArray) -> FloatArray:
    return p["friction_coefficient"] * block_n


def cylinder_force_n(
    wagon: WagonConfig | None,
    p_bar: ArrayLike,
    *,
    cylinder_diameter_m: float | None = None,
    cylinder_spring_force_n: float | None = None,
) -> float | FloatArray:
    """F_cyl = p A_cyl - F_s,cyl (eq. 4), zero where negative; ``p_bar`` gauge, float or array.

    Parameters come from ``wagon``; an explicit keyword number takes precedence (``wagon`` may
    then be ``None`` if every parameter is given). NaN pressure gives NaN force.
    """
    p = _params(
        wagon,
        "cylinder_force_n",
        {
            "cylinder_diameter_m": cylinder_diameter_m,
            "cylinder_spring_force_n": cylinder_spring_force_n,
        },
    )
    pressure_pa, scalar = _pressure_pa(p_bar)
    return _out(_cylinder_n(p, pressure_pa), scalar)


def bogie_force_n(
    wagon: WagonConfig | None,
    p_bar: ArrayLike,
    *,
    cylinder_diameter_m: float | None = None,
    cylinder_spring_force_n: float | None = None,
    rigging_ratio_total: float | None = None,
    rigging_ratio_after_central: float | None = None,
    rigging_efficiency: float | None = None,
    regulator_force_n: float | None = None,
) -> float | FloatArray:
    """F_bogie = (F_cyl i_tot - F_s,rig i_II) eta (eq. 3), zero where negative.

    Total block force of the bogie, from cylinder pressure ``p_bar`` (gauge, float or array).
    Parameters as in :func:`cylinder_force_n`.
    """
    p = _params(
        wagon,
        "bogie_force_n",
        {
            "cylinder_diameter_m": cylinder_diameter_m,
            "cylinder_spring_force_n": cylinder_spring_force_n,
            "rigging_ratio_total": rigging_ratio_total,
            "rigging_ratio_after_central": rigging_ratio_after_central,
            "rigging_efficiency": rigging_efficiency,
            "regulator_force_n": regulator_force_n,
        },
    )
    pressure_pa, scalar = _pressure_pa(p_bar)
    return _out(_bogie_n(p, _cylinder_n(p, pressure_pa)), scalar)


def block_force_n(
    wagon: WagonConfig | None,
    p_bar: ArrayLike,
    *,
    cylinder_diameter_m: float | None = None,
    cylinder_spring_force_n: float | None = None,
    rigging_ratio_total: float | None = None,
    rigging_ratio_after_central: float | None = None,
    rigging_efficiency: float | None = None,
    regulator_force_n: float | None = None,
    blocks_per_bogie: int | None = None,
) -> float | FloatArray:
    """F_block = F_bogie / blocks_per_bogie (eq. 2): normal force of one block on the wheel, >= 0.

    Zero below the thresholds of the cylinder spring and the regulator; non-decreasing in
    pressure. Parameters as in :func:`cylinder_force_n`.
    """
    p = _params(
        wagon,
        "block_force_n",
        {
            "cylinder_diameter_m": cylinder_diameter_m,
            "cylinder_spring_force_n": cylinder_spring_force_n,
            "rigging_ratio_total": rigging_ratio_total,
            "rigging_ratio_after_central": rigging_ratio_after_central,
            "rigging_efficiency": rigging_efficiency,
            "regulator_force_n": regulator_force_n,
            "blocks_per_bogie": blocks_per_bogie,
        },
    )
    pressure_pa, scalar = _pressure_pa(p_bar)
    return _out(_block_n(p, _bogie_n(p, _cylinder_n(p, pressure_pa))), scalar)


def friction_force_n(
    wagon: WagonConfig | None,
    p_bar: ArrayLike,
    *,
    cylinder_diameter_m: float | None = None,
    cylinder_spring_force_n: float | None = None,
    rigging_ratio_total: float | None = None,
    rigging_ratio_after_central: float | None = None,
    rigging_efficiency: float | None = None,
    regulator_force_n: float | None = None,
    blocks_per_bogie: int | None = None,
    friction_coefficient: float | None = None,
) -> float | FloatArray:
    """F_t = mu F_block (eq. 5): tangential friction force of one block. Parameters as above."""
    p = _params(
        wagon,
        "friction_force_n",
        {
            "cylinder_diameter_m": cylinder_diameter_m,
            "cylinder_spring_force_n": cylinder_spring_force_n,
            "rigging_ratio_total": rigging_ratio_total,
            "rigging_ratio_after_central": rigging_ratio_after_central,
            "rigging_efficiency": rigging_efficiency,
            "regulator_force_n": regulator_force_n,
            "blocks_per_bogie": blocks_per_bogie,
            "friction_coefficient": friction_coefficient,
        },
    )
    pressure_pa, scalar = _pressure_pa(p_bar)
    block_n = _block_n(p, _bogie_n(p, _cylinder_n(p, pressure_pa)))
    return _out(_friction_n(p, block_n), scalar)


_CHAIN_KEYS = (
    "cylinder_diameter_m",
    "cylinder_spring_force_n",
    "rigging_ratio_total",
    "rigging_ratio_after_central",
    "rigging_efficiency",
    "regulator_force_n",
    "blocks_per_bogie",
    "friction_coefficient",
)


@dataclass(frozen=True)
class ForceChain:
    """Every value of the force chain (eqs. 2-5) for one pressure (or an array of them)."""

    pressure_bar: float | FloatArray
    pressure_pa: float | FloatArray
    cylinder_area_m2: float
    cylinder_force_n: float | FloatArray
    bogie_force_n: float | FloatArray
    block_force_n: float | FloatArray
    friction_force_n: float | FloatArray

    def __str__(self) -> str:
        symbols = {
            "pressure_bar": "p",
            "pressure_pa": "p",
            "cylinder_area_m2": "A_cyl",
            "cylinder_force_n": "F_cyl",
            "bogie_force_n": "F_bogie",
            "block_force_n": "F_block",
            "friction_force_n": "F_t",
        }
        lines = []
        for f in fields(self):
            value = getattr(self, f.name)
            shown = f"{value:.6g}" if isinstance(value, float) else np.array2string(value)
            lines.append(f"{symbols[f.name]:>8} = {shown}  ({f.name})")
        return "\n".join(lines)


def force_chain(wagon: WagonConfig, p_bar: ArrayLike) -> ForceChain:
    """The force chain of ``wagon`` at cylinder pressure ``p_bar`` (gauge), every value named."""
    p = {key: float(getattr(wagon, key)) for key in _CHAIN_KEYS}
    pressure_pa, scalar = _pressure_pa(p_bar)
    cylinder_n = _cylinder_n(p, pressure_pa)
    bogie_n = _bogie_n(p, cylinder_n)
    block_n = _block_n(p, bogie_n)
    friction_n = _friction_n(p, block_n)
    return ForceChain(
        pressure_bar=_out(pressure_pa / BAR_TO_PA, scalar),
        pressure_pa=_out(pressure_pa, scalar),
        cylinder_area_m2=cylinder_area_m2(wagon),
        cylinder_force_n=_out(cylinder_n, scalar),
        bogie_force_n=_out(bogie_n, scalar),
        block_force_n=_out(block_n, scalar),
        friction_force_n=_out(friction_n, scalar),
    )


# --------------------------------------------------------------------------------------------
# Heat partition, eqs. 9-12


def heat_partition_alpha(
    source: WagonConfig | BlockGeometry,
    *,
    blocks_per_wheel: int | None = None,
    block_material: Material | None = None,
    wheel_material: Material = WHEEL_MATERIAL,
) -> float:
    """alpha, the wheel's share of the friction heat (eqs. 9-12); the block gets 1 - alpha.

    alpha = beta_w S_w / (beta_w S_w + beta_s S_s), beta = sqrt(k rho c),
    S_w = 2 pi R_w H_b (the wheel's swept tread), S_s = L_b H_b N_bw (the friction faces of the
    blocks on one wheel), L_b = R_w theta_c.

    From a :class:`WagonConfig`: its geometry, ``blocks_per_wheel`` and block material (each
    may be overridden). From a bare :class:`BlockGeometry`: ``blocks_per_wheel`` is required,
    the block material defaults to the reference cast iron.
    """
    if isinstance(source, WagonConfig):
        geometry = source.geometry
        n_blocks = source.blocks_per_wheel if blocks_per_wheel is None else blocks_per_wheel
        material = source.block_material if block_material is None else block_material
    elif isinstance(source, BlockGeometry):
        if blocks_per_wheel is None:
            raise TypeError("heat_partition_alpha: from a BlockGeometry, give blocks_per_wheel")
        geometry = source
        n_blocks = blocks_per_wheel
        material = BLOCK_MATERIAL if block_material is None else block_material
    else:
        raise TypeError(
            f"heat_partition_alpha: source must be a WagonConfig or BlockGeometry, "
            f"got {type(source).__name__}"
        )
    problem = check_value("blocks_per_wheel", n_blocks)
    if problem is not None:
        raise ValueError(f"heat_partition_alpha: blocks_per_wheel {problem}")
    wheel_area_m2 = 2.0 * math.pi * geometry.wheel_radius_m * geometry.block_width_m
    blocks_area_m2 = geometry.contact_arc_m * geometry.block_width_m * n_blocks
    wheel_term = wheel_material.effusivity * wheel_area_m2
    block_term = material.effusivity * blocks_area_m2
    return wheel_term / (wheel_term + block_term)


# --------------------------------------------------------------------------------------------
# (a) Event mean: eqs. 1, 6-8


@dataclass(frozen=True)
class Manoeuvre:
    """A braking manoeuvre as the paper's Table 2 describes one.

    ``distance_m`` travelled while braking, speeds at activation and release, block
    temperature at activation ``t0_c``, time-mean cylinder pressure ``p_mean_bar`` (gauge),
    ``duration_s``, and (paper only) the time from activation to the sensor's maximum.
    """

    distance_m: float
    v0_kmh: float
    v1_kmh: float
    t0_c: float
    p_mean_bar: float
    duration_s: float
    time_to_peak_s: float | None = None

    def __post_init__(self) -> None:
        _check_not_negative("Manoeuvre.distance_m", self.distance_m)
        _check_not_negative("Manoeuvre.v0_kmh", self.v0_kmh)
        _check_not_negative("Manoeuvre.v1_kmh", self.v1_kmh)
        _check_positive("Manoeuvre.duration_s", self.duration_s)
        for name in ("t0_c", "p_mean_bar"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"Manoeuvre.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"Manoeuvre.{name} must be finite, got {value!r}")
        if self.time_to_peak_s is not None:
            _check_not_negative("Manoeuvre.time_to_peak_s", self.time_to_peak_s)

    @property
    def mean_speed_m_s(self) -> float:
        """d_f / Delta t, the mean speed that eq. 6 uses."""
        return self.distance_m / self.duration_s


PAPER_MANOEUVRES: Mapping[str, Manoeuvre] = MappingProxyType(
    {
        "A": Manoeuvre(
            distance_m=786.0,
            v0_kmh=95.0,
            v1_kmh=33.0,
            t0_c=23.0,
            p_mean_bar=1.12,
            duration_s=47.0,
            time_to_peak_s=271.0,
        ),
        "B": Manoeuvre(
            distance_m=713.0,
            v0_kmh=93.0,
            v1_kmh=23.0,
            t0_c=37.0,
            p_mean_bar=1.20,
            duration_s=46.0,
            time_to_peak_s=220.0,
        ),
    }
)
"""The paper's two manoeuvres (Table 2 of block-model.md), read-only."""


def mean_pressure_bar(p_bar: ArrayLike, dt_s: float = 1.0) -> float:
    """p_mean = (1 / (t_f - t_i)) integral p dt (eq. 1), trapezoid over equally spaced samples.

    The first sample is at activation (t_i), the last at release (t_f); at least two samples.
    A NaN sample gives NaN (fill gaps first with :func:`fill_short_gaps` if wanted).
    """
    _check_positive("dt_s", dt_s)
    samples = _series("p_bar", p_bar)
    if samples.size < 2:
        raise ValueError(f"mean_pressure_bar needs at least two samples, got {samples.size}")
    integral_bar_s = float(np.sum(samples[1:] + samples[:-1]) * 0.5 * dt_s)
    return integral_bar_s / ((samples.size - 1) * dt_s)


def event_power_w(
    wagon: WagonConfig, p_mean_bar: float, distance_m: float, duration_s: float
) -> float:
    """P = F_t(p_mean) d_f / Delta t, friction power of one block in W (eq. 6, corrected).

    The paper's eq. 6 prints E_th = F_block d_f / Delta t, the normal force where the friction
    force belongs; block-model.md (and this function) use F_t = mu F_block.
    """
    _check_not_negative("distance_m", distance_m)
    _check_positive("duration_s", duration_s)
    if isinstance(p_mean_bar, bool) or not isinstance(p_mean_bar, int | float):
        raise ValueError(f"p_mean_bar must be a number, got {p_mean_bar!r}")
    return float(friction_force_n(wagon, p_mean_bar)) * distance_m / duration_s


def frictional_flux_w_m2(
    source: WagonConfig | BlockGeometry, power_w: ArrayLike
) -> float | FloatArray:
    """Phi_th = P / A_contact (eq. 7): the friction power per area of the friction face."""
    geometry = source.geometry if isinstance(source, WagonConfig) else source
    power = _as_float_array("power_w", power_w)
    return _out(power / geometry.contact_area_m2, power.ndim == 0)


def block_flux_w_m2(
    wagon: WagonConfig, flux_w_m2: ArrayLike, *, alpha: float | None = None
) -> float | FloatArray:
    """Phi_b = (1 - alpha) Phi_th (eq. 8): the block's share of the frictional flux.

    ``alpha`` defaults to :func:`heat_partition_alpha` of the wagon.
    """
    if alpha is None:
        alpha = heat_partition_alpha(wagon)
    elif not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha!r}")
    flux = _as_float_array("flux_w_m2", flux_w_m2)
    return _out((1.0 - alpha) * flux, flux.ndim == 0)


@dataclass(frozen=True)
class EventHeatInput:
    """Every value of the event-mean heat input (eqs. 1-8) of one manoeuvre on one wagon."""

    manoeuvre: Manoeuvre
    forces: ForceChain
    power_w: float
    contact_area_m2: float
    frictional_flux_w_m2: float
    alpha: float
    block_flux_w_m2: float

    @property
    def block_energy_j_m2(self) -> float:
        """Heat per friction-face area into the block over the manoeuvre: Phi_b Delta t."""
        return self.block_flux_w_m2 * self.manoeuvre.duration_s


def event_heat_input(wagon: WagonConfig, manoeuvre: Manoeuvre) -> EventHeatInput:
    """The paper's heat input for a manoeuvre (eqs. 1-12), every intermediate value kept."""
    forces = force_chain(wagon, manoeuvre.p_mean_bar)
    power_w = event_power_w(wagon, manoeuvre.p_mean_bar, manoeuvre.distance_m, manoeuvre.duration_s)
    flux_w_m2 = float(frictional_flux_w_m2(wagon, power_w))
    alpha = heat_partition_alpha(wagon)
    return EventHeatInput(
        manoeuvre=manoeuvre,
        forces=forces,
        power_w=power_w,
        contact_area_m2=wagon.geometry.contact_area_m2,
        frictional_flux_w_m2=flux_w_m2,
        alpha=alpha,
        block_flux_w_m2=float(block_flux_w_m2(wagon, flux_w_m2, alpha=alpha)),
    )


def event_mean_flux_w_m2(wagon: WagonConfig, manoeuvre: Manoeuvre) -> float:
    """Phi_b of the paper for ``manoeuvre``: constant flux into the block while it lasts, W/m^2."""
    return event_heat_input(wagon, manoeuvre).block_flux_w_m2


def pulse_flux_series_w_m2(
    flux_w_m2: float, duration_s: float, n_steps: int, dt_s: float = 1.0
) -> FloatArray:
    """A per-step flux series: ``flux_w_m2`` for ``duration_s`` from t = 0, then zero.

    Step n holds on [n dt, (n + 1) dt]; the step in which the pulse ends carries the fraction
    of it that the pulse covers, so the series' energy (sum x dt) is flux x duration exactly
    unless ``n_steps`` cuts the pulse short.
    """
    if isinstance(n_steps, bool) or not isinstance(n_steps, int | np.integer) or n_steps < 0:
        raise ValueError(f"n_steps must be an integer >= 0, got {n_steps!r}")
    _check_positive("dt_s", dt_s)
    _check_not_negative("duration_s", duration_s)
    if not math.isfinite(flux_w_m2):
        raise ValueError(f"flux_w_m2 must be finite, got {flux_w_m2!r}")
    step_start_s = np.arange(n_steps, dtype=np.float64) * dt_s
    covered = np.clip((duration_s - step_start_s) / dt_s, 0.0, 1.0)
    return flux_w_m2 * covered


def event_flux_series_w_m2(
    wagon: WagonConfig, manoeuvre: Manoeuvre, n_steps: int, dt_s: float = 1.0
) -> FloatArray:
    """The paper's input for a thermal simulation: Phi_b for the manoeuvre's duration, then 0.

    ``n_steps`` values, step n on [n dt, (n + 1) dt], t = 0 at brake activation.
    """
    return pulse_flux_series_w_m2(
        event_mean_flux_w_m2(wagon, manoeuvre), manoeuvre.duration_s, n_steps, dt_s
    )


# --------------------------------------------------------------------------------------------
# (b) Time-resolved


def friction_power_series_w(
    wagon: WagonConfig, p_bar: ArrayLike, speed_kmh: ArrayLike
) -> FloatArray:
    """P(t) = F_t(p(t)) v(t) at each sample, W per block (v converted from km/h to m/s).

    ``p_bar`` and ``speed_kmh`` are equally long 1-D series of the same instants. A NaN in
    either gives NaN power at that sample: nothing is guessed (see :func:`fill_short_gaps`).
    A negative speed is an error.
    """
    pressure = _series("p_bar", p_bar)
    speed = _series("speed_kmh", speed_kmh)
    if pressure.shape != speed.shape:
        raise ValueError(
            f"p_bar and speed_kmh must be equally long, got {pressure.size} and {speed.size}"
        )
    if np.any(speed < 0):  # NaN compares False: missing is not negative
        first = int(np.flatnonzero(speed < 0)[0])
        raise ValueError(f"speed_kmh must be >= 0, got {speed[first]!r} at sample {first}")
    friction_n = np.asarray(friction_force_n(wagon, pressure), dtype=np.float64)
    return friction_n * speed * KMH_TO_M_S


def time_resolved_flux_series_w_m2(
    wagon: WagonConfig,
    p_bar: ArrayLike,
    speed_kmh: ArrayLike,
    n_steps: int | None = None,
) -> FloatArray:
    """Phi_b per step from 1 Hz samples of pressure and speed (the time-resolved variant).

    From N samples at t_k = k dt (k = 0 .. N-1), step n (on [t_n, t_n+1]) holds the interval
    mean (trapezoid) of Phi_b(t) = (1 - alpha) F_t(p(t)) v(t) / A_contact: N - 1 steps, then
    zeros up to ``n_steps`` if given (or cut to ``n_steps``). The step length is the sample
    spacing; the flux does not depend on it. A NaN sample makes its two adjacent steps NaN.
    """
    power_w = friction_power_series_w(wagon, p_bar, speed_kmh)
    if power_w.size < 2:
        raise ValueError(f"need at least two samples, got {power_w.size}")
    sample_flux_w_m2 = np.asarray(
        block_flux_w_m2(wagon, frictional_flux_w_m2(wagon, power_w)), dtype=np.float64
    )
    step_flux_w_m2 = 0.5 * (sample_flux_w_m2[:-1] + sample_flux_w_m2[1:])
    if n_steps is None:
        return step_flux_w_m2
    if isinstance(n_steps, bool) or not isinstance(n_steps, int | np.integer) or n_steps < 0:
        raise ValueError(f"n_steps must be an integer >= 0, got {n_steps!r}")
    out = np.zeros(n_steps, dtype=np.float64)
    kept = min(n_steps, step_flux_w_m2.size)
    out[:kept] = step_flux_w_m2[:kept]
    return out


def fill_short_gaps(values: ArrayLike, max_gap_s: float, dt_s: float = 1.0) -> FloatArray:
    """Fill runs of NaN samples lasting at most ``max_gap_s`` by linear interpolation.

    A run of k missing samples between two present ones lasts k dt_s. Longer runs, and runs at
    either end of the series (nothing to interpolate towards), stay NaN. Returns a copy.
    """
    _check_not_negative("max_gap_s", max_gap_s)
    _check_positive("dt_s", dt_s)
    series = _series("values", values).copy()
    missing = np.isnan(series)
    if not missing.any() or missing.all():
        return series
    index = np.arange(series.size)
    present = index[~missing]
    filled = np.interp(index, present, series[~missing])
    # Label each run of missing samples and measure it.
    starts = np.flatnonzero(missing & ~np.concatenate(([False], missing[:-1])))
    ends = np.flatnonzero(missing & ~np.concatenate((missing[1:], [False])))
    tolerance_s = 1e-9 * dt_s
    for start, end in zip(starts, ends, strict=True):
        interior = start > 0 and end < series.size - 1
        if interior and (end - start + 1) * dt_s <= max_gap_s + tolerance_s:
            series[start : end + 1] = filled[start : end + 1]
    return series
