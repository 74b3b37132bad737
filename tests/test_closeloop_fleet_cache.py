"""The cache of written acceptance fleets (``acceptance_fleets.cached_fleet``).

An acceptance fleet written by the full model at ``FE_REFINEMENT`` 0.6 costs 7-26 min (about
1 h 40 min for convection_speed), so ``test_closeloop_acceptance`` keeps each one under
``$FLEETBRAKE_ACCEPTANCE_CACHE`` (default ``~/.cache/fleetbrake/acceptance``; ``off``: no
cache), keyed by (case, seed, writer version), the version a hash of what determines the
fleet (``acceptance_fleets.writer_version``: the full model's refinement, the SynthConfig
with its drawn effect, this repository's writer sources and the acceptance module's writing
part). Here, on a tiny fleet (one wagon, one day, the full model at refinement 0.2, not the
0.6 writer): the version changes when any of its inputs does, a cached fleet is reused and
not written again, the run gets a copy, and the writer sources cover every ``fleetbrake``
module whose code runs while a fleet is written.
"""

from __future__ import annotations

import dataclasses
import filecmp
import sys
from collections.abc import Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import pytest

import acceptance_fleets as af
from fleetbrake import _ext
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.fullmodel import FullModelRunner
from fleetbrake.synth.config import draw_effect
from fleetbrake.synth.generator import SynthConfig, generate_fleet, load_truth

TINY_REFINEMENT = 0.2


def tiny_config(seed: int = 7) -> SynthConfig:
    return SynthConfig(
        wagons=1,
        days=1,
        seed=seed,
        effects=(draw_effect("sensor_lag", seed),),
        unregistered_wagon=False,
        bad_registry_entry=False,
        solver="full",
        refinement=TINY_REFINEMENT,
    )


def tiny_writer(wagon: WagonConfig) -> FullModelRunner:
    return FullModelRunner.for_wagon(wagon, refinement=TINY_REFINEMENT)


@pytest.fixture
def sources(tmp_path: Path) -> Iterator[tuple[Path, list[str]]]:
    root = tmp_path / "repo"
    (root / "pkg").mkdir(parents=True)
    (root / "pkg" / "a.py").write_text("A = 1\n")
    (root / "pkg" / "estimator.rs").write_text("// not the writer\n")
    (root / "pkg" / "rom.rs").write_text("// not the full model's writer\n")
    (root / "pkg" / "rom").mkdir()
    (root / "pkg" / "rom" / "chain.rs").write_text("// a module of the reduced model\n")
    (root / "pkg" / "estimator").mkdir()
    (root / "pkg" / "estimator" / "filter.rs").write_text("// a module of the estimator\n")
    (root / "b.rs").write_text("fn b() {}\n")
    yield root, ["pkg", "b.rs"]


def test_the_writer_version_changes_with_each_of_its_inputs(
    sources: tuple[Path, list[str]],
) -> None:
    root, names = sources
    config = tiny_config()
    base = af.writer_version(config, 0.6, names, root)
    assert af.writer_version(config, 0.6, names, root) == base  # a function of its inputs
    effect = config.effects.effects[0]
    changed = {
        "refinement": af.writer_version(config, 0.5, names, root),
        "seed": af.writer_version(dataclasses.replace(config, seed=8), 0.6, names, root),
        "effect": af.writer_version(
            dataclasses.replace(
                config, effects=(dataclasses.replace(effect, tau_s=effect.tau_s + 1e-9),)
            ),
            0.6,
            names,
            root,
        ),
        "config": af.writer_version(
            dataclasses.replace(config, sensor_noise_k=0.11), 0.6, names, root
        ),
    }
    (root / "pkg" / "a.py").write_text("A = 2\n")
    changed["python source"] = af.writer_version(config, 0.6, names, root)
    (root / "b.rs").write_text("fn b() { }\n")
    changed["rust source"] = af.writer_version(config, 0.6, names, root)
    (root / "pkg" / "c.py").write_text("")
    changed["a new source file"] = af.writer_version(config, 0.6, names, root)
    versions = [base, *changed.values()]
    assert len(set(versions)) == len(versions), changed
    # the estimator does not write fleets: its source is not part of the version
    (root / "pkg" / "estimator.rs").write_text("// changed\n")
    (root / "pkg" / "estimator" / "filter.rs").write_text("// changed\n")
    assert af.writer_version(config, 0.6, names, root) == changed["a new source file"]
    # the reduced model's Rust does not write a fleet of the full model, but one of its own
    reduced = dataclasses.replace(config, solver="rom")
    before = af.writer_version(reduced, 0.6, names, root)
    (root / "pkg" / "rom.rs").write_text("// changed\n")
    assert af.writer_version(config, 0.6, names, root) == changed["a new source file"]
    after_bindings = af.writer_version(reduced, 0.6, names, root)
    assert after_bindings != before
    (root / "pkg" / "rom" / "chain.rs").write_text("// changed\n")
    assert af.writer_version(config, 0.6, names, root) == changed["a new source file"]
    assert af.writer_version(reduced, 0.6, names, root) != after_bindings
    # every acceptance case has its own version, and the repository's sources all exist
    real = {c.name: af.writer_version(af.synth_config(c)) for c in af.CASES}
    assert len(set(real.values())) == len(af.CASES)


