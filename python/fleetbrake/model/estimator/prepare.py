"""One wagon's filtering problem (:func:`prepare`), in steps: the series on its time grid
(:mod:`~fleetbrake.model.estimator.grid`), the declared inputs of each step
(:class:`DeclaredSteps`), what kind of step each is (:class:`StepKinds`), the state's layout
(:class:`StateLayout`), the table of distinct transitions and each step's
(:class:`~fleetbrake.model.estimator.transitions.TransitionTable`), the prior, the power's
processes (:class:`PowerProcesses`), and the arrays of
:class:`~fleetbrake.model.estimator.problem.EstimatorProblem`."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import DriveInputs, EffectSet, SensorLag
from fleetbrake.model.estimator.config import EstimatorConfig
from fleetbrake.model.estimator.grid import Grid, series_grid
from fleetbrake.model.estimator.problem import (
    EstimatorInputError,
    EstimatorProblem,
    FloatArray,
    WagonSeries,
)
from fleetbrake.model.estimator.transitions import TransitionTable, modal_response, modal_vector
from fleetbrake.model.rom import ReducedModel
from fleetbrake.model.timeline import H_QUANTUM_W_M2K, drive_inputs

__all__ = ["DeclaredSteps", "PowerProcesses", "StateLayout", "StepKinds", "prepare"]


@dataclass(frozen=True)
class DeclaredSteps:
    """The declared inputs of each step (N-1 rows): the mean of the two bounding samples,
    the standstill inputs over an unlogged standstill."""

    flux_w_m2: FloatArray
    """The friction heat flux into the block's face (0 over a standstill gap)."""
    ambient_c: FloatArray
    h_w_m2k: FloatArray
    """(N-1, faces): each face's convection, quantised where it varies."""
    dh_w_m2k: FloatArray
    """(N-1, faces): ``h_w_m2k`` less the reduced model's nominal convection."""
    h_nominal_w_m2k: FloatArray
    """(faces): the reduced model's nominal convection."""
    t_ref_c: float
    """The reference temperature the state is relative to: the first valid reading (the first
    ambient without one)."""


@dataclass(frozen=True)
class StepKinds:
    """What kind of step each step is (N-1 rows)."""

    samples: NDArray[np.int64]
    """Its length in samples."""
    held: NDArray[np.bool_]
    """The wheel stands: the unexplained power neither heats nor diffuses."""
    applied: NDArray[np.bool_]
    """The cylinder is applied (its quiet-mode noise of its own)."""
    braking: NDArray[np.bool_]
    """The declared friction heat is not zero (where the braking's power ``P_b`` lives)."""


@dataclass(frozen=True)
class StateLayout:
    """The state's layout: ``r`` modal coordinates (the modes, the seat's error), ``P``, the
    lagged reading, ``P_b``."""

    order: int
    """r: the modal coordinates."""
    seat_error: bool
    lag_tau_s: float
    """The sensor lag's time constant (0: no lag)."""
    brake: bool
    c_probe: FloatArray
    """The sensor seat's output row (the first probe), with the seat error's coordinate."""

    @property
    def lag(self) -> bool:
        return self.lag_tau_s > 0

    @property
    def n_state(self) -> int:
        return self.order + 1 + int(self.lag) + int(self.brake)


@dataclass(frozen=True)
class PowerProcesses:
    """The noise of the unexplained power in proportion to the declared braking power, and the
    braking's power ``P_b``'s process (all None where the configuration has none)."""

    power_noise: FloatArray | None
    brake_phi: FloatArray | None
    brake_q: FloatArray | None


def prepare(
    rom: ReducedModel,
    wagon: WagonConfig,
    series: WagonSeries,
    *,
    effects: EffectSet = EffectSet(),  # noqa: B008 (immutable)
    config: EstimatorConfig = EstimatorConfig(),  # noqa: B008 (immutable)
    h_w_m2k: Mapping[str, float | ArrayLike] | None = None,
    contact_c: ArrayLike | None = None,
) -> EstimatorProblem:
    """The filtering problem of one wagon's series under a model revision (``rom`` and
    ``effects``; ``h_w_m2k`` the declared convection, None: the reduced model's nominal, as
    in ``simulate_timeline``). ``contact_c`` (one per logged sample) feeds state-dependent
    effects (:func:`~fleetbrake.model.estimator.estimates.estimate_contact` iterates on it)."""
    grid = series_grid(series, config)
    declared = _declared_steps(rom, wagon, series, grid, effects, config, h_w_m2k, contact_c)
    kinds = _step_kinds(grid, declared, config)
    layout = _state_layout(rom, effects, config)
    table = TransitionTable(
        rom=rom,
        c_probe=layout.c_probe,
        lag_tau_s=layout.lag_tau_s,
        tau_p_s=config.power_time_constant_s,
        area_m2=wagon.geometry.contact_area_m2,
        gap_sd_k=config.gap_offset_sd_k,
        gap_tau_s=config.gap_offset_time_constant_s,
        offset_var_per_s=config.model_offset_sd_k_per_sqrt_s**2,
        seat_sd_k=config.seat_error_sd_k,
        seat_tau_s=config.seat_error_time_constant_s,
    )
    index = _transition_index(table, grid, declared, kinds, config.dt_s)
    w = modal_response(
        rom,
        table,
        index,
        declared.flux_w_m2,
        declared.h_w_m2k * (declared.ambient_c - declared.t_ref_c)[:, None],
        layout.order,
    )
    uniform, cov0 = _prior(rom, layout, declared, config)
    power = _power_processes(table, grid, declared, kinds, wagon, config)
    return _problem(
        series, grid, rom, config, layout, table, index, w, declared, kinds, uniform, cov0, power
    )


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


