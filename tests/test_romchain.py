"""The close loop's chain (``fleetbrake.model.romchain``): the reduced model's chain kernel with
the sensor and the face mean only, its step systems found in Rust, against
:meth:`ReducedModel.simulate_chain` (bit for bit) on a small model whose convection switches
among recurring values on two time steps."""

from __future__ import annotations

import numpy as np
import pytest

from fleetbrake import _ext
from fleetbrake.model.rom import ChainPieces, ChainRule, ReducedModel
from fleetbrake.model.romchain import simulate_chain_sensor


def toy_model(order: int = 6) -> ReducedModel:
    """A reduced model of ``order`` modes, two face sets (air at 10 W/m2K nominal, friction
    at 0), one probe, the face mean and three face nodes."""
    rng = np.random.default_rng(3)
    faces = []
    for _ in range(2):
        a = rng.normal(size=(order, order)) * 0.01
        faces.append(a @ a.T)
    arrays = {
        "lam": np.geomspace(1e-3, 0.5, order),
        "b_flux": rng.normal(size=order) * 1e-4,
        "b_faces": rng.normal(size=(2, order)) * 1e-2,
        "h_faces": np.stack(faces),
        "c_out": rng.normal(size=(5, order)),
    }
    meta = {"face_names": ["air", "friction"], "h_nominal": {"air": 10.0}, "n_probes": 1}
    return ReducedModel(arrays, meta)


def chain(h_air: np.ndarray) -> tuple[ChainPieces, np.ndarray, np.ndarray]:
    """Three segments (the last on a 5 s grid), a window continued past the second: the
    pieces, the trusted readings and the air of a 121 s span; ``h_air`` per step (118)."""
    steps = 118
    flux = np.where((np.arange(steps) // 10) % 3 == 0, 4e4, 0.0)
    h = np.column_stack([h_air, np.where(np.arange(steps) % 17 < 4, 2.0, 0.0)])
    pieces = ChainPieces(
        a=np.array([0, 40, 80, 80]),
        b=np.array([40, 80, 120, 110]),
        dt_s=np.array([1.0, 1.0, 5.0, 1.0]),
        step_offsets=np.array([0, 40, 80, 88, 118]),
        at=np.arange(80.0, 121.0, 5.0),
        at_offsets=np.array([0, 0, 0, 9, 9]),
        flux_w_m2=flux,
        ambient_c=8.0 + 0.05 * np.arange(steps),
        h_w_m2k=h,
        window_continuation=np.array([-1, 3, -1]),
        window_length=np.array([0, 60, 0]),
    )
    trusted = np.full(121, np.nan)
    trusted[:3], trusted[35:40], trusted[80:86] = 21.0, 60.0, 20.0
    return pieces, trusted, np.full(121, 9.0)


def switching_air(seed: int) -> np.ndarray:
    """Air convection per step in runs of recurring quantised values (as a convection law of
    speed gives after rounding), the nominal among them."""
    rng = np.random.default_rng(seed)
    values = 10.0 + 0.25 * rng.integers(0, 9, size=40)
    return np.repeat(values, 3)[:118]


@pytest.mark.parametrize("lag_tau_s", [None, 20.0])
def test_the_sensor_and_face_mean_are_simulate_chains_bit_for_bit(lag_tau_s):
    model = toy_model()
    pieces, trusted, air = chain(switching_air(5))
    rule = ChainRule(5, 3, 10, 1e-3, lag_tau_s)
    full = model.simulate_chain(pieces, trusted_c=trusted, ambient_c=air, rule=rule)
    got = simulate_chain_sensor(model, pieces, trusted_c=trusted, ambient_c=air, rule=rule)
    for name in (
        "sensor_c",
        "contact_mean_c",
        "shift_k",
        "reference_c",
        "window_sensor_c",
        "window_mean_c",
    ):
        assert np.array_equal(getattr(got, name), getattr(full, name), equal_nan=True), name
    assert np.array_equal(got.anchor, full.anchor)
    assert np.isnan(got.contact_max_c).all() and np.isnan(got.window_max_c).all()
    assert got.window_max_c.size == full.window_max_c.size == 60
    # the convection matters here: the nominal one everywhere gives another chain
    nominal, _, _ = chain(np.full(118, 10.0))
    other = simulate_chain_sensor(model, nominal, trusted_c=trusted, ambient_c=air, rule=rule)
    assert np.nanmax(np.abs(other.window_sensor_c - got.window_sensor_c)) > 1e-3


def test_each_step_gets_its_own_rounded_convection_and_time_step():
    pieces, _, _ = chain(switching_air(9) + 1e-14)  # the nominal off by less than the rounding
    h = np.ascontiguousarray(pieces.h_w_m2k)
    h_nominal = np.array([10.0, 0.0])
    dh, dt, index = _ext.rom_chain_systems(h, h_nominal, pieces.dt_s, pieces.step_offsets)
    step_dt = np.repeat(pieces.dt_s, np.diff(pieces.step_offsets))
    # what ReducedModel.simulate_chain keys each step's propagator by, step by step
    assert np.array_equal(dh[index], np.round(h - h_nominal, 12))
    assert np.array_equal(dt[index], step_dt)
    keys = np.column_stack([dh, dt])
    assert np.unique(keys, axis=0).shape[0] == keys.shape[0]  # each system once
    _, first = np.unique(index, return_index=True)
    assert np.all(np.diff(first) > 0)  # numbered in the order they first come
    assert dh.shape[0] < 40  # recurring values share a system
    assert (dh == 0.0).all(axis=1).any()  # the nominal's (off by less than the rounding)
    with pytest.raises(ValueError, match="face sets"):
        _ext.rom_chain_systems(h, np.zeros(3), pieces.dt_s, pieces.step_offsets)
