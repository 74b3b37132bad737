"""The reduced model against the full finite-element model (issue: fleet speed).

Both are integrated with the same Crank-Nicolson scheme at 1 s steps, so what is compared is
the reduction alone: sensor within 0.02 K, friction-face mean within 0.1 K, on the paper's
manoeuvres and on generated sessions with every kind of change the closed loop makes (a
convection coefficient varying with speed, more convection on one face set, an ambient
offset, a different heat partition, a speed-dependent heat input, a lagging sensor).
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.physics import PAPER_MANOEUVRES, event_flux_series_w_m2
from fleetbrake.model.rom import ReducedModel, first_order_lag
from fleetbrake.model.thermal import BlockModel, InvalidParameterError, LengthMismatchError

REFINEMENT = 0.6
WAGON = WagonConfig(wagon_id="ROM-TEST")


@pytest.fixture(scope="module")
def full_model() -> BlockModel:
    return BlockModel(
        WAGON.geometry, WAGON.block_material, refinement=REFINEMENT, sensor_m=WAGON.sensor_point_m
    )


@pytest.fixture(scope="module")
def rom(tmp_path_factory: pytest.TempPathFactory) -> ReducedModel:
    cache = tmp_path_factory.mktemp("rom-cache")
    return ReducedModel.for_wagon(WAGON, refinement=REFINEMENT, cache_dir=cache)


def session(seconds: int, seed: int) -> dict[str, np.ndarray]:
    """A generated session: a speed profile with stops and brakings (cylinder filling over
    20 s, release over 45 s), a drag application, and a drifting ambient."""
    rng = np.random.default_rng(seed)
    t = np.arange(seconds, dtype=np.float64)
    speed_kmh = np.clip(60 + 35 * np.sin(t / 400.0) + rng.normal(0, 1, seconds), 0, 100)
    flux = np.zeros(seconds)
    for start in rng.choice(
        np.arange(60, seconds - 300), size=max(2, seconds // 900), replace=False
    ):
        length = int(rng.integers(30, 120))
        level = rng.uniform(1.5e4, 6e4)
        ramp = np.clip((t - start) / 20.0, 0, 1) * np.clip((start + length + 45 - t) / 45.0, 0, 1)
        flux += level * ramp * (speed_kmh / 80.0)
    drag = slice(seconds // 2, seconds // 2 + 240)
    flux[drag] += 5e3
    ambient = 8.0 + 4.0 * np.sin(t / 3000.0)
    return {"flux": flux, "speed": speed_kmh, "ambient": ambient}


def compare(full_model, rom, *, flux, initial_c, ambient, h=None, lag_s=0.0):
    probe = [WAGON.sensor_point_m]
    full = full_model.simulate(
        dt_s=1.0, flux_w_m2=flux, initial_c=initial_c, ambient_c=ambient, h_w_m2k=h, probes_m=probe
    )
    red = rom.simulate(
        dt_s=1.0,
        flux_w_m2=flux,
        initial_c=initial_c,
        ambient_c=ambient,
        h_w_m2k=h,
        scheme="crank-nicolson",
    )
    sensor_full = first_order_lag(full.probe_c[:, 0], 1.0, lag_s)
    sensor_red = first_order_lag(red.probe_c[:, 0], 1.0, lag_s)
    return (
        float(np.abs(sensor_full - sensor_red).max()),
        float(np.abs(full.face_mean_c - red.face_mean_c).max()),
        float(np.abs(full.face_max_c - red.face_max_c).max()),
        full,
    )


def test_order_is_chosen_by_the_a_posteriori_check(rom):
    check = rom.meta["check"]
    assert check["passed"], check
    assert check["max_error_sensor_k"] <= check["tol_sensor_k"]
    assert 8 <= rom.order <= 120
    assert rom.meta["face_max_nodes"] >= 1


@pytest.mark.parametrize("name", ["A", "B"])
def test_paper_manoeuvres(full_model, rom, name):
    manoeuvre = PAPER_MANOEUVRES[name]
    flux = event_flux_series_w_m2(WAGON, manoeuvre, 1200)
    e_sensor, e_mean, e_max, full = compare(
        full_model, rom, flux=flux, initial_c=manoeuvre.t0_c, ambient=WAGON.ambient_temp_c
    )
    assert full.probe_c[:, 0].max() - manoeuvre.t0_c > 5.0  # the block did heat
    assert e_sensor < 0.02, e_sensor
    assert e_mean < 0.1, e_mean
    assert e_max < 0.1, e_max


EFFECTS = {
    "declared": {},
    "convection_speed": {"h": "speed"},
    "holder_conduction": {"h": {"air": 10.0, "holder": 60.0}},
    "ambient_offset": {"ambient_offset": 4.0},
    "heat_partition": {"flux_scale": 1.3},
    "friction_speed": {"flux_speed": True},
    "sensor_lag": {"lag_s": 25.0},
}


def loading_with(effect: dict, s: dict[str, np.ndarray]):
    flux = s["flux"] * effect.get("flux_scale", 1.0)
    if effect.get("flux_speed"):
        flux = flux * (1.0 + 0.004 * (80.0 - s["speed"]))  # friction higher at low speed
    ambient = s["ambient"] + effect.get("ambient_offset", 0.0)
    h = effect.get("h")
    if h == "speed":
        h_air = 10.0 * (1.0 + 0.02 * np.round(s["speed"]))  # 10 .. 30 W/m^2 K
        h = {"air": h_air, "holder": h_air}
    return flux, ambient, h


@pytest.mark.parametrize("effect", list(EFFECTS))
def test_generated_session_with_each_effect(full_model, rom, effect):
    s = session(1800, seed=list(EFFECTS).index(effect))
    flux, ambient, h = loading_with(EFFECTS[effect], s)
    e_sensor, e_mean, e_max, _ = compare(
        full_model,
        rom,
        flux=flux,
        initial_c=35.0,
        ambient=ambient,
        h=h,
        lag_s=EFFECTS[effect].get("lag_s", 0.0),
    )
    assert e_sensor < 0.02, (effect, e_sensor)
    assert e_mean < 0.1, (effect, e_mean)
    assert e_max < 0.15, (effect, e_max)


@pytest.mark.slow
@pytest.mark.parametrize("effect", list(EFFECTS))
def test_sessions_of_several_hours_with_each_effect(full_model, rom, effect):
    s = session(4 * 3600, seed=100 + list(EFFECTS).index(effect))
    flux, ambient, h = loading_with(EFFECTS[effect], s)
    e_sensor, e_mean, _, _ = compare(
        full_model,
        rom,
        flux=flux,
        initial_c=20.0,
        ambient=ambient,
        h=h,
        lag_s=EFFECTS[effect].get("lag_s", 0.0),
    )
    assert e_sensor < 0.02 and e_mean < 0.1, (effect, e_sensor, e_mean)


def test_exact_integration_is_time_step_independent(rom):
    """Exact for inputs held over a step: one 10 s step equals ten 1 s steps."""
    flux = np.repeat([4e4, 0.0, 2e4, 0.0], [6, 10, 4, 30])
    fine = rom.simulate(dt_s=1.0, flux_w_m2=np.repeat(flux, 10), initial_c=20.0)
    coarse = rom.simulate(dt_s=10.0, flux_w_m2=flux, initial_c=20.0)
    np.testing.assert_allclose(coarse.probe_c[:, 0], fine.probe_c[::10, 0], atol=1e-9)
    np.testing.assert_allclose(coarse.face_mean_c, fine.face_mean_c[::10], atol=1e-9)


def test_continuing_a_run_equals_one_run(rom):
    flux = np.r_[np.full(40, 3e4), np.zeros(200)]
    whole = rom.simulate(dt_s=1.0, flux_w_m2=flux, initial_c=25.0)
    first = rom.simulate(dt_s=1.0, flux_w_m2=flux[:100], initial_c=25.0)
    second = rom.simulate(
        dt_s=1.0, flux_w_m2=flux[100:], initial_c=25.0, initial_state=first.final_state
    )
    np.testing.assert_allclose(second.probe_c[:, 0], whole.probe_c[100:, 0], atol=1e-12)


def test_a_block_at_ambient_stays_there(rom):
    out = rom.simulate(dt_s=1.0, flux_w_m2=np.zeros(300), initial_c=17.0, ambient_c=17.0)
    assert np.abs(out.probe_c - 17.0).max() < 1e-12
    assert np.abs(out.face_max_c - 17.0).max() < 1e-12


def test_batch_equals_single_runs(rom):
    rng = np.random.default_rng(3)
    flux = np.where(np.arange(300)[None, :] < rng.integers(10, 80, 13)[:, None], 3e4, 0.0)
    start = rng.uniform(10, 60, 13)
    batch = rom.simulate_batch(dt_s=1.0, flux_w_m2=flux, initial_c=start, ambient_c=12.0)
    for e in (0, 7, 12):
        one = rom.simulate(dt_s=1.0, flux_w_m2=flux[e], initial_c=start[e], ambient_c=12.0)
        np.testing.assert_allclose(batch.probe_c[e, :, 0], one.probe_c[:, 0], atol=1e-10)
        np.testing.assert_allclose(batch.face_mean_c[e], one.face_mean_c, atol=1e-10)
        np.testing.assert_allclose(batch.face_max_c[e], one.face_max_c, atol=1e-10)


def test_cache_is_reused_and_a_damaged_entry_rebuilt(tmp_path, monkeypatch):
    kwargs = {"refinement": 0.35, "cache_dir": tmp_path}
    built = ReducedModel.for_wagon(WAGON, **kwargs)
    files = list((tmp_path / "rom").glob("*.npz"))
    assert len(files) == 1
    with monkeypatch.context() as mp:  # loaded, not built again

        def no_build(*args, **kwargs):
            raise AssertionError("the cached model was built again")

        mp.setattr(ReducedModel, "build", no_build)
        again = ReducedModel.for_wagon(WAGON, **kwargs)
    np.testing.assert_array_equal(again.lam, built.lam)
    files[0].write_bytes(b"not a numpy archive")
    rebuilt = ReducedModel.for_wagon(WAGON, **kwargs)
    np.testing.assert_allclose(rebuilt.lam, built.lam)
    # another sensor seat is another model
    other = WagonConfig(wagon_id="ROM-TEST", sensor_depth_m=0.05)
    ReducedModel.for_wagon(other, **kwargs)
    assert len(list((tmp_path / "rom").glob("*.npz"))) == 2


def test_two_writers_of_one_model_at_once_both_succeed(rom, tmp_path, monkeypatch):
    """Two processes (here: threads) that built the same model save it to the same cache path
    at once: each writes a temporary file of its own and renames it into place, so both
    succeed, the entry is whole, and no temporary file is left. (With one fixed ``.tmp``
    name, the second rename found the file gone.)"""
    path = tmp_path / "rom" / "same-key.npz"
    both_written = threading.Barrier(2, timeout=30)
    savez = np.savez

    def savez_then_wait(file, *args, **kwargs):
        savez(file, *args, **kwargs)
        both_written.wait()  # neither renames before both have written

    monkeypatch.setattr(np, "savez", savez_then_wait)
    errors: list[BaseException] = []

    def save() -> None:
        try:
            rom.save(path)
        except BaseException as error:  # reported below, in the test's thread
            errors.append(error)

    writers = [threading.Thread(target=save) for _ in range(2)]
    for writer in writers:
        writer.start()
    for writer in writers:
        writer.join()
    assert errors == []
    monkeypatch.undo()
    assert sorted(p.name for p in path.parent.iterdir()) == ["same-key.npz"]
    loaded = ReducedModel.load(path)
    np.testing.assert_array_equal(loaded.lam, rom.lam)
    np.testing.assert_array_equal(loaded.c_out, rom.c_out)


def test_bad_inputs_are_clear_errors(rom):
    with pytest.raises(LengthMismatchError, match="ambient_c"):
        rom.simulate(dt_s=1.0, flux_w_m2=np.zeros(10), initial_c=20.0, ambient_c=np.zeros(3))
    with pytest.raises(InvalidParameterError, match="nope"):
        rom.simulate(dt_s=1.0, flux_w_m2=np.zeros(10), initial_c=20.0, h_w_m2k={"nope": 1.0})
    with pytest.raises(InvalidParameterError, match=">= 0"):
        rom.simulate(dt_s=1.0, flux_w_m2=np.zeros(10), initial_c=20.0, h_w_m2k={"air": -1.0})
    with pytest.raises(LengthMismatchError, match="ambient_c"):
        rom.simulate_batch(
            dt_s=1.0, flux_w_m2=np.zeros((4, 10)), initial_c=20.0, ambient_c=np.zeros(3)
        )


def test_unique_rows_equals_numpys_unique_of_rows() -> None:
    """The run-wise distinct rows (convection series) are numpy's, keys and inverse alike."""
    from fleetbrake.model.rom import unique_rows

    rng = np.random.default_rng(3)
    for _ in range(100):
        n, faces = int(rng.integers(1, 700)), int(rng.integers(1, 4))
        runs = rng.integers(1, 50, size=n)
        levels = rng.choice([0.0, 1.5, -2.0, 3.25], size=(n, faces))
        values = np.repeat(levels, runs, axis=0)[:n]
        keys, inverse = np.unique(values, axis=0, return_inverse=True)
        got_keys, got_inverse = unique_rows(values)
        np.testing.assert_array_equal(got_keys, keys)
        np.testing.assert_array_equal(got_inverse, inverse.reshape(-1))
    empty_keys, empty_inverse = unique_rows(np.zeros((0, 2)))
    assert empty_keys.shape == (0, 2) and empty_inverse.shape == (0,)