def test_the_writing_part_of_the_acceptance_module_is_in_the_version(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    config = af.synth_config(af.CASES[0])
    base = af.writer_version(config)

    def writer_for(wagon: WagonConfig) -> FullModelRunner:  # another writer's source
        return FullModelRunner.for_wagon(wagon, refinement=0.5)

    functions = tuple(writer_for if f is af.writer_for else f for f in af.WRITER_FUNCTIONS)
    monkeypatch.setattr(af, "WRITER_FUNCTIONS", functions)
    assert af.writer_version(config) != base


def _tiny_write(directory: Path, writes: list[Path]) -> None:
    writes.append(directory)
    generate_fleet(directory, tiny_config(), rom=tiny_writer)


def test_a_cached_fleet_is_reused_and_the_run_gets_a_copy(tmp_path: Path) -> None:
    root = tmp_path / "cache"
    writes: list[Path] = []
    version = af.writer_version(tiny_config(), TINY_REFINEMENT)
    first = af.cached_fleet(
        "tiny",
        tiny_config(),
        tmp_path / "first" / "fleet",
        lambda d: _tiny_write(d, writes),
        version=version,
        root=root,
    )
    assert (first, len(writes)) == (False, 1)
    assert not writes[0].exists()  # written in a staging directory, renamed into place
    entries = [p.name for p in root.iterdir()]
    assert entries == [f"tiny-s7-{version[:24]}"]  # nothing else left behind
    second = af.cached_fleet(
        "tiny",
        tiny_config(),
        tmp_path / "second" / "fleet",
        lambda d: _tiny_write(d, writes),
        version=version,
        root=root,
    )
    assert (second, len(writes)) == (True, 1)  # reused, not written again
    cached = root / entries[0] / "fleet"
    compared = filecmp.dircmp(cached, tmp_path / "second" / "fleet")
    assert not (compared.left_only or compared.right_only or compared.diff_files)
    truth = load_truth(tmp_path / "second" / "fleet")
    assert truth.out_dir == tmp_path / "second" / "fleet"
    assert truth.to_dict() == load_truth(tmp_path / "first" / "fleet").to_dict()
    # the run's copy is its own: changing it leaves the cache as it was
    for path in (tmp_path / "second" / "fleet").rglob("*"):
        if path.is_file():
            path.unlink()
    assert any(p.is_file() for p in cached.rglob("*"))
    # another version is another entry, written again
    other = af.cached_fleet(
        "tiny",
        tiny_config(),
        tmp_path / "third" / "fleet",
        lambda d: _tiny_write(d, writes),
        version="0" * 64,
        root=root,
    )
    assert (other, len(writes)) == (False, 2)


def test_a_failed_write_leaves_no_entry(tmp_path: Path) -> None:
    root = tmp_path / "cache"

    def fails(directory: Path) -> None:
        directory.mkdir(parents=True)
        (directory / "half.csv").write_text("time_utc\n")
        raise RuntimeError("killed while writing")

    with pytest.raises(RuntimeError, match="killed while writing"):
        af.cached_fleet(
            "tiny", tiny_config(), tmp_path / "fleet", fails, version="1" * 64, root=root
        )
    assert list(root.iterdir()) == []


def test_the_cache_is_where_the_environment_says(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FLEETBRAKE_ACCEPTANCE_CACHE", "/somewhere/else")
    assert af.fleet_cache_root() == Path("/somewhere/else")
    monkeypatch.setenv("FLEETBRAKE_ACCEPTANCE_CACHE", "off")
    assert af.fleet_cache_root() is None
    monkeypatch.delenv("FLEETBRAKE_ACCEPTANCE_CACHE")
    assert af.fleet_cache_root() == Path.home() / ".cache" / "fleetbrake" / "acceptance"


def test_the_writer_sources_cover_every_module_that_runs_while_writing(
    tmp_path: Path,
) -> None:
    """Every ``fleetbrake`` Python module whose functions are called while the full model
    writes a tiny fleet is among ``acceptance_fleets.WRITER_SOURCES`` (a writer that starts
    calling another module makes this fail until the module is added to the version)."""
    package = af.REPO / "python" / "fleetbrake"
    ran: set[Path] = set()

    def profile(frame: FrameType, event: str, _arg: Any) -> None:
        if event == "call":
            ran.add(Path(frame.f_code.co_filename))

    sys.setprofile(profile)
    try:
        generate_fleet(tmp_path / "fleet", tiny_config(), rom=tiny_writer)
    finally:
        sys.setprofile(None)
    ran_here = {p.resolve() for p in ran if p.resolve().is_relative_to(package)}
    assert ran_here, "the profile saw no fleetbrake module"
    hashed = {p.resolve() for p in af.writer_source_files()}
    assert sorted(map(str, ran_here - hashed)) == []


def _reduced_model_rust_raises(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every binding of the reduced model's Rust (``_ext.rom_*``) made to raise; their names."""
    names = sorted(n for n in dir(_ext) if n.startswith("rom_"))

    def forbidden(*_args: object, **_kwargs: object) -> object:
        raise AssertionError("the reduced model's Rust was called")

    for name in names:
        monkeypatch.setattr(_ext, name, forbidden)
    return names


def test_the_full_writer_calls_no_reduced_model_rust(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Why ``FULL_WRITER_EXCLUDED`` (``rom.rs``) may be left out of a full-model fleet's
    version: with every ``_ext.rom_*`` raising, the full model writes its fleet, while a fleet
    of the reduced model cannot be written (the stubs are where the writer would call them)."""
    assert _reduced_model_rust_raises(monkeypatch)
    truth = generate_fleet(tmp_path / "full", tiny_config(), rom=tiny_writer)
    assert truth.wagons and truth.files and truth.rom["solver"] == "full"
    with pytest.raises(AssertionError, match="reduced model's Rust was called"):
        generate_fleet(tmp_path / "rom", dataclasses.replace(tiny_config(), solver="rom"))
