"""The undeclared effects (fleetbrake.model.effects) and the one simulation (fleetbrake.model.timeline).

Every effect is checked where it acts, against what physics says it must do, with its
parameters drawn at random from its PARAMETER_RANGES (seeded). The reduced model is the
session's (tests/conftest.py: refinement 0.6, built once).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import (
    EFFECT_CLASSES,
    EFFECT_ORDER,
    EFFECTS,
    LAWS,
    AmbientOffset,
    ConvectionFlatPlate,
    ConvectionSpeed,
    DriveInputs,
    EffectSet,
    Empirical,
    FrictionSpeed,
    FrictionSpeedNormalised,
    FrictionTemperature,
    HeatPartition,
    HeatPartitionEffusivity,
    HolderConduction,
    SensorLag,
    SensorLagTwoStage,
    effect_from_dict,
    parse_effect,
)
from fleetbrake.model.effects.base import FAMILY_LAWS
from fleetbrake.model.physics import heat_partition_alpha, time_resolved_flux_series_w_m2
from fleetbrake.model.rom import first_order_lag
from fleetbrake.model.timeline import FixedPointError, simulate_timeline

WAGON = WagonConfig(wagon_id="TEST-0001")
N_S = 3600
T0_C = 20.0
P_BAR = 1.2
V_KMH = 80.0
DRAWS = 3


def _braking(n_s: int = N_S, p_bar: float = P_BAR, v_kmh: float = V_KMH):
    """A 60 s application at constant speed (the train runs on, as downhill), from t = 60 s."""
    t = np.arange(n_s)
    p = np.where((t >= 60) & (t < 120), p_bar, 0.0)
    v = np.full(n_s, v_kmh)
    return p, v


def _run(rom, effects=(), **kwargs):
    p, v = kwargs.pop("pv", _braking())
    return simulate_timeline(
        rom,
        WAGON,
        dt_s=1.0,
        p_bar=p,
        speed_kmh=v,
        ambient_c=kwargs.pop("ambient_c", T0_C),
        initial_c=kwargs.pop("initial_c", T0_C),
        effects=EffectSet(tuple(effects)),
        **kwargs,
    )


def _draws(cls, count: int = DRAWS):
    rng = np.random.default_rng(sum(map(ord, cls.name)))
    return [cls.random(rng) for _ in range(count)]


@pytest.fixture(scope="module")
def base(default_rom):
    return _run(default_rom)


# --------------------------------------------------------------------------------------------
# simulate_timeline, no effects


def test_no_effects_is_the_rom_driven_by_the_physics_flux(default_rom, base):
    p, v = _braking()
    flux = time_resolved_flux_series_w_m2(WAGON, p, v)
    ref = default_rom.simulate(dt_s=1.0, flux_w_m2=flux, initial_c=T0_C, ambient_c=T0_C)
    np.testing.assert_array_equal(base.flux_w_m2, flux)
    np.testing.assert_allclose(base.sensor_c, ref.probe_c[:, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(base.contact_mean_c, ref.face_mean_c, rtol=0, atol=1e-9)
    np.testing.assert_allclose(base.contact_max_c, ref.face_max_c, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(base.sensor_c, base.seat_c)
    assert base.iterations == 1
    # the braking heats: friction face first and most, the sensor later and less
    assert base.contact_max_c.max() > base.contact_mean_c.max() > base.sensor_c.max() > T0_C + 5
    assert base.contact_max_c.argmax() < base.sensor_c.argmax()


def test_batch_kernel_and_continuation_agree(default_rom, base):
    fast = _run(default_rom, keep_state=False)
    assert fast.final_state is None
    np.testing.assert_allclose(fast.sensor_c, base.sensor_c, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.contact_max_c, base.contact_max_c, rtol=0, atol=1e-9)
    p, v = _braking()
    half = N_S // 2
    first = simulate_timeline(
        default_rom,
        WAGON,
        dt_s=1.0,
        p_bar=p[: half + 1],
        speed_kmh=v[: half + 1],
        ambient_c=T0_C,
        initial_c=T0_C,
    )
    second = simulate_timeline(
        default_rom,
        WAGON,
        dt_s=1.0,
        p_bar=p[half:],
        speed_kmh=v[half:],
        ambient_c=T0_C,
        initial_c=T0_C,
        initial_state=first.final_state,
    )
    joined = np.concatenate((first.sensor_c, second.sensor_c[1:]))
    np.testing.assert_allclose(joined, base.sensor_c, rtol=0, atol=1e-9)


def test_dragging_brake_heats_without_pressure(default_rom):
    n = 1800
    p, v = np.zeros(n), np.full(n, 70.0)
    still = _run(default_rom, pv=(p, v))
    np.testing.assert_allclose(still.sensor_c, T0_C, atol=1e-9)
    assert np.all(still.flux_w_m2 == 0.0)
    dragging = _run(default_rom, pv=(p, v), drag_force_n=300.0)
    assert np.all(dragging.block_force_n == 300.0)
    # 300 N x mu 0.15 x 19.4 m/s = 875 W per block, a quarter of it into the block for 30 min
    assert dragging.sensor_c[-1] > T0_C + 30.0
    assert np.all(np.diff(dragging.sensor_c[60:]) > 0)
    # a dragging brake on a standing wagon makes no heat
    parked = _run(default_rom, pv=(p, np.zeros(n)), drag_force_n=300.0)
    np.testing.assert_allclose(parked.sensor_c, T0_C, atol=1e-9)


def test_weak_brake_scales_the_heating(default_rom, base):
    weak = _run(default_rom, brake_efficiency=0.5)
    np.testing.assert_allclose(weak.block_force_n, 0.5 * base.block_force_n)
    np.testing.assert_allclose(weak.sensor_c - T0_C, 0.5 * (base.sensor_c - T0_C), atol=1e-9)
    # per sample: only the second half of the run is weak
    efficiency = np.where(np.arange(N_S) < 90, 1.0, 0.0)
    half = _run(default_rom, brake_efficiency=efficiency)
    assert T0_C < half.sensor_c.max() < base.sensor_c.max()


def _block_volume_m3(wagon: WagonConfig) -> float:
    g = wagon.geometry
    r0, r1 = g.wheel_radius_m, g.wheel_radius_m + g.body_thickness_m
    r2 = r1 + g.lug_height_m
    body = math.radians(g.contact_angle_deg) / 2 * (r1**2 - r0**2) * g.block_width_m
    lug = math.radians(g.lug_angle_deg) / 2 * (r2**2 - r1**2) * g.lug_width_m
    return body + lug


def test_energy_flux_times_area_is_the_blocks_heat_input(default_rom):
    p, v = _braking()
    v = np.linspace(90.0, 30.0, N_S)  # a speed that varies, so the trapezoid matters
    result = _run(default_rom, pv=(p, v), h_w_m2k={"air": 0.0, "holder": 0.0})
    # the heat input by hand: (1 - alpha) mu F_block v, F_block from the chain of eqs. 2-4
    area_cyl = math.pi * WAGON.cylinder_diameter_m**2 / 4
    f_cyl = np.maximum(p * 1e5 * area_cyl - WAGON.cylinder_spring_force_n, 0.0)
    f_bogie = np.maximum(
        (
            f_cyl * WAGON.rigging_ratio_total
            - WAGON.regulator_force_n * WAGON.rigging_ratio_after_central
        )
        * WAGON.rigging_efficiency,
        0.0,
    )
    power = WAGON.friction_coefficient * f_bogie / WAGON.blocks_per_bogie * v / 3.6
    block_power = (1 - heat_partition_alpha(WAGON)) * power
    energy_j = float(np.sum(0.5 * (block_power[1:] + block_power[:-1])))
    assert energy_j > 1e4
    assert result.heat_input_j == pytest.approx(energy_j, rel=1e-9)
    assert float(np.sum(result.flux_w_m2)) * WAGON.geometry.contact_area_m2 == pytest.approx(
        energy_j, rel=1e-9
    )
    # adiabatic block: after an hour it is uniform, and m c dT is that energy
    m = WAGON.block_material
    capacity = m.density_kg_m3 * m.specific_heat_j_kgk * _block_volume_m3(WAGON)
    assert result.contact_max_c[-1] - result.sensor_c[-1] < 0.01
    assert result.sensor_c[-1] - T0_C == pytest.approx(energy_j / capacity, rel=2e-3)


def test_missing_inputs_are_errors(default_rom):
    p, v = _braking()
    v = v.copy()
    v[10] = np.nan
    with pytest.raises(ValueError, match="speed_kmh"):
        _run(default_rom, pv=(p, v))
    with pytest.raises(ValueError, match="one per sample"):
        _run(default_rom, ambient_c=np.zeros(5))
    with pytest.raises(ValueError, match="at least two"):
        _run(default_rom, pv=(p[:1], v[:1]))


# --------------------------------------------------------------------------------------------
# Each effect, where it acts


def _karwatzki(v_kmh: float, force_kn: float, v_s: float = 100.0, k_s: float = 980.665) -> float:
    """Karwatzki's law for cast-iron blocks, the force in kN against K_s in kN."""
    return 0.6 * (16 * force_kn + k_s) / (80 * force_kn + k_s) * (v_kmh + v_s) / (5 * v_kmh + v_s)


