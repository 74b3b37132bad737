"""Shared pytest fixtures."""

from __future__ import annotations

import fcntl
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

TEST_REFINEMENT = float(os.environ.get("FLEETBRAKE_TEST_REFINEMENT", "0.6"))
"""Mesh refinement of the reduced models built in tests (~12 s to build, instead of ~60 s)."""


@pytest.fixture(scope="session")
def rom_refinement() -> float:
    """``TEST_REFINEMENT``, for tests that must pass it on (e.g. as ``--refinement`` to a
    command run in-process, or in a ``SimulationConfig``)."""
    return TEST_REFINEMENT


@pytest.fixture(scope="session")
def rom_cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where the session's reduced models are cached: ``$FLEETBRAKE_CACHE_DIR`` if set, else
    one directory shared by every xdist worker of the session."""
    env = os.environ.get("FLEETBRAKE_CACHE_DIR")
    path = Path(env) if env else tmp_path_factory.getbasetemp().parent / "fleetbrake-cache"
    path.mkdir(parents=True, exist_ok=True)
    return path


@pytest.fixture(scope="session")
def reduced_model_for(rom_cache_dir: Path) -> Iterator[Callable[..., object]]:
    """``reduced_model_for(wagon)``: the wagon's reduced model at ``TEST_REFINEMENT``, built
    once per session (a file lock keeps parallel workers from building it twice) and cached
    in ``rom_cache_dir``. Nothing is put in the environment."""
    from fleetbrake.model.rom import ReducedModel

    models: dict[tuple[object, ...], ReducedModel] = {}

    def get(wagon: object) -> ReducedModel:
        key = (wagon.geometry, wagon.block, wagon.sensor_point_m)  # type: ignore[attr-defined]
        if key not in models:
            with open(rom_cache_dir / "build.lock", "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)
                try:
                    models[key] = ReducedModel.for_wagon(
                        wagon,  # type: ignore[arg-type]
                        refinement=TEST_REFINEMENT,
                        cache_dir=rom_cache_dir,
                    )
                finally:
                    fcntl.flock(lock, fcntl.LOCK_UN)
        return models[key]

    yield get


FE_REFINEMENT = 0.2
"""The full model's mesh of the tests' full-FE fleets (409 hex20 nodes): not the reduced
model's (``TEST_REFINEMENT``), so that the model that writes a fleet is not the one that reads
it (the modules that generate such fleets say ``FE_REFINEMENT = 0.2`` too)."""


@pytest.fixture(scope="session")
def full_model_for() -> Callable[..., object]:
    """``full_model_for(wagon)``: the full finite-element model of the wagon's block at
    ``FE_REFINEMENT``, assembled once per block for the session."""
    from fleetbrake.model.fullmodel import FullModelRunner

    models: dict[tuple[object, ...], FullModelRunner] = {}

    def get(wagon: object) -> FullModelRunner:
        key = (wagon.geometry, wagon.block, wagon.sensor_point_m)  # type: ignore[attr-defined]
        if key not in models:
            models[key] = FullModelRunner.for_wagon(
                wagon,  # type: ignore[arg-type]
                refinement=FE_REFINEMENT,
            )
        return models[key]

    return get


@pytest.fixture(scope="session")
def computed_once(
    tmp_path_factory: pytest.TempPathFactory,
) -> Callable[[str, Callable[[], dict[str, np.ndarray]]], dict[str, np.ndarray]]:
    """``computed_once(name, make)``: the arrays ``make()`` returns, computed once per test
    session: by the first xdist worker to ask for ``name`` (a file lock per name, so two names
    are computed in parallel) and read by the others from the session's temporary directory
    (nothing is kept outside it, nothing is read from another session)."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "computed-once"
    root.mkdir(parents=True, exist_ok=True)

    def get(name: str, make: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        path = root / f"{name}.npz"
        with open(root / f"{name}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                if not path.exists():
                    part = root / f"{name}.part.npz"
                    np.savez(part, **make())
                    part.replace(path)
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)
        with np.load(path) as arrays:
            return {key: arrays[key] for key in arrays.files}

    return get


@pytest.fixture(scope="session")
def default_rom(reduced_model_for: Callable[..., object]) -> object:
    """The reduced model of the registry's default wagon (the reference block and seat)."""
    from fleetbrake.fleet.registry import WagonConfig

    return reduced_model_for(WagonConfig(wagon_id="TEST-0001"))


@dataclass(frozen=True)
class RunFleet:
    """A generated fleet, run: its database and the simulation config it was run with."""

    db: Path
    simulation: Any


@pytest.fixture(scope="session")
def convection_fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_cache_dir: Path,
) -> Iterator[RunFleet]:
    """The database and simulation config of two wagons x 2 days (seed 4) with an undeclared
    convection (gain 2.0, exponent 0.8) and the anomalies, run: the close loop's small fleet.
    Tests that write to it work on a copy."""
    from fleetbrake.app.run import run_fleet
    from fleetbrake.model.effects import ConvectionSpeed, EffectSet
    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        out = tmp_path_factory.mktemp("clfleet")
        effects = EffectSet((ConvectionSpeed(gain=2.0, exponent=0.8),))
        config = SynthConfig(wagons=2, days=2, seed=4, effects=effects, anomalies=True)
        generate_fleet(out / "fleet", config, rom=reduced_model_for)
        simulation = SimulationConfig(refinement=TEST_REFINEMENT)
        run_fleet(out / "fleet", out / "fleet.duckdb", simulation=simulation, progress=False)
        yield RunFleet(out / "fleet.duckdb", simulation)