def _declared_steps(
    rom: ReducedModel,
    wagon: WagonConfig,
    series: WagonSeries,
    grid: Grid,
    effects: EffectSet,
    config: EstimatorConfig,
    h_w_m2k: Mapping[str, float | ArrayLike] | None,
    contact_c: ArrayLike | None,
) -> DeclaredSteps:
    """The declared inputs of each step: the samples' loading (and the same samples at
    standstill, what a sleeping unit's wagon does in a long gap), averaged over each step."""
    dt = config.dt_s
    n = grid.size
    contact: FloatArray | None = None
    if contact_c is not None:
        logged_contact = np.asarray(contact_c, dtype=np.float64).reshape(-1)
        if logged_contact.size != series.time_s.size:
            raise EstimatorInputError(
                f"wagon {series.wagon_id!r}: contact_c has {logged_contact.size} values, "
                f"expected {series.time_s.size}"
            )
        contact = np.interp(grid.time_s, grid.time_s[grid.logged], logged_contact)
    inputs = _drive_inputs(
        wagon, rom, dt, grid.p_bar, grid.speed_kmh, grid.ambient_c, h_w_m2k, effects, contact
    )
    still = _drive_inputs(
        wagon, rom, dt, np.zeros(n), np.zeros(n), grid.ambient_c, h_w_m2k, effects, contact
    )
    valid = np.flatnonzero(np.isfinite(grid.reading_c))
    t_ref = float(grid.reading_c[valid[0]]) if valid.size else float(grid.ambient_c[0])
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
    gap = grid.gap
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
    return DeclaredSteps(
        flux_w_m2=step_flux,
        ambient_c=step_amb,
        h_w_m2k=step_h,
        dh_w_m2k=np.round(step_h - h_nom, 12),
        h_nominal_w_m2k=h_nom,
        t_ref_c=t_ref,
    )


def _step_kinds(grid: Grid, declared: DeclaredSteps, config: EstimatorConfig) -> StepKinds:
    """Each step's length and kind: the wheel standing (power held), the cylinder applied,
    declared friction heat."""
    gap = grid.gap
    held = _held_steps(grid.speed_kmh, gap, config)
    applied = _applied_steps(grid.p_bar, gap | held, config)
    # the steps whose declared friction heat is not zero (where the braking's power P_b lives)
    braking = (
        (declared.flux_w_m2 > 0.0) & ~(gap | held)
        if config.brake_power_w_per_sqrt_s is not None
        else np.zeros(gap.size, dtype=bool)
    )
    samples = np.rint(np.diff(grid.time_s) / config.dt_s).astype(np.int64)
    return StepKinds(samples=samples, held=held, applied=applied, braking=braking)


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


def _state_layout(rom: ReducedModel, effects: EffectSet, config: EstimatorConfig) -> StateLayout:
    """The state's layout under the revision's effects (a sensor lag) and the configuration
    (the seat's error, the braking's power)."""
    lag_effect = effects.get("sensor_lag")
    lag_tau = lag_effect.tau_s if isinstance(lag_effect, SensorLag) else 0.0
    seat_error = config.seat_error_sd_k > 0
    # the sensor seat: the first probe (output rows: probes, mean, nodes), plus its error
    c_probe = np.append(rom.c_out[0], 1.0) if seat_error else rom.c_out[0]
    return StateLayout(
        order=rom.order + int(seat_error),
        seat_error=seat_error,
        lag_tau_s=float(lag_tau),
        brake=config.brake_power_w_per_sqrt_s is not None,
        c_probe=c_probe,
    )


def _codes(column: FloatArray) -> tuple[FloatArray, NDArray[np.int64]]:
    """``np.unique(column, return_inverse=True)``, without its sort for a constant column
    (a face's convection at its nominal value throughout: every step of ``run``'s declared
    revision)."""
    if column.size and bool(np.all(column == column[0])):
        return column[:1].copy(), np.zeros(column.size, dtype=np.int64)
    return np.unique(column, return_inverse=True)