def _karwatzki_as_published(v_kmh: float, force_tf: float) -> float:
    """The law as the literature prints it: K in tonne-force, v in km/h, constants 100."""
    return 0.6 * (16 * force_tf + 100) / (80 * force_tf + 100) * (v_kmh + 100) / (5 * v_kmh + 100)


def test_friction_speed_is_karwatzkis_law_with_its_level():
    law = FrictionSpeed()  # level 1, the literature's constants
    for v, force_kn in [(0.0, 0.0), (100.0, 10.0), (60.0, 1.5), (30.0, 4.2), (120.0, 25.0)]:
        expected = _karwatzki_as_published(v, force_kn / 9.80665)
        assert float(law.mu(np.array(v), np.array(force_kn * 1000.0))) == pytest.approx(
            expected, rel=1e-12
        )
    # written out at two points: mu(0, 0) = 0.6; mu(100 km/h, 1 tf) = 0.6 (116/180) (200/600)
    assert float(law.mu(np.array(0.0), np.array(0.0))) == pytest.approx(0.6)
    one_tf_n = 9.80665e3
    assert float(law.mu(np.array(100.0), np.array(one_tf_n))) == pytest.approx(
        0.6 * 116 / 180 / 3, rel=1e-12
    )
    # the SI form of the textbooks, (1.6 K + 100)/(8 K + 100) with K in kN, rounds g to 10:
    # within 1 % of the tonne-force law over a wagon's block forces
    for force_kn in (5.0, 15.0, 25.0, 40.0):
        si = 0.6 * (1.6 * force_kn + 100) / (8 * force_kn + 100)
        assert float(law.mu(np.array(0.0), np.array(force_kn * 1e3))) == pytest.approx(si, rel=1e-2)
    # cast iron's level at a freight wagon's 20-30 kN a block and 40 km/h: 0.12-0.14 (read
    # with K in kN against K_s = 100, it would be half of that)
    mu_40 = law.mu(np.array([40.0, 40.0]), np.array([20e3, 30e3]))
    assert np.all((mu_40 > 0.12) & (mu_40 < 0.145))
    assert _karwatzki(40.0, 25.0, k_s=100.0) < 0.07
    # the free parameters: the level scales mu, the scales replace the literature's constants
    other = FrictionSpeed(level=1.2, speed_scale_kmh=80.0, force_scale_kn=1500.0)
    v, k = 70.0, 25.0
    written = 1.2 * 0.6 * (16 * k + 1500) / (80 * k + 1500) * (v + 80) / (5 * v + 80)
    assert float(other.mu(np.array(v), np.array(k * 1e3))) == pytest.approx(written, rel=1e-12)
    # negative inputs are no force and standstill
    assert float(law.mu(np.array(-5.0), np.array(-10.0))) == pytest.approx(0.6)


