"""Synthetic effects that drift over the calendar (a component that degrades)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fleetbrake.model.effects import ConvectionSpeed, EffectSet, SensorLag
from fleetbrake.synth.config import SynthConfig
from fleetbrake.synth.generator import generate_fleet

GAIN = ConvectionSpeed(gain=2.0, exponent=0.8)


def test_the_drifting_parameter_moves_by_its_rate():
    config = SynthConfig.clean(effects=EffectSet((GAIN,)), effect_drift_per_day={"gain": 0.5})
    assert config.effects_on_day(0.0) == EffectSet((GAIN,))
    on_day_2 = config.effects_on_day(2.0).get("convection_speed")
    assert isinstance(on_day_2, ConvectionSpeed)
    assert on_day_2.gain == pytest.approx(3.0) and on_day_2.exponent == 0.8
    qualified = dataclasses.replace(config, effect_drift_per_day={"convection_speed.gain": -0.5})
    assert qualified.effects_on_day(1.0).get("convection_speed").gain == pytest.approx(1.5)  # type: ignore[union-attr]
    # the drift survives the truth's round trip
    assert SynthConfig.from_dict(config.to_dict()) == config


def test_a_drift_that_names_nothing_or_the_sensor_is_refused():
    with pytest.raises(ValueError, match="'tau' names 0 parameters"):
        SynthConfig.clean(effects=EffectSet((GAIN,)), effect_drift_per_day={"tau": 1.0})
    lag = EffectSet((SensorLag(tau_s=60.0),))
    with pytest.raises(ValueError, match="acts on the sensor"):
        SynthConfig.clean(effects=lag, effect_drift_per_day={"tau_s": 1.0})
    with pytest.raises(ValueError, match="finite"):
        SynthConfig.clean(effects=EffectSet((GAIN,)), effect_drift_per_day={"gain": np.nan})


def test_a_drifting_convection_cools_the_later_days_more(tmp_path, reduced_model_for):
    steady = SynthConfig.clean(wagons=1, days=2, seed=5, effects=EffectSet((GAIN,)))
    drifting = dataclasses.replace(steady, effect_drift_per_day={"gain": 2.0})
    a = generate_fleet(tmp_path / "steady", steady, rom=reduced_model_for)
    b = generate_fleet(tmp_path / "drifting", drifting, rom=reduced_model_for)
    sa, sb = a.series("SGG-0001"), b.series("SGG-0001")
    assert sa["brake_pressure_bar"].to_list() == sb["brake_pressure_bar"].to_list()
    rise_a = sa["contact_mean_c"].to_numpy() - sa["ambient_c"].to_numpy()
    rise_b = sb["contact_mean_c"].to_numpy() - sb["ambient_c"].to_numpy()
    first, second = slice(0, 6 * 3600), slice(86_400, 2 * 86_400)
    # the first hours alike, the second day cooler by more convection
    assert np.mean(np.abs(rise_b[first] - rise_a[first])) < 0.05 * np.mean(np.abs(rise_a[first]))
    assert np.mean(rise_b[second]) < 0.9 * np.mean(rise_a[second])