def _transition_index(
    table: TransitionTable, grid: Grid, declared: DeclaredSteps, kinds: StepKinds, dt_s: float
) -> NDArray[np.int64]:
    """Each step's transition (N-1), the table filled with one transition per distinct
    (convection, length, standstill gap, power held, cylinder applied, braking): integer
    codes per column, then one key per step (sorting floats row by row is slow)."""
    gap, held, applied, braking = grid.gap, kinds.held, kinds.applied, kinds.braking
    dh, steps_of = declared.dh_w_m2k, kinds.samples
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
                dt_s,
                bool(gap[i]),
                bool(held[i]),
                bool(applied[i]),
                bool(braking[i]),
            )
            for i in first
        ],
        dtype=np.int64,
    )
    return ids[inverse.reshape(-1)] if grid.size > 1 else np.zeros(0, dtype=np.int64)


def _prior(
    rom: ReducedModel, layout: StateLayout, declared: DeclaredSteps, config: EstimatorConfig
) -> tuple[FloatArray, FloatArray]:
    """The direction of a uniform 1 K offset of the block (and of the lagged reading), and
    the prior covariance: that offset's, and the seat's error at its stationary
    distribution."""
    r = layout.order
    b_air = declared.h_nominal_w_m2k @ rom.b_faces
    uniform = np.zeros(layout.n_state)
    uniform[: rom.order] = np.divide(b_air, rom.lam, out=np.zeros(rom.order), where=rom.lam > 0)
    if layout.lag:
        uniform[r + 1] = 1.0
    sd0 = config.initial_temperature_sd_k
    cov0 = sd0 * sd0 * np.outer(uniform, uniform)
    if layout.seat_error:
        cov0[r - 1, r - 1] = config.seat_error_sd_k**2
    return uniform, cov0


def _power_processes(
    table: TransitionTable,
    grid: Grid,
    declared: DeclaredSteps,
    kinds: StepKinds,
    wagon: WagonConfig,
    config: EstimatorConfig,
) -> PowerProcesses:
    """The declared braking power of each step (W into the block), its share of the noise
    (none at all with the option off: no array of zeros per wagon-second to build and ship),
    and the braking's power ``P_b``: a random walk while braking, decaying otherwise."""
    gain = config.declared_power_noise_per_sqrt_s
    power_noise = (
        np.where(
            kinds.held | grid.gap,
            0.0,
            (gain * declared.flux_w_m2 * wagon.geometry.contact_area_m2) ** 2,
        )
        if gain > 0.0
        else None
    )
    brake_phi: FloatArray | None = None
    brake_q: FloatArray | None = None
    if config.brake_power_w_per_sqrt_s is not None:
        on = np.array(table.braking, dtype=bool)
        length = np.array(table.length_s, dtype=np.float64)
        tau_b = config.brake_power_time_constant_s
        brake_phi = np.where(on, 1.0, np.exp(-length / tau_b) if tau_b > 0 else 0.0)
        brake_q = np.where(on, config.brake_power_w_per_sqrt_s**2 * length, 0.0)
    return PowerProcesses(power_noise=power_noise, brake_phi=brake_phi, brake_q=brake_q)


def _problem(
    series: WagonSeries,
    grid: Grid,
    rom: ReducedModel,
    config: EstimatorConfig,
    layout: StateLayout,
    table: TransitionTable,
    index: NDArray[np.int64],
    w: FloatArray,
    declared: DeclaredSteps,
    kinds: StepKinds,
    uniform: FloatArray,
    cov0: FloatArray,
    power: PowerProcesses,
) -> EstimatorProblem:
    """The problem's arrays from the steps' hand-offs."""
    r = layout.order
    lag_rows = table.lag
    eigen = table.eigen_arrays()
    return EstimatorProblem(
        wagon_id=series.wagon_id,
        order=r,
        lag=layout.lag,
        t_ref_c=declared.t_ref_c,
        time_s=grid.time_s,
        logged=grid.logged,
        reading_c=grid.reading_c,
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
        c_probe=np.ascontiguousarray(layout.c_probe),
        c_mean=np.ascontiguousarray(modal_vector(rom.c_out[rom.n_probes], r)),
        c_nodes=np.ascontiguousarray(
            np.pad(rom.c_out[rom.n_probes + 1 :], ((0, 0), (0, r - rom.order)))
        ),
        x0=np.zeros(layout.n_state),
        cov0=cov0,
        p_prior_unit=0.5 * config.power_time_constant_s,
        q_gap=np.array(table.q_gap, dtype=np.float64),
        gap_dir=uniform,
        held=kinds.held,
        q_modes=np.stack(table.q_modes) if table.q_modes else np.zeros((0, r)),
        applied=np.array(table.applied, dtype=bool),
        power_noise=power.power_noise,
        brake_phi=power.brake_phi,
        brake_q=power.brake_q,
        eigenvectors=None if eigen is None else eigen[0],
        eigenvalues=None if eigen is None else eigen[1],
    )