@pytest.mark.parametrize("effect", _draws(FrictionSpeed), ids=str)
def test_friction_speed_sets_the_heating_by_its_own_mu(default_rom, base, effect):
    # constant speed and force: the flux, hence (linear model) the rise, scales by
    # mu(v, F) / mu_registry: the law's own level, not normalised to the registry's mu
    result = _run(default_rom, [effect])
    force = float(base.block_force_n[90])
    scales = (effect.speed_scale_kmh, effect.force_scale_kn)
    mu = effect.level * _karwatzki(V_KMH, force / 1000.0, *scales)
    factor = mu / WAGON.friction_coefficient
    assert float(effect.mu(np.array(V_KMH), np.array(force))) == pytest.approx(mu, rel=1e-12)
    np.testing.assert_allclose(result.sensor_c - T0_C, factor * (base.sensor_c - T0_C), atol=1e-9)
    # slower, mu is higher: the heating grows by the law's ratio
    slow = _run(default_rom, [effect], pv=_braking(v_kmh=25.0))
    slow_base = _run(default_rom, pv=_braking(v_kmh=25.0))
    slow_factor = effect.level * _karwatzki(25.0, force / 1000.0, *scales)
    slow_factor /= WAGON.friction_coefficient
    assert slow_factor > factor
    np.testing.assert_allclose(
        slow.sensor_c - T0_C, slow_factor * (slow_base.sensor_c - T0_C), atol=1e-9
    )


