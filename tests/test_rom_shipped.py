"""The reduced models the package ships: the files are those of the current keys (a change of
any input names another file), a shipped model is used without building, a block that differs
is built on demand, and the shipped default model is what a fresh build gives."""

from __future__ import annotations

import datetime as dt
import logging
from pathlib import Path

import numpy as np
import pytest

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model import rom as rom_module
from fleetbrake.model.rom import (
    DEFAULT_REFINEMENT,
    SHIPPED_MODELS,
    ReducedModel,
    cache_key,
    shipped_name,
    wagon_model_inputs,
)
from fleetbrake.model.rombasis import TRAINING_INITIAL_C, training_loading
from fleetbrake.model.romdata import SHIPPED_REFINEMENTS, shipped_models, write_shipped_models

WAGON = WagonConfig(wagon_id="ROM-SHIPPED")
SMALL = 0.35
"""A coarse mesh whose model builds in a few seconds."""


def no_build(*args: object, **kwargs: object) -> ReducedModel:
    raise AssertionError("a reduced model was built")


def test_the_package_ships_the_models_of_the_current_keys() -> None:
    expected = {shipped_name(key) for key in shipped_models()}
    present = {entry.name for entry in SHIPPED_MODELS.iterdir() if entry.name.endswith(".npz")}
    assert present == expected, (
        "the shipped reduced models are not those of the model's current inputs: "
        "run `python -m fleetbrake.model.romdata` (make rom-data)"
    )
    for key in shipped_models():
        model = ReducedModel.shipped(key)
        assert model is not None and model.meta["cache_key"] == key
        assert model.meta["check"]["passed"]


def test_a_default_wagon_on_the_meshes_of_run_and_close_loop_is_shipped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The run's default mesh and the coarse meshes of the close loop's numerical term."""
    from fleetbrake.closeloop.config import CloseLoopConfig

    ratios = CloseLoopConfig(dt.date(2024, 3, 7)).numerical_grid_ratios
    meshes = [DEFAULT_REFINEMENT] + [DEFAULT_REFINEMENT / ratio for ratio in ratios]
    assert set(meshes) <= set(SHIPPED_REFINEMENTS)
    monkeypatch.setattr(ReducedModel, "build", no_build)
    for refinement in meshes:
        model = ReducedModel.for_wagon(WAGON, refinement=refinement, cache_dir=tmp_path)
        assert model.meta["cache_key"] == cache_key(*wagon_model_inputs(WAGON, refinement))
    assert not (tmp_path / "rom").exists()  # nothing built, nothing cached


def test_every_input_of_the_model_is_in_its_key() -> None:
    factory, probes = wagon_model_inputs(WAGON, SMALL)
    key = cache_key(factory, probes)
    assert cache_key(factory, probes) == key
    others = [
        cache_key(*wagon_model_inputs(WagonConfig(wagon_id="W", wheel_radius_m=0.5), SMALL)),
        cache_key(*wagon_model_inputs(WagonConfig(wagon_id="W", sensor_depth_m=0.05), SMALL)),
        cache_key(*wagon_model_inputs(WAGON, 0.4)),
        cache_key({**factory, "element": "hex8"}, probes),
        cache_key(factory, probes, {"flank": 12.0}),
    ]
    assert len({key, *others}) == len(others) + 1
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rom_module, "DEFAULT_CONVECTION_W_M2K", 11.0)
        assert cache_key(factory, probes) != key
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rom_module, "ROM_VERSION", rom_module.ROM_VERSION + 1)
        assert cache_key(factory, probes) != key


def test_a_shipped_model_is_used_a_stale_one_removed_and_another_block_built(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    shipped, cache = tmp_path / "data", tmp_path / "cache"
    shipped.mkdir()
    (shipped / "rom-0123456789abcdef0123456789abcdef.npz").write_bytes(b"of an older key")
    (written,) = write_shipped_models(shipped, refinements=(SMALL,))
    assert sorted(p.name for p in shipped.iterdir()) == [written.name]
    key = cache_key(*wagon_model_inputs(WAGON, SMALL))
    assert written.name == shipped_name(key)
    monkeypatch.setattr(rom_module, "SHIPPED_MODELS", shipped)
    with monkeypatch.context() as mp:
        mp.setattr(ReducedModel, "build", no_build)
        model = ReducedModel.for_wagon(WAGON, refinement=SMALL, cache_dir=cache)
    assert model.meta["cache_key"] == key
    assert not cache.exists()
    # a wagon whose sensor seat differs: built on demand and cached
    other = WagonConfig(wagon_id="W", sensor_depth_m=0.05)
    built = ReducedModel.for_wagon(other, refinement=SMALL, cache_dir=cache)
    assert built.meta["cache_key"] != key
    assert len(list((cache / "rom").glob("*.npz"))) == 1
    # a shipped file that cannot be read is said and the model built instead
    written.write_bytes(b"damaged")
    with caplog.at_level(logging.WARNING, logger="fleetbrake.model.rom"):
        rebuilt = ReducedModel.for_wagon(WAGON, refinement=SMALL, cache_dir=cache)
    assert "unusable, built instead" in caplog.text
    np.testing.assert_allclose(rebuilt.lam, model.lam, rtol=1e-9)


def outputs(model: ReducedModel) -> dict[str, np.ndarray]:
    """The model's sensor, face mean and face maximum over the training loading."""
    loading = training_loading()
    run = model.simulate(
        dt_s=1.0,
        flux_w_m2=loading["flux_w_m2"],
        ambient_c=loading["ambient_c"],
        initial_c=TRAINING_INITIAL_C,
        h_w_m2k={face: 15.0 for face in model.face_names if face != "friction"},
    )
    return {"probe_c": run.probe_c, "face_mean_c": run.face_mean_c, "face_max_c": run.face_max_c}


@pytest.mark.slow
def test_the_shipped_default_model_is_what_a_fresh_build_gives() -> None:
    """Built afresh (about 15 processor-seconds): the same eigenvalues and, on the training
    loading at other than nominal convection, the same outputs to 1e-9 K (the modes' signs are
    free, so the arrays themselves are not compared)."""
    for key, (wagon, refinement) in shipped_models().items():
        shipped = ReducedModel.shipped(key)
        assert shipped is not None
        fresh = ReducedModel.build_keyed(*wagon_model_inputs(wagon, refinement))
        assert fresh.meta["cache_key"] == key
        assert shipped.meta["face_max_nodes"] == fresh.meta["face_max_nodes"]
        np.testing.assert_allclose(shipped.lam, fresh.lam, rtol=1e-9, atol=1e-12)
        for name, values in outputs(fresh).items():
            np.testing.assert_allclose(outputs(shipped)[name], values, rtol=0, atol=1e-9)
