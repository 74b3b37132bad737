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
    EFFECT_ORDER,
    EFFECTS,
    AmbientOffset,
    ConvectionSpeed,
    DriveInputs,
    EffectSet,
    FrictionSpeed,
    FrictionTemperature,
    HeatPartition,
    HolderConduction,
    SensorLag,
    effect_from_dict,
    parse_effect,
)
from fleetbrake.model.physics import heat_partition_alpha, time_resolved_flux_series_w_m2
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


@pytest.mark.parametrize("effect", _draws(FrictionSpeed), ids=str)
def test_friction_speed_scales_the_heating_by_mu(default_rom, base, effect):
    # constant speed and force: the flux, hence (linear model) the rise, scales by mu / mu_0
    result = _run(default_rom, [effect])
    force = float(base.block_force_n[90])
    factor = float(effect.friction_factor(np.array(V_KMH), np.array(force)))
    expected_k = FrictionSpeed(effect.speed_scale_kmh, 0.0)._k(np.array(V_KMH)) / FrictionSpeed(
        effect.speed_scale_kmh, 0.0
    )._k(np.array(60.0))
    assert factor == pytest.approx(float(expected_k) * (force / 1500.0) ** -effect.force_exponent)
    assert factor < 1.0  # mu falls with speed; 80 km/h is above the reference 60
    np.testing.assert_allclose(result.sensor_c - T0_C, factor * (base.sensor_c - T0_C), atol=1e-9)
    assert result.sensor_c.max() < base.sensor_c.max() - 0.02 * (base.sensor_c.max() - T0_C)
    # slow: mu is higher than the reference's
    slow = _run(default_rom, [effect], pv=_braking(v_kmh=25.0))
    slow_base = _run(default_rom, pv=_braking(v_kmh=25.0))
    assert slow.sensor_c.max() > slow_base.sensor_c.max()


@pytest.mark.parametrize("effect", _draws(HeatPartition), ids=str)
def test_heat_partition_scales_the_blocks_share(default_rom, base, effect):
    result = _run(default_rom, [effect])
    factor = (1 - effect.alpha) / (1 - heat_partition_alpha(WAGON))
    np.testing.assert_allclose(result.sensor_c - T0_C, factor * (base.sensor_c - T0_C), atol=1e-9)
    np.testing.assert_allclose(result.flux_w_m2, factor * base.flux_w_m2, rtol=1e-12)
    # alpha above the declared 0.7455 means less heat in the block
    assert (result.sensor_c.max() < base.sensor_c.max()) == (effect.alpha > 0.7455)


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


# --------------------------------------------------------------------------------------------
# Sets, parameters, serialisation


def test_every_vocabulary_effect_but_empirical_is_here():
    assert set(EFFECTS) == {
        "friction_speed",
        "friction_temperature",
        "convection_speed",
        "sensor_lag",
        "heat_partition",
        "holder_conduction",
        "ambient_offset",
    }
    for cls in EFFECT_ORDER:
        assert cls.PARAMETER_RANGES, cls.name
        for key, (low, high) in cls.PARAMETER_RANGES.items():
            assert low < high
            limits = cls.LIMITS[key]
            assert limits[0] is None or limits[0] <= low
            assert limits[1] is None or high <= limits[1]


@pytest.mark.parametrize("cls", EFFECT_ORDER, ids=lambda c: c.name)
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


def test_effect_sets_are_ordered_unique_and_serialisable():
    rng = np.random.default_rng(5)
    effects = [cls.random(rng) for cls in EFFECT_ORDER]
    forward, backward = EffectSet(tuple(effects)), EffectSet(tuple(reversed(effects)))
    assert forward == backward
    assert forward.names == tuple(cls.name for cls in EFFECT_ORDER)
    assert EffectSet.from_json(forward.to_json()) == forward
    assert forward.state_dependent and not EffectSet((SensorLag(),)).state_dependent
    assert str(EffectSet()) == "declared"
    replaced = forward.with_effect(SensorLag(tau_s=10.0))
    assert replaced.get("sensor_lag") == SensorLag(tau_s=10.0) and len(replaced) == len(forward)
    with pytest.raises(ValueError, match="at most once"):
        EffectSet((SensorLag(), SensorLag(tau_s=5.0)))


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="unknown effect"):
        parse_effect("empirical")
    with pytest.raises(ValueError, match="unknown parameter"):
        parse_effect("sensor_lag:tau=3")
    with pytest.raises(ValueError, match="must be a number"):
        parse_effect("sensor_lag:tau_s=fast")
    with pytest.raises(ValueError, match="tau_s must be in"):
        SensorLag(tau_s=-1.0)
    with pytest.raises(ValueError, match="finite number"):
        HeatPartition(alpha=float("nan"))
    with pytest.raises(ValueError, match="finite number"):
        effect_from_dict({"name": "ambient_offset", "parameters": {"offset_k": True}})
    assert parse_effect(" convection_speed : gain = 1.5 ") == ConvectionSpeed(gain=1.5)


def test_effects_leave_their_inputs_alone():
    n = 4
    inputs = DriveInputs(
        dt_s=1.0,
        speed_kmh=np.full(n, 50.0),
        block_force_n=np.full(n, 1000.0),
        flux_w_m2=np.full(n, 1e4),
        alpha=0.7455,
        ambient_c=np.full(n, 10.0),
        h_w_m2k={"air": np.full(n, 10.0), "holder": np.full(n, 10.0)},
        contact_c=np.full(n, 120.0),
    )
    rng = np.random.default_rng(9)
    changed = EffectSet(tuple(cls.random(rng) for cls in EFFECT_ORDER)).apply_to_inputs(inputs)
    assert np.all(inputs.flux_w_m2 == 1e4) and np.all(inputs.h_w_m2k["holder"] == 10.0)
    assert np.all(inputs.ambient_c == 10.0)
    assert not np.allclose(changed.flux_w_m2, 1e4)
    assert np.all(changed.h_w_m2k["holder"] > changed.h_w_m2k["air"])