def test_friction_speed_needs_the_registry_mu():
    inputs = _inputs().replace(friction_coefficient=None)
    with pytest.raises(ValueError, match="friction coefficient"):
        FrictionSpeed().apply_to_inputs(inputs)


def test_the_normalised_friction_speed_scales_the_declared_mu_by_its_speed_law(default_rom, base):
    effect = FrictionSpeedNormalised(speed_scale_kmh=120.0, force_exponent=0.2)
    result = _run(default_rom, [effect])
    force = float(base.block_force_n[90])

    def k(v):
        return (v + 120.0) / (5 * v + 120.0)

    factor = k(V_KMH) / k(60.0) * (force / 1500.0) ** -0.2
    assert float(effect.friction_factor(np.array(V_KMH), np.array(force))) == pytest.approx(factor)
    np.testing.assert_allclose(result.sensor_c - T0_C, factor * (base.sensor_c - T0_C), atol=1e-9)


@pytest.mark.parametrize("effect", _draws(HeatPartition), ids=str)
def test_heat_partition_scales_the_blocks_share(default_rom, base, effect):
    result = _run(default_rom, [effect])
    factor = (1 - effect.alpha) / (1 - heat_partition_alpha(WAGON))
    np.testing.assert_allclose(result.sensor_c - T0_C, factor * (base.sensor_c - T0_C), atol=1e-9)
    np.testing.assert_allclose(result.flux_w_m2, factor * base.flux_w_m2, rtol=1e-12)
    # alpha above the declared 0.7455 means less heat in the block
    assert (result.sensor_c.max() < base.sensor_c.max()) == (effect.alpha > 0.7455)


def _charron_alpha(contact_factor: float) -> float:
    """Charron's partition of block-model.md eqs. 9-12 written out for the reference block
    (4 blocks on a 920 mm wheel), the block's side scaled by the contact factor."""
    beta_w, beta_s = math.sqrt(45 * 7850 * 460), math.sqrt(48 * 7100 * 520)
    s_w = 2 * math.pi * 0.46  # x H_b, which cancels
    s_s = 0.46 * math.radians(29.4) * 4
    return beta_w * s_w / (beta_w * s_w + contact_factor * beta_s * s_s)


def test_heat_partition_by_effusivity_is_charrons_with_a_contact_factor():
    alpha_d = heat_partition_alpha(WAGON)
    assert _charron_alpha(1.0) == pytest.approx(alpha_d, rel=1e-12)
    assert HeatPartitionEffusivity(contact_factor=1.0).flux_factor(alpha_d) == pytest.approx(1.0)
    for c in (0.3, 0.7, 1.6, 2.0):
        law = HeatPartitionEffusivity(contact_factor=c)
        assert law.alpha(alpha_d) == pytest.approx(_charron_alpha(c), rel=1e-12)
        assert law.flux_factor(alpha_d) == pytest.approx(
            (1 - _charron_alpha(c)) / (1 - alpha_d), rel=1e-12
        )
        # the same family as the plain alpha
        same = HeatPartition(alpha=law.alpha(alpha_d))
        assert same.flux_factor(alpha_d) == pytest.approx(law.flux_factor(alpha_d), rel=1e-12)
    # a better contact of the block takes more of the heat into it
    assert HeatPartitionEffusivity(contact_factor=1.5).flux_factor(alpha_d) > 1.0


@pytest.mark.parametrize("effect", _draws(HeatPartitionEffusivity), ids=str)
def test_heat_partition_by_effusivity_scales_the_heating(default_rom, base, effect):
    result = _run(default_rom, [effect])
    factor = (1 - _charron_alpha(effect.contact_factor)) / (1 - heat_partition_alpha(WAGON))
    np.testing.assert_allclose(result.sensor_c - T0_C, factor * (base.sensor_c - T0_C), atol=1e-9)


@pytest.mark.parametrize("effect", _draws(FrictionTemperature), ids=str)
def test_friction_temperature_fades_and_its_fixed_point_converges(default_rom, base, effect):
    result = _run(default_rom, [effect])
    assert 2 <= result.iterations <= 10
    # hotter face, lower mu: the rise is smaller, but by less than the fade at the hottest face
    rise, base_rise = result.sensor_c.max() - T0_C, base.sensor_c.max() - T0_C
    worst = float(effect.friction_factor(np.array(base.contact_mean_c.max())))
    assert worst * base_rise < rise < base_rise
    # a fixed point: the flux is the declared one faded by its own face temperature
    fade = effect.friction_factor(result.contact_mean_c)
    np.testing.assert_allclose(result.sample_flux_w_m2, base.sample_flux_w_m2 * fade, rtol=1e-5)
    again = _run(default_rom, [effect], tol_k=1e-8)
    np.testing.assert_allclose(again.sensor_c, result.sensor_c, atol=1e-3)


