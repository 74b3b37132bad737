"""The close loop's chain (``fleetbrake.model.romchain``): the reduced model's chain kernel with
the sensor and the face mean only, its step systems found in Rust, against
:meth:`ReducedModel.simulate_chain` (bit for bit) on a small model whose convection switches
among recurring values on two time steps."""

from __future__ import annotations

import numpy as np
import pytest

from fleetbrake import _ext
from fleetbrake.model.chaintypes import ChainPieces, ChainRule
from fleetbrake.model.rom import ReducedModel
from fleetbrake.model.romchain import chain_convection, simulate_chain_sensor


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


def numpy_step_convection(
    samples: list[list[np.ndarray]], gather: np.ndarray, step_offsets: np.ndarray, quantum: float
) -> np.ndarray:
    """The close loop's former numpy path (``fitdata`` before the Rust pass): each source's
    step means concatenated and gathered, per face set; a face set varying inside a piece
    rounded to ``quantum`` on that piece."""
    h = np.column_stack(
        [np.concatenate([0.5 * (x[:-1] + x[1:]) for x in face])[gather] for face in samples]
    )
    starts = step_offsets[:-1]
    varying = np.maximum.reduceat(h, starts, axis=0) != np.minimum.reduceat(h, starts, axis=0)
    rows = np.repeat(varying, np.diff(step_offsets), axis=0)
    return np.where(rows, np.round(h / quantum) * quantum, h)


def convection_sources(seed: int) -> tuple[list[list[np.ndarray]], np.ndarray, np.ndarray]:
    """Two face sets on a fine source of 81 samples and two coarse ones (9 and 5 samples):
    air varying (a law of a speed, values half way between quanta among them), friction
    constant but on one coarse source; the chain's 88 steps: fine 0..40, coarse 0..8, fine
    40..80, coarse 8..12 (four pieces)."""
    rng = np.random.default_rng(seed)
    speed = [rng.uniform(0.0, 120.0, size=n) for n in (81, 9, 5)]
    air = [10.0 * (1.0 + 2.1 * (v / 100.0) ** 0.8) for v in speed]
    air[0][10:14] = [10.125, 10.125, 10.375, 10.375]  # step means exactly half way
    air[2][:] = 12.3  # constant on its piece: not rounded
    friction = [np.zeros(81), np.linspace(0.0, 3.3, 9), np.zeros(5)]
    gather = np.concatenate(
        [np.arange(40), 80 + np.arange(8), 40 + np.arange(40), 88 + np.arange(4)]
    )
    return [air, friction], gather, np.array([0, 40, 48, 88, 92])


def test_the_convection_pass_is_numpys_step_means_gathered_and_rounded_bit_for_bit():
    model = toy_model()
    samples, gather, step_offsets = convection_sources(4)
    piece_dt = np.array([1.0, 10.0, 1.0, 12.0])
    h, (dh, dt, index) = chain_convection(
        model,
        samples,
        gather=gather,
        step_offsets=step_offsets,
        piece_dt_s=piece_dt,
        quantum_w_m2k=0.25,
    )
    expected = numpy_step_convection(samples, gather, step_offsets, 0.25)
    assert h.shape == (92, 2)
    assert np.array_equal(h, expected)
    assert np.array_equal(h[88:, 0], np.full(4, 12.3))  # the constant piece as it is
    assert h[10, 0] == 10.0 and h[12, 0] == 10.5  # 40.5 -> 40, 41.5 -> 42: half to even
    # the systems are rom_chain_systems' of that convection
    ref = _ext.rom_chain_systems(
        np.ascontiguousarray(expected), model._h_nominal_by_face(), piece_dt, step_offsets
    )
    for got, want in zip((dh, dt, index), ref, strict=True):
        assert np.array_equal(got, want)
    # a step gathered from its neighbour, or the pieces cut elsewhere, give another
    # convection: the pass reads both
    for other_gather, other_offsets in (
        (np.roll(gather, 1), step_offsets),
        (gather, np.array([0, 40, 48, 86, 92])),
    ):
        moved, _ = chain_convection(
            model,
            samples,
            gather=other_gather,
            step_offsets=other_offsets,
            piece_dt_s=piece_dt,
            quantum_w_m2k=0.25,
        )
        assert np.array_equal(
            moved, numpy_step_convection(samples, other_gather, other_offsets, 0.25)
        )
        assert not np.array_equal(moved, h)
    with pytest.raises(ValueError, match="face sets"):
        chain_convection(
            model,
            samples[:1],
            gather=gather,
            step_offsets=step_offsets,
            piece_dt_s=piece_dt,
            quantum_w_m2k=0.25,
        )
    with pytest.raises(ValueError, match="gather"):
        chain_convection(
            model,
            samples,
            gather=gather + 10,
            step_offsets=step_offsets,
            piece_dt_s=piece_dt,
            quantum_w_m2k=0.25,
        )


@pytest.mark.parametrize("lag_tau_s", [None, 20.0])
def test_outputs_only_where_read_are_the_full_runs_bit_for_bit(lag_tau_s):
    """The window seconds wanted (some in the braking segment, some in its continuation):
    those of the full run bit for bit, the anchoring the same; without a lag the others NaN
    but where the anchoring reads the timeline (the 5 s before and the first 5 s of a
    segment: window seconds 0..4, 35..40); under a lag every output."""
    model = toy_model()
    pieces, trusted, air = chain(switching_air(5))
    rule = ChainRule(5, 3, 10, 1e-3, lag_tau_s)
    full = simulate_chain_sensor(model, pieces, trusted_c=trusted, ambient_c=air, rule=rule)
    wanted = np.zeros(60, dtype=bool)
    wanted[[7, 20, 41, 42, 55, 59]] = True
    got = simulate_chain_sensor(
        model, pieces, trusted_c=trusted, ambient_c=air, rule=rule, windows=wanted
    )
    assert np.array_equal(got.anchor, full.anchor)
    assert np.array_equal(got.shift_k, full.shift_k)
    assert np.array_equal(got.reference_c, full.reference_c)
    read = wanted.copy()
    if lag_tau_s is None:
        read[[0, 1, 2, 3, 4, 35, 36, 37, 38, 39, 40]] = True  # samples 40..44, 75..80
    else:
        read[:] = True
    for name in ("window_sensor_c", "window_mean_c"):
        ours, theirs = getattr(got, name), getattr(full, name)
        assert np.array_equal(ours[read], theirs[read]), name
        assert np.isnan(ours[~read]).all(), name
    # a mask moved by one second gives NaN where the fit reads
    moved = simulate_chain_sensor(
        model, pieces, trusted_c=trusted, ambient_c=air, rule=rule, windows=np.roll(wanted, 1)
    )
    if lag_tau_s is None:
        assert np.isnan(moved.window_sensor_c[[7, 20, 41, 55]]).all()
    with pytest.raises(ValueError, match="window outputs"):
        simulate_chain_sensor(
            model, pieces, trusted_c=trusted, ambient_c=air, rule=rule, windows=wanted[1:]
        )
