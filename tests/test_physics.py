"""Tests of fleetbrake.model.physics: the paper's eqs. 1-12 as block-model.md fixes them."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fleetbrake.fleet.block import BLOCK_MATERIAL, WHEEL_MATERIAL, BlockGeometry, Material
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.physics import (
    BAR_TO_PA,
    KMH_TO_M_S,
    PAPER_MANOEUVRES,
    ForceChain,
    Manoeuvre,
    block_flux_w_m2,
    block_force_n,
    bogie_force_n,
    cylinder_area_m2,
    cylinder_force_n,
    event_flux_series_w_m2,
    event_heat_input,
    event_mean_flux_w_m2,
    event_power_w,
    fill_short_gaps,
    force_chain,
    friction_force_n,
    friction_power_series_w,
    frictional_flux_w_m2,
    heat_partition_alpha,
    mean_pressure_bar,
    pulse_flux_series_w_m2,
    time_resolved_flux_series_w_m2,
)

WAGON = WagonConfig(wagon_id="SGG-0001")  # every value the default of fleet-data.md

# Thresholds of the defaults, worked from the formulas: the cylinder spring is overcome at
# p A_cyl = 1500 N, the regulator at F_cyl i_tot = 2000 N i_II, i.e. F_cyl = 1000 N.
A_CYL_M2 = math.pi * 0.254**2 / 4
SPRING_THRESHOLD_BAR = 1500.0 / A_CYL_M2 / 1e5  # 0.29603 bar
REGULATOR_THRESHOLD_BAR = (1500.0 + 2000.0 * 4.0 / 8.0) / A_CYL_M2 / 1e5  # 0.49338 bar


# --------------------------------------------------------------------------------------------
# Manoeuvre A by hand


def test_manoeuvre_a_force_chain_by_hand() -> None:
    # Paper manoeuvre A, defaults of fleet-data.md, every step from the formulas with literals.
    # The numbers (as this implementation gives them):
    #   A_cyl   = 0.05067074790974978 m^2
    #   F_cyl   = 4175.123765891975 N
    #   F_bogie = 21082.821805522715 N
    #   F_block = 1317.6763628451697 N
    #   F_t     = 197.65145442677544 N
    #   P       = 3305.405174030755 W      (F_t 786 m / 47 s)
    #   A_contact = 0.01888306624317705 m^2
    #   Phi_th  = 175045.99790434382 W/m^2
    #   alpha   = 0.7456327216230548
    #   Phi_b   = 44525.974077704384 W/m^2
    p_pa = 1.12 * 1e5
    a_cyl = math.pi * 0.254**2 / 4.0
    f_cyl = p_pa * a_cyl - 1500.0
    f_bogie = (f_cyl * 8.0 - 2000.0 * 4.0) * 0.83
    f_block = f_bogie / 16
    f_t = 0.15 * f_block
    power = f_t * 786.0 / 47.0
    a_contact = 0.46 * (29.4 * math.pi / 180.0) * 0.080
    phi_th = power / a_contact
    beta_w = math.sqrt(45.0 * 7850.0 * 460.0)
    beta_s = math.sqrt(48.0 * 7100.0 * 520.0)
    s_w = 2.0 * math.pi * 0.46 * 0.080
    s_s = 0.46 * (29.4 * math.pi / 180.0) * 0.080 * 4
    alpha = beta_w * s_w / (beta_w * s_w + beta_s * s_s)
    phi_b = (1.0 - alpha) * phi_th

    heat = event_heat_input(WAGON, PAPER_MANOEUVRES["A"])
    chain = heat.forces
    rel = 1e-12
    assert chain.pressure_pa == pytest.approx(p_pa, rel=rel)
    assert chain.cylinder_area_m2 == pytest.approx(a_cyl, rel=rel)
    assert chain.cylinder_force_n == pytest.approx(f_cyl, rel=rel)
    assert chain.bogie_force_n == pytest.approx(f_bogie, rel=rel)
    assert chain.block_force_n == pytest.approx(f_block, rel=rel)
    assert chain.friction_force_n == pytest.approx(f_t, rel=rel)
    assert heat.power_w == pytest.approx(power, rel=rel)
    assert heat.contact_area_m2 == pytest.approx(a_contact, rel=rel)
    assert heat.frictional_flux_w_m2 == pytest.approx(phi_th, rel=rel)
    assert heat.alpha == pytest.approx(alpha, rel=rel)
    assert heat.block_flux_w_m2 == pytest.approx(phi_b, rel=rel)
    assert event_mean_flux_w_m2(WAGON, PAPER_MANOEUVRES["A"]) == pytest.approx(phi_b, rel=rel)
    assert heat.block_energy_j_m2 == pytest.approx(phi_b * 47.0, rel=rel)

    # The named single-step functions give the same values.
    assert cylinder_area_m2(WAGON) == pytest.approx(a_cyl, rel=rel)
    assert cylinder_force_n(WAGON, 1.12) == pytest.approx(f_cyl, rel=rel)
    assert bogie_force_n(WAGON, 1.12) == pytest.approx(f_bogie, rel=rel)
    assert block_force_n(WAGON, 1.12) == pytest.approx(f_block, rel=rel)
    assert friction_force_n(WAGON, 1.12) == pytest.approx(f_t, rel=rel)
    assert event_power_w(WAGON, 1.12, 786.0, 47.0) == pytest.approx(power, rel=rel)
    assert frictional_flux_w_m2(WAGON, power) == pytest.approx(phi_th, rel=rel)
    assert block_flux_w_m2(WAGON, phi_th) == pytest.approx(phi_b, rel=rel)

    # Regression guard on the recorded numbers (a wrong formula in both places would pass
    # the comparisons above).
    assert heat.forces.block_force_n == pytest.approx(1317.6763628451697, rel=1e-9)
    assert heat.power_w == pytest.approx(3305.405174030755, rel=1e-9)
    assert heat.block_flux_w_m2 == pytest.approx(44525.974077704384, rel=1e-9)


def test_event_power_uses_friction_force_not_normal_force() -> None:
    # The paper's eq. 6 prints F_block; the declared model uses F_t = mu F_block.
    power_w = event_power_w(WAGON, 1.12, 786.0, 47.0)
    assert power_w == pytest.approx(0.15 * block_force_n(WAGON, 1.12) * 786.0 / 47.0, rel=1e-12)
    assert power_w < block_force_n(WAGON, 1.12) * 786.0 / 47.0 * 0.2


def test_manoeuvre_b_flux_is_positive_and_close_to_a() -> None:
    flux_a = event_mean_flux_w_m2(WAGON, PAPER_MANOEUVRES["A"])
    flux_b = event_mean_flux_w_m2(WAGON, PAPER_MANOEUVRES["B"])
    assert flux_b > flux_a > 0  # B: higher pressure, similar mean speed
    assert flux_b / flux_a == pytest.approx(1.045, abs=0.01)


def test_paper_manoeuvres_table_2() -> None:
    a, b = PAPER_MANOEUVRES["A"], PAPER_MANOEUVRES["B"]
    assert (a.distance_m, a.v0_kmh, a.v1_kmh, a.t0_c, a.p_mean_bar, a.duration_s) == (
        786.0,
        95.0,
        33.0,
        23.0,
        1.12,
        47.0,
    )
    assert a.time_to_peak_s == 271.0
    assert (b.distance_m, b.v0_kmh, b.v1_kmh, b.t0_c, b.p_mean_bar, b.duration_s) == (
        713.0,
        93.0,
        23.0,
        37.0,
        1.20,
        46.0,
    )
    assert b.time_to_peak_s == 220.0
    assert a.mean_speed_m_s == pytest.approx(786.0 / 47.0)
    with pytest.raises(TypeError):
        PAPER_MANOEUVRES["C"] = a  # type: ignore[index]
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.duration_s = 1.0  # type: ignore[misc]


@pytest.mark.parametrize(
    "change",
    [
        {"duration_s": 0.0},
        {"duration_s": -3.0},
        {"distance_m": -1.0},
        {"v0_kmh": -5.0},
        {"p_mean_bar": math.nan},
        {"t0_c": math.inf},
        {"time_to_peak_s": -1.0},
        {"duration_s": True},
    ],
)
def test_manoeuvre_rejects_impossible_values(change: dict[str, float]) -> None:
    with pytest.raises(ValueError, match=next(iter(change))):
        dataclasses.replace(PAPER_MANOEUVRES["A"], **change)


# --------------------------------------------------------------------------------------------
# Heat partition


def test_alpha_with_defaults_is_0_7455() -> None:
    assert heat_partition_alpha(WAGON) == pytest.approx(0.7455, abs=0.0005)


def test_alpha_from_geometry_equals_alpha_from_wagon() -> None:
    from_geometry = heat_partition_alpha(BlockGeometry(), blocks_per_wheel=4)
    assert from_geometry == heat_partition_alpha(WAGON)
    with pytest.raises(TypeError, match="blocks_per_wheel"):
        heat_partition_alpha(BlockGeometry())


def test_alpha_follows_its_inputs() -> None:
    # More blocks on the wheel take more of the heat; alpha is independent of R_w and H_b
    # (both S_w and S_s scale with them); a better conducting block takes more.
    alpha_4 = heat_partition_alpha(WAGON)
    assert heat_partition_alpha(WAGON, blocks_per_wheel=2) > alpha_4
    assert heat_partition_alpha(WAGON, blocks_per_wheel=8) < alpha_4
    big_wheel = dataclasses.replace(WAGON, wheel_radius_m=0.5)
    assert heat_partition_alpha(big_wheel) == pytest.approx(alpha_4, rel=1e-12)
    copper = Material(conductivity_w_mk=400.0, density_kg_m3=8900.0, specific_heat_j_kgk=385.0)
    assert heat_partition_alpha(WAGON, block_material=copper) < alpha_4
    same = heat_partition_alpha(WAGON, block_material=WHEEL_MATERIAL)
    s_w, s_s = 2 * math.pi, math.radians(29.4) * 4
    assert same == pytest.approx(s_w / (s_w + s_s), rel=1e-12)
    assert BLOCK_MATERIAL.effusivity > WHEEL_MATERIAL.effusivity


# --------------------------------------------------------------------------------------------
# Force chain: thresholds, sign, monotony, vectorisation, explicit numbers


def test_zero_force_below_the_spring_threshold() -> None:
    for p_bar in (-1.0, 0.0, 0.1, SPRING_THRESHOLD_BAR * 0.999):
        assert cylinder_force_n(WAGON, p_bar) == 0.0
        assert block_force_n(WAGON, p_bar) == 0.0
    assert cylinder_force_n(WAGON, SPRING_THRESHOLD_BAR * 1.01) > 0.0


def test_zero_force_below_the_regulator_threshold() -> None:
    # Between the thresholds the cylinder pushes, but not hard enough to beat the regulator.
    p_between_bar = 0.5 * (SPRING_THRESHOLD_BAR + REGULATOR_THRESHOLD_BAR)
    assert cylinder_force_n(WAGON, p_between_bar) > 0.0
    assert bogie_force_n(WAGON, p_between_bar) == 0.0
    assert block_force_n(WAGON, p_between_bar) == 0.0
    assert friction_force_n(WAGON, p_between_bar) == 0.0
    assert block_force_n(WAGON, REGULATOR_THRESHOLD_BAR * 0.999) == 0.0
    assert block_force_n(WAGON, REGULATOR_THRESHOLD_BAR * 1.001) > 0.0


@given(
    p1=st.floats(min_value=-1.0, max_value=10.0, allow_nan=False),
    p2=st.floats(min_value=-1.0, max_value=10.0, allow_nan=False),
)
def test_block_force_never_negative_and_monotone(p1: float, p2: float) -> None:
    low, high = sorted((p1, p2))
    f_low, f_high = block_force_n(WAGON, low), block_force_n(WAGON, high)
    assert f_low >= 0.0
    assert f_high >= 0.0
    assert f_low <= f_high


@given(
    st.lists(st.floats(min_value=-1.0, max_value=10.0, allow_nan=False), min_size=1, max_size=50)
)
def test_block_force_vectorised_equals_scalar(pressures_bar: list[float]) -> None:
    forces = block_force_n(WAGON, np.array(pressures_bar))
    assert isinstance(forces, np.ndarray)
    assert forces.shape == (len(pressures_bar),)
    for p_bar, force in zip(pressures_bar, forces, strict=True):
        assert force == block_force_n(WAGON, p_bar)
    ordered = block_force_n(WAGON, np.sort(pressures_bar))
    assert np.all(np.diff(ordered) >= 0.0)


def test_scalar_in_scalar_out_array_in_array_out() -> None:
    assert isinstance(friction_force_n(WAGON, 2.0), float)
    assert isinstance(friction_force_n(WAGON, 2), float)
    series = friction_force_n(WAGON, [0.0, 1.0, 2.0])
    assert isinstance(series, np.ndarray)
    assert series.dtype == np.float64
    chain = force_chain(WAGON, np.array([0.0, 1.12, 3.0]))
    assert isinstance(chain, ForceChain)
    assert chain.block_force_n[1] == pytest.approx(block_force_n(WAGON, 1.12), rel=1e-15)
    assert chain.block_force_n[0] == 0.0


def test_nan_pressure_gives_nan_force() -> None:
    forces = friction_force_n(WAGON, np.array([1.0, np.nan, 2.0]))
    assert np.isnan(forces[1])
    assert np.isfinite(forces[[0, 2]]).all()
    assert math.isnan(block_force_n(WAGON, math.nan))


def test_explicit_numbers_instead_of_a_wagon() -> None:
    explicit = cylinder_force_n(
        None, 2.0, cylinder_diameter_m=0.305, cylinder_spring_force_n=1500.0
    )
    assert explicit == pytest.approx(2.0e5 * math.pi * 0.305**2 / 4 - 1500.0, rel=1e-12)
    # An explicit number overrides the wagon's value.
    assert cylinder_force_n(WAGON, 2.0, cylinder_diameter_m=0.305) == explicit
    bigger = dataclasses.replace(WAGON, cylinder_diameter_m=0.305)
    assert friction_force_n(WAGON, 2.0, cylinder_diameter_m=0.305) == friction_force_n(bigger, 2.0)
    with pytest.raises(TypeError, match="cylinder_spring_force_n"):
        cylinder_force_n(None, 2.0, cylinder_diameter_m=0.305)
    with pytest.raises(ValueError, match="cylinder_diameter_m"):
        cylinder_force_n(WAGON, 2.0, cylinder_diameter_m=-0.3)
    with pytest.raises(ValueError, match="friction_coefficient"):
        friction_force_n(WAGON, 2.0, friction_coefficient=1.5)
    with pytest.raises(ValueError, match="blocks_per_bogie"):
        block_force_n(WAGON, 2.0, blocks_per_bogie=16.0)  # type: ignore[arg-type]


def test_force_chain_prints_every_value() -> None:
    text = str(force_chain(WAGON, 1.12))
    for name in ("cylinder_area_m2", "cylinder_force_n", "bogie_force_n", "block_force_n"):
        assert name in text
    assert "F_t" in text


def test_pressure_must_be_numbers() -> None:
    with pytest.raises(TypeError):
        block_force_n(WAGON, np.array([True, False]))
    with pytest.raises(TypeError):
        block_force_n(WAGON, np.array(["1.0"]))


# --------------------------------------------------------------------------------------------
# Eq. 1 and flux series


def test_mean_pressure_is_the_trapezoid_time_average() -> None:
    # integral of [0, 1, 2, 1] at 1 Hz = 0.5 + 1.5 + 1.5 = 3.5 bar s over 3 s
    assert mean_pressure_bar([0.0, 1.0, 2.0, 1.0]) == pytest.approx(3.5 / 3.0, rel=1e-15)
    assert mean_pressure_bar(np.full(48, 1.12)) == pytest.approx(1.12, rel=1e-15)
    assert mean_pressure_bar([0.0, 1.0, 2.0, 1.0], dt_s=2.0) == pytest.approx(3.5 / 3.0)
    assert math.isnan(mean_pressure_bar([1.0, math.nan, 1.0]))
    with pytest.raises(ValueError, match="two samples"):
        mean_pressure_bar([1.0])


def test_event_flux_series_is_the_constant_pulse_then_zero() -> None:
    manoeuvre = PAPER_MANOEUVRES["A"]
    flux_w_m2 = event_mean_flux_w_m2(WAGON, manoeuvre)
    series = event_flux_series_w_m2(WAGON, manoeuvre, n_steps=600)
    assert series.shape == (600,)
    assert np.all(series[:47] == flux_w_m2)
    assert np.all(series[47:] == 0.0)
    assert event_flux_series_w_m2(WAGON, manoeuvre, n_steps=10).shape == (10,)


def test_pulse_with_a_fractional_end_keeps_its_energy() -> None:
    series = pulse_flux_series_w_m2(1000.0, duration_s=2.5, n_steps=5)
    assert series.tolist() == [1000.0, 1000.0, 500.0, 0.0, 0.0]
    series = pulse_flux_series_w_m2(1000.0, duration_s=7.0, n_steps=10, dt_s=2.0)
    assert series.tolist() == [1000.0, 1000.0, 1000.0, 500.0] + [0.0] * 6
    assert float(np.sum(series) * 2.0) == pytest.approx(7000.0, rel=1e-15)
    with pytest.raises(ValueError, match="n_steps"):
        pulse_flux_series_w_m2(1000.0, duration_s=2.0, n_steps=-1)


def test_event_mean_and_time_resolved_carry_the_same_energy() -> None:
    # Constant pressure, constant deceleration from 95 to 33 km/h in 47 s, sampled at 1 Hz:
    # 48 samples; the distance consistent with them is the mean speed x duration.
    duration_s = 47.0
    v0_kmh, v1_kmh = 95.0, 33.0
    time_s = np.arange(48, dtype=np.float64)
    speed_kmh = v0_kmh + (v1_kmh - v0_kmh) * time_s / duration_s
    pressure_bar = np.full(time_s.size, 1.12)
    distance_m = 0.5 * (v0_kmh + v1_kmh) * KMH_TO_M_S * duration_s
    manoeuvre = Manoeuvre(
        distance_m=distance_m,
        v0_kmh=v0_kmh,
        v1_kmh=v1_kmh,
        t0_c=23.0,
        p_mean_bar=mean_pressure_bar(pressure_bar),
        duration_s=duration_s,
    )
    n_steps = 300
    event_series = event_flux_series_w_m2(WAGON, manoeuvre, n_steps=n_steps)
    resolved_series = time_resolved_flux_series_w_m2(
        WAGON, pressure_bar, speed_kmh, n_steps=n_steps
    )
    assert resolved_series.shape == (n_steps,)
    assert np.all(resolved_series[47:] == 0.0)
    # The time-resolved flux falls with the speed; the event mean is constant.
    assert np.all(np.diff(resolved_series[:47]) < 0.0)
    event_energy_j_m2 = float(np.sum(event_series) * 1.0)
    resolved_energy_j_m2 = float(np.sum(resolved_series) * 1.0)
    assert resolved_energy_j_m2 == pytest.approx(event_energy_j_m2, rel=1e-9)
    # Both equal F_t d_f (1 - alpha) / A_contact, worked independently.
    heat = event_heat_input(WAGON, manoeuvre)
    expected_j_m2 = (
        heat.forces.friction_force_n * distance_m * (1 - heat.alpha) / heat.contact_area_m2
    )
    assert event_energy_j_m2 == pytest.approx(expected_j_m2, rel=1e-12)


def test_time_resolved_power_per_sample() -> None:
    power_w = friction_power_series_w(WAGON, [1.12, 1.12, 0.0], [36.0, 0.0, 80.0])
    assert power_w[0] == pytest.approx(friction_force_n(WAGON, 1.12) * 10.0, rel=1e-12)
    assert power_w[1] == 0.0  # standing still
    assert power_w[2] == 0.0  # released
    # Without n_steps: N samples give N - 1 interval means.
    flux = time_resolved_flux_series_w_m2(WAGON, [1.12, 1.12, 1.12], [36.0, 36.0, 0.0])
    flux_36 = (1 - heat_partition_alpha(WAGON)) * power_w[0] / WAGON.geometry.contact_area_m2
    assert flux.shape == (2,)
    assert flux[0] == pytest.approx(flux_36, rel=1e-12)
    assert flux[1] == pytest.approx(flux_36 / 2, rel=1e-12)


def test_time_resolved_missing_samples_give_nan() -> None:
    pressure_bar = np.array([1.12, np.nan, 1.12, 1.12, 1.12])
    speed_kmh = np.array([60.0, 60.0, 60.0, np.nan, 60.0])
    power_w = friction_power_series_w(WAGON, pressure_bar, speed_kmh)
    assert np.isnan(power_w).tolist() == [False, True, False, True, False]
    flux = time_resolved_flux_series_w_m2(WAGON, pressure_bar, speed_kmh)
    assert np.isnan(flux).all()  # every interval touches a missing sample
    filled = time_resolved_flux_series_w_m2(
        WAGON, fill_short_gaps(pressure_bar, max_gap_s=1.0), fill_short_gaps(speed_kmh, 1.0)
    )
    assert np.isfinite(filled).all()
    assert np.allclose(filled, filled[0], rtol=1e-12)


def test_time_resolved_rejects_bad_series() -> None:
    with pytest.raises(ValueError, match="equally long"):
        friction_power_series_w(WAGON, [1.0, 1.0], [10.0])
    with pytest.raises(ValueError, match=">= 0"):
        friction_power_series_w(WAGON, [1.0, 1.0], [10.0, -2.0])
    with pytest.raises(ValueError, match="one-dimensional"):
        friction_power_series_w(WAGON, [[1.0]], [[1.0]])
    with pytest.raises(ValueError, match="two samples"):
        time_resolved_flux_series_w_m2(WAGON, [1.0], [10.0])


def test_fill_short_gaps() -> None:
    nan = math.nan
    values = np.array([nan, 1.0, nan, 3.0, nan, nan, nan, 7.0, nan])
    filled = fill_short_gaps(values, max_gap_s=1.0)
    # One missing sample is filled; three in a row are not; the ends stay missing.
    assert filled[2] == pytest.approx(2.0)
    assert np.isnan(filled[[0, 4, 5, 6, 8]]).all()
    filled = fill_short_gaps(values, max_gap_s=3.0)
    assert filled[4:7].tolist() == pytest.approx([4.0, 5.0, 6.0])
    assert np.isnan(filled[[0, 8]]).all()
    # dt_s scales the gap: three samples at 2 s last 6 s.
    assert np.isnan(fill_short_gaps(values, max_gap_s=5.0, dt_s=2.0)[5])
    assert not np.isnan(fill_short_gaps(values, max_gap_s=6.0, dt_s=2.0)[5])
    assert np.isnan(values[2])  # the input is left alone
    assert np.isnan(fill_short_gaps([nan, nan], max_gap_s=10.0)).all()


def test_units_of_the_constants() -> None:
    assert BAR_TO_PA == 1e5
    assert 3.6 * KMH_TO_M_S == pytest.approx(1.0, rel=1e-15)