def test_friction_temperature_that_cannot_converge_says_so(default_rom):
    # a 10x hotter braking and the steepest admissible fade: the iteration oscillates
    with pytest.raises(FixedPointError, match="friction_temperature"):
        _run(
            default_rom,
            [FrictionTemperature(fade_per_k=0.01)],
            pv=_braking(p_bar=3.8, v_kmh=100.0),
            max_iterations=3,
            tol_k=1e-12,
        )


@pytest.mark.parametrize("effect", _draws(ConvectionSpeed), ids=str)
def test_convection_speed_lowers_the_peak_and_cools_faster(default_rom, base, effect):
    result = _run(default_rom, [effect])
    factor = float(effect.h_factor(np.array(V_KMH)))
    assert 1.5 < factor < 5.5
    base_rise = base.sensor_c.max() - T0_C
    assert result.sensor_c.max() < base.sensor_c.max() - 0.01 * base_rise
    assert result.sensor_c.argmax() < base.sensor_c.argmax()
    # an hour on, the excess has decayed much more than with h0 (h x factor)
    base_left = (base.sensor_c[-1] - T0_C) / base_rise
    left = (result.sensor_c[-1] - T0_C) / (result.sensor_c.max() - T0_C)
    assert left < base_left - 0.05
    # at standstill, no effect
    still = (_braking()[0], np.zeros(N_S))
    np.testing.assert_allclose(
        _run(default_rom, [effect], pv=still).sensor_c, _run(default_rom, pv=still).sensor_c
    )


def _flat_plate_h(v_kmh: float) -> float:
    """Incropera eqs. 7.30 / 7.38 for a 0.236 m plate in air at 300 K, written out."""
    length = 0.46 * math.radians(29.4)
    re = v_kmh / 3.6 * length / 15.89e-6
    nu = (0.664 * re**0.5 if re <= 5e5 else 0.037 * re**0.8 - 871) * 0.707 ** (1 / 3)
    return nu * 0.0263 / length


def test_convection_flat_plate_is_the_correlation():
    for v in (10.0, 50.0, 100.0, 160.0):  # 160 km/h: Re above 5e5, the mixed branch
        assert float(ConvectionFlatPlate.h_forced(np.array(v))) == pytest.approx(
            _flat_plate_h(v), rel=1e-12
        )
    # at 100 km/h: Re = 4.1e5, Nu = 380, h = 42 W/m^2 K
    assert float(ConvectionFlatPlate.h_forced(np.array(100.0))) == pytest.approx(42.3, abs=0.1)
    law = ConvectionFlatPlate(multiplier=0.4)
    changed = law.apply_to_inputs(_inputs())
    for face in ("air", "holder"):
        np.testing.assert_allclose(changed.h_w_m2k[face], 10.0 + 0.4 * _flat_plate_h(50.0))
    # the branches nearly join at the critical Reynolds number (within 2 %)
    v_c = 5e5 * 15.89e-6 / (0.46 * math.radians(29.4)) * 3.6
    below, above = ConvectionFlatPlate.h_forced(np.array([v_c * (1 - 1e-9), v_c * (1 + 1e-9)]))
    assert above == pytest.approx(below, rel=0.02) and above != below


@pytest.mark.parametrize("effect", _draws(ConvectionFlatPlate), ids=str)
def test_convection_flat_plate_lowers_the_peak_and_cools_faster(default_rom, base, effect):
    result = _run(default_rom, [effect])
    base_rise = base.sensor_c.max() - T0_C
    assert result.sensor_c.max() < base.sensor_c.max() - 0.01 * base_rise
    left = (result.sensor_c[-1] - T0_C) / (result.sensor_c.max() - T0_C)
    assert left < (base.sensor_c[-1] - T0_C) / base_rise - 0.05
    still = (_braking()[0], np.zeros(N_S))
    np.testing.assert_allclose(
        _run(default_rom, [effect], pv=still).sensor_c, _run(default_rom, pv=still).sensor_c
    )


@pytest.mark.parametrize("effect", _draws(HolderConduction), ids=str)
def test_holder_conduction_cools_faster(default_rom, base, effect):
    result = _run(default_rom, [effect])
    base_rise = base.sensor_c.max() - T0_C
    assert result.sensor_c.max() < base.sensor_c.max()
    left = (result.sensor_c[-1] - T0_C) / (result.sensor_c.max() - T0_C)
    assert left < (base.sensor_c[-1] - T0_C) / base_rise - 0.1
    # the sensor sits in the lug, next to the holder: it feels the holder more than the face
    face_drop = base.contact_max_c.max() - result.contact_max_c.max()
    sensor_drop = base.sensor_c.max() - result.sensor_c.max()
    assert sensor_drop > face_drop >= 0


@pytest.mark.parametrize("effect", _draws(AmbientOffset), ids=str)
def test_ambient_offset_shifts_the_steady_state(default_rom, effect):
    n = 150_000  # ~14 time constants of the block's cooling
    pv = (np.zeros(n), np.zeros(n))
    result = _run(default_rom, [effect], pv=pv, keep_state=False)
    plain = _run(default_rom, pv=pv, keep_state=False)
    np.testing.assert_allclose(plain.sensor_c, T0_C, atol=1e-9)
    assert result.sensor_c[-1] - T0_C == pytest.approx(
        effect.offset_k, abs=0.01 * abs(effect.offset_k)
    )
    assert result.contact_mean_c[-1] - T0_C == pytest.approx(
        effect.offset_k, abs=0.01 * abs(effect.offset_k)
    )
    # and moves towards it monotonically
    assert np.all(np.sign(np.diff(result.sensor_c[1:])) * np.sign(effect.offset_k) >= 0)


@pytest.mark.parametrize("effect", _draws(SensorLag), ids=str)
def test_sensor_lag_delays_the_reading_by_about_tau(default_rom, base, effect):
    result = _run(default_rom, [effect])
    tau = effect.tau_s
    np.testing.assert_array_equal(result.seat_c, base.sensor_c)  # the block is the same
    np.testing.assert_array_equal(result.contact_max_c, base.contact_max_c)
    level = T0_C + 0.5 * (base.sensor_c.max() - T0_C)
    delay = int(np.argmax(result.sensor_c >= level)) - int(np.argmax(base.sensor_c >= level))
    assert 0.7 * tau <= delay <= 1.2 * tau + 1
    assert result.sensor_c.argmax() - base.sensor_c.argmax() >= 0.7 * tau
    assert result.sensor_c.max() <= base.sensor_c.max()


@pytest.mark.parametrize("effect", _draws(SensorLagTwoStage), ids=str)
def test_two_stage_sensor_lag_is_two_lags_in_series(default_rom, base, effect):
    result = _run(default_rom, [effect])
    np.testing.assert_array_equal(result.seat_c, base.sensor_c)
    expected = first_order_lag(
        first_order_lag(base.sensor_c, 1.0, effect.tau_contact_s), 1.0, effect.tau_body_s
    )
    np.testing.assert_allclose(result.sensor_c, expected, atol=1e-12)
    # later than either lag alone
    for tau in (effect.tau_contact_s, effect.tau_body_s):
        single = _run(default_rom, [SensorLag(tau_s=tau)])
        assert result.sensor_c.argmax() > single.sensor_c.argmax()
    # the chain simulation carries one lag: asking it for one time constant is an error
    with pytest.raises(ValueError, match="two time constants"):
        _ = effect.tau_s


def test_empirical_is_no_change_at_zero_and_linear_in_its_parameters():
    inputs = _inputs()
    same = Empirical().apply_to_inputs(inputs)
    np.testing.assert_array_equal(same.flux_w_m2, inputs.flux_w_m2)
    for face in inputs.h_w_m2k:
        np.testing.assert_array_equal(same.h_w_m2k[face], inputs.h_w_m2k[face])
    np.testing.assert_array_equal(same.ambient_c, inputs.ambient_c)
    law = Empirical(flux_gain=0.1, flux_speed_gain=-0.2, h_extra_w_m2k=2.0, h_speed_w_m2k=4.0)
    out = law.apply_to_inputs(inputs)
    v = 50.0 / 100.0
    np.testing.assert_allclose(out.flux_w_m2, 1e4 * (1 + 0.1 - 0.2 * v))
    for face in ("air", "holder"):
        np.testing.assert_allclose(out.h_w_m2k[face], 10.0 + 2.0 + 4.0 * v)
    # never a negative heat input or coefficient
    cut = Empirical(flux_gain=-0.9, flux_speed_gain=-2.0, h_extra_w_m2k=-9.0, h_speed_w_m2k=-50)
    out = cut.apply_to_inputs(inputs)
    assert np.all(out.flux_w_m2 == 0.0) and np.all(out.h_w_m2k["air"] == 0.0)
    assert Empirical.fallback and not any(cls.fallback for cls in EFFECT_ORDER[:-1])
    assert EFFECT_ORDER[-1] is Empirical


# --------------------------------------------------------------------------------------------
# Sets, parameters, serialisation


def test_the_whole_vocabulary_is_here_with_its_laws():
    assert (
        set(EFFECTS)
        == set(LAWS)
        == {
            "friction_speed",
            "friction_temperature",
            "convection_speed",
            "sensor_lag",
            "heat_partition",
            "holder_conduction",
            "ambient_offset",
            "empirical",
        }
    )
    assert {cls.law for cls in LAWS["convection_speed"]} == {"power", "flat_plate"}
    # each family's laws in the order an effect's text infers its law from
    assert {name: tuple(laws) for name, laws in FAMILY_LAWS.items()} == dict(LAWS)
    assert EFFECTS["friction_speed"] is FrictionSpeed
    assert EFFECTS["heat_partition"] is HeatPartitionEffusivity
    # the candidates: one of each name at least, the laws kept for stored sets out, empirical
    # last
    assert {cls.name for cls in EFFECT_ORDER} == set(EFFECTS)
    assert FrictionSpeedNormalised not in EFFECT_ORDER and HeatPartition not in EFFECT_ORDER
    for cls in EFFECT_CLASSES:
        assert cls.__doc__ and cls.law, cls
        assert set(cls.PARAMETER_RANGES) == set(cls.parameter_names()), cls  # all free
        for key, (low, high) in cls.PARAMETER_RANGES.items():
            assert low < high
            limits = cls.LIMITS[key]
            assert limits[0] is None or limits[0] <= low
            assert limits[1] is None or high <= limits[1]
    assert len({(cls.name, cls.law) for cls in EFFECT_CLASSES}) == len(EFFECT_CLASSES)
    # a fade is a fade: the fit may not turn it into a friction rising with the heat (else an
    # hour-of-day misfit can be fitted as a negative fade_per_k through the face temperature)
    assert FrictionTemperature.LIMITS["fade_per_k"][0] == 0.0


@pytest.mark.parametrize("cls", EFFECT_CLASSES, ids=lambda c: f"{c.name}-{c.law}")
def test_parameters_round_trip_through_json(cls):
    rng = np.random.default_rng(3)
    for _ in range(5):
        effect = cls.random(rng)
        for key, (low, high) in cls.PARAMETER_RANGES.items():
            assert low <= getattr(effect, key) <= high
        text = json.dumps(effect.to_dict())
        back = effect_from_dict(json.loads(text))
        assert back == effect and type(back) is cls
        assert parse_effect(str(effect)) == effect
        assert cls.from_parameters(effect.parameters) == effect


def _one_law_each(rng, which: int = 0):
    """One effect per vocabulary name: the ``which``-th candidate law (the last if fewer)."""
    chosen = []
    for name in EFFECTS:
        laws = [cls for cls in EFFECT_ORDER if cls.name == name]
        chosen.append(laws[min(which, len(laws) - 1)].random(rng))
    return chosen


@pytest.mark.parametrize("which", [0, 1])
def test_effect_sets_are_ordered_unique_and_serialisable(which):
    rng = np.random.default_rng(5)
    effects = _one_law_each(rng, which)
    forward, backward = EffectSet(tuple(effects)), EffectSet(tuple(reversed(effects)))
    assert forward == backward
    order = [cls for cls in EFFECT_CLASSES if cls in {type(e) for e in effects}]
    assert [type(e) for e in forward] == order
    assert EffectSet.from_json(forward.to_json()) == forward
    assert all(item["law"] == e.law for item, e in zip(forward.to_list(), forward, strict=True))
    assert forward.state_dependent and not EffectSet((SensorLag(),)).state_dependent
    assert str(EffectSet()) == "declared"
    replaced = forward.with_effect(SensorLag(tau_s=10.0))
    assert replaced.get("sensor_lag") == SensorLag(tau_s=10.0) and len(replaced) == len(forward)
    with pytest.raises(ValueError, match="at most once"):
        EffectSet((SensorLag(), SensorLag(tau_s=5.0)))
    with pytest.raises(ValueError, match="at most once"):  # two laws of one name
        EffectSet((ConvectionSpeed(), ConvectionFlatPlate()))


def test_effect_sets_stored_without_laws_load_by_their_parameter_names():
    # parameters_json of revisions without a "law" key
    stored = json.dumps(
        [
            {
                "name": "friction_speed",
                "parameters": {"force_exponent": 0.1, "speed_scale_kmh": 90},
            },
            {"name": "heat_partition", "parameters": {"alpha": 0.78}},
            {"name": "convection_speed", "parameters": {"exponent": 0.8, "gain": 2.0}},
            {"name": "sensor_lag", "parameters": {"tau_s": 35.0}},
            {"name": "holder_conduction", "parameters": {"h_holder_extra_w_m2k": 60.0}},
            {"name": "ambient_offset", "parameters": {"offset_k": 1.5}},
            {"name": "friction_temperature", "parameters": {"fade_per_k": 0.001}},
        ]
    )
    loaded = EffectSet.from_json(stored)
    assert loaded.get("friction_speed") == FrictionSpeedNormalised(
        speed_scale_kmh=90.0, force_exponent=0.1
    )
    assert loaded.get("heat_partition") == HeatPartition(alpha=0.78)
    assert loaded.get("convection_speed") == ConvectionSpeed(gain=2.0, exponent=0.8)
    assert loaded.get("sensor_lag") == SensorLag(tau_s=35.0)
    assert loaded.get("holder_conduction") == HolderConduction(h_holder_extra_w_m2k=60.0)
    assert loaded.get("ambient_offset") == AmbientOffset(offset_k=1.5)
    assert loaded.get("friction_temperature") == FrictionTemperature(fade_per_k=0.001)
    # and written again, with their laws, they read back the same
    assert EffectSet.from_json(loaded.to_json()) == loaded
    # the command line's spellings without a law too
    assert parse_effect("heat_partition:alpha=0.8") == HeatPartition(alpha=0.8)
    assert parse_effect("friction_speed:speed_scale_kmh=80,force_exponent=0.2") == (
        FrictionSpeedNormalised(speed_scale_kmh=80.0, force_exponent=0.2)
    )
    assert parse_effect("friction_speed:level=1.1") == FrictionSpeed(level=1.1)
    assert parse_effect("convection_speed:law=flat_plate") == ConvectionFlatPlate()
    assert parse_effect("convection_speed:multiplier=0.3") == ConvectionFlatPlate(multiplier=0.3)


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="unknown effect"):
        parse_effect("emprical")
    with pytest.raises(ValueError, match="unknown parameter"):
        parse_effect("sensor_lag:tau=3")
    with pytest.raises(ValueError, match="unknown law"):
        parse_effect("sensor_lag:law=third_order")
    with pytest.raises(ValueError, match="unknown law"):
        effect_from_dict({"name": "convection_speed", "law": "cylinder", "parameters": {}})
    with pytest.raises(ValueError, match="unknown parameter"):
        effect_from_dict({"name": "convection_speed", "law": "power", "parameters": {"x": 1}})
    with pytest.raises(ValueError, match="must be a number"):
        parse_effect("sensor_lag:tau_s=fast")
    with pytest.raises(ValueError, match="tau_s must be in"):
        SensorLag(tau_s=-1.0)
    with pytest.raises(ValueError, match="finite number"):
        HeatPartition(alpha=float("nan"))
    with pytest.raises(ValueError, match="finite number"):
        effect_from_dict({"name": "ambient_offset", "parameters": {"offset_k": True}})
    assert parse_effect(" convection_speed : gain = 1.5 ") == ConvectionSpeed(gain=1.5)
    assert parse_effect("empirical") == Empirical()


def _inputs(n: int = 4) -> DriveInputs:
    return DriveInputs(
        dt_s=1.0,
        speed_kmh=np.full(n, 50.0),
        block_force_n=np.full(n, 1000.0),
        flux_w_m2=np.full(n, 1e4),
        alpha=0.7455,
        ambient_c=np.full(n, 10.0),
        h_w_m2k={"air": np.full(n, 10.0), "holder": np.full(n, 10.0)},
        contact_c=np.full(n, 120.0),
        friction_coefficient=0.15,
    )


@pytest.mark.parametrize("which", [0, 1])
def test_effects_leave_their_inputs_alone(which):
    inputs = _inputs()
    rng = np.random.default_rng(9)
    chosen = [e for e in _one_law_each(rng, which) if not isinstance(e, Empirical)]
    changed = EffectSet(tuple(chosen)).apply_to_inputs(inputs)
    assert np.all(inputs.flux_w_m2 == 1e4) and np.all(inputs.h_w_m2k["holder"] == 10.0)
    assert np.all(inputs.ambient_c == 10.0)
    assert not np.allclose(changed.flux_w_m2, 1e4)
    assert np.all(changed.h_w_m2k["holder"] > changed.h_w_m2k["air"])
