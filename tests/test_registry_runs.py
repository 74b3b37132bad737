"""The registry checked whole at every run, and failed commands without side effects.

* A registry entry of a wagon the warehouse holds results of is checked at every run, with
  or without new files: an invalid value is a configuration error (exit 2, one line naming
  the file, wagon, key and allowed range) and the warehouse is left as it was; a valid change
  re-simulates that wagon alone.
* A wagon never stored with a bad entry is left out and its files quarantined, the rest of
  the fleet run (``shared/spec/fleet-data.md``).
* ``close-loop``, ``record`` and ``report`` on a path where no database exists fail before
  opening it: no database file, folder or lock file left behind.
* A failed ``run`` (an invalid registry) writes nothing.
"""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from fleetbrake.cli.main import app
from fleetgen import T0_UTC, make_session, registry_text, snapshot, write_session
from test_cli import _one_line_failure, _use_refinement

WAGONS = ["SGG-0001", "SGG-0002"]


def _write_fleet(fleet_dir: Path, extra: str = "") -> None:
    fleet_dir.mkdir(parents=True, exist_ok=True)
    (fleet_dir / "fleet.toml").write_text(registry_text(WAGONS, extra), encoding="utf-8")


def _set_key(fleet_dir: Path, wagon: str, line: str) -> None:
    """Add ``line`` (``key = value``) to ``wagon``'s entry of ``fleet.toml``."""
    path = fleet_dir / "fleet.toml"
    entry = f'id = "{wagon}"\n'
    text = path.read_text(encoding="utf-8")
    assert entry in text
    path.write_text(text.replace(entry, entry + line + "\n"), encoding="utf-8")


@pytest.fixture(scope="module")
def stored(
    tmp_path_factory: pytest.TempPathFactory, rom_refinement: float, rom_cache_dir: Path
) -> tuple[Path, Path]:
    """A fleet of two wagons, one session each, and the database of its first run."""
    from fleetbrake.app.run import run_fleet
    from fleetbrake.simulation.config import SimulationConfig

    root = tmp_path_factory.mktemp("registry-runs")
    fleet_dir, db = root / "fleet", root / "fleet.duckdb"
    _write_fleet(fleet_dir)
    for k, wagon in enumerate(WAGONS):
        session = make_session(np.random.default_rng(200 + k), T0_UTC, n_events=4)
        write_session(fleet_dir, wagon, session.frame, T0_UTC)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        report = run_fleet(
            fleet_dir, db, simulation=SimulationConfig(refinement=rom_refinement), progress=False
        )
    assert sorted(report.simulation.wagons_simulated) == WAGONS
    return fleet_dir, db


@pytest.fixture
def copy(stored: tuple[Path, Path], tmp_path: Path) -> tuple[Path, Path]:
    """The stored fleet and database, copied for one test to change."""
    fleet_dir, db = stored
    shutil.copytree(fleet_dir, tmp_path / "fleet")
    for made in db.parent.glob(db.name + "*"):  # the database and the lock file of its run
        shutil.copy(made, tmp_path / made.name)
    return tmp_path / "fleet", tmp_path / "fleet.duckdb"


@pytest.fixture
def cli(monkeypatch: pytest.MonkeyPatch, rom_refinement: float, rom_cache_dir: Path) -> CliRunner:
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    _use_refinement(monkeypatch, rom_refinement)
    return CliRunner()


@pytest.mark.parametrize(
    ("line", "key", "allowed"),
    [
        ("cylinder_diameter_m = -0.254", "cylinder_diameter_m", "[0.1, 0.6] m"),
        ("cylinder_diameter_m = 254", "cylinder_diameter_m", "[0.1, 0.6] m"),
        ('friction_coefficient = "0.15"', "friction_coefficient", "must be a number"),
        ("blocks_per_bogie = 0", "blocks_per_bogie", "[1, 64]"),
    ],
)
@pytest.mark.parametrize("command", ["run", "ingest"])
def test_an_invalid_value_of_a_stored_wagon_is_a_configuration_error(
    copy: tuple[Path, Path], cli: CliRunner, line: str, key: str, allowed: str, command: str
) -> None:
    fleet_dir, db = copy
    before = snapshot(db)
    _set_key(fleet_dir, "SGG-0001", line)  # no new file of the wagon: checked all the same
    result = cli.invoke(app, [command, str(fleet_dir), "--db", str(db)])
    message = _one_line_failure(result, 2, command)
    assert f"{fleet_dir / 'fleet.toml'}: wagon SGG-0001, key {key}: " in message
    assert allowed in message
    assert "nothing was written" in message
    assert snapshot(db) == before


def test_an_invalid_default_is_a_configuration_error_once_wagons_are_stored(
    copy: tuple[Path, Path], cli: CliRunner
) -> None:
    fleet_dir, db = copy
    before = snapshot(db)
    text = (fleet_dir / "fleet.toml").read_text(encoding="utf-8")
    (fleet_dir / "fleet.toml").write_text(
        text.replace("[defaults]\n", "[defaults]\nrigging_efficiency = 1.5\n"), encoding="utf-8"
    )
    result = cli.invoke(app, ["run", str(fleet_dir), "--db", str(db)])
    message = _one_line_failure(result, 2, "run")
    assert "key defaults.rigging_efficiency: must be a number in (0, 1]" in message
    assert snapshot(db) == before


def test_a_valid_change_re_simulates_that_wagon_alone(
    copy: tuple[Path, Path],
    rom_refinement: float,
    monkeypatch: pytest.MonkeyPatch,
    rom_cache_dir: Path,
) -> None:
    from fleetbrake.app.run import run_fleet
    from fleetbrake.simulation.config import SimulationConfig

    fleet_dir, db = copy
    _set_key(fleet_dir, "SGG-0002", "cylinder_diameter_m = 0.305")
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    simulation = SimulationConfig(refinement=rom_refinement)
    report = run_fleet(fleet_dir, db, simulation=simulation, progress=False)
    assert report.simulation.wagons_simulated == ["SGG-0002"]
    assert report.ingest.ingested == []
    assert report.flags is not None
    assert "SGG-0001" not in report.flags.wagons
    again = run_fleet(fleet_dir, db, simulation=simulation, progress=False)
    assert again.simulation.wagons_simulated == []


def test_a_new_wagon_with_a_bad_entry_is_left_out_and_the_rest_runs(
    tmp_path: Path,
    rom_refinement: float,
    monkeypatch: pytest.MonkeyPatch,
    rom_cache_dir: Path,
) -> None:
    from fleetbrake.app.run import run_fleet
    from fleetbrake.simulation.config import SimulationConfig

    fleet_dir, db = tmp_path / "fleet", tmp_path / "fleet.duckdb"
    _write_fleet(fleet_dir, '[[wagon]]\nid = "BAD-0001"\ncylinder_diameter_m = -0.3\n')
    start = T0_UTC + dt.timedelta(hours=1)
    for k, wagon in enumerate(["SGG-0001", "BAD-0001"]):
        session = make_session(np.random.default_rng(300 + k), start, n_events=3)
        write_session(fleet_dir, wagon, session.frame, start)
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    report = run_fleet(
        fleet_dir, db, simulation=SimulationConfig(refinement=rom_refinement), progress=False
    )
    assert [r.wagon_id for r in report.ingest.ingested] == ["SGG-0001"]
    (quarantined,) = report.ingest.quarantined
    assert "cylinder_diameter_m" in (quarantined.reason or "")
    assert any("BAD-0001" in p for p in report.ingest.registry_problems)


# --------------------------------------------------------------------------------------------
# Commands that need a warehouse, given a path where none exists


def _reading_commands(db: Path, out: Path) -> dict[str, list[str]]:
    return {
        "close-loop": [
            "close-loop",
            "--db",
            str(db),
            "--holdout-from",
            "2024-03-05",
            "--json",
            str(out / "loop.json"),
        ],
        "record": ["record", "--db", str(db), "--wagon", "SGG-0001", "--out", str(out / "a.rrd")],
        "report": ["report", "--db", str(db), "--out", str(out / "report")],
    }


@pytest.mark.parametrize("command", ["close-loop", "record", "report"])
@pytest.mark.parametrize("where", ["file", "folder"])
def test_a_reading_command_on_a_missing_database_leaves_nothing_behind(
    tmp_path: Path, command: str, where: str
) -> None:
    db = tmp_path / "fleet.duckdb" if where == "file" else tmp_path / "nowhere" / "fleet.duckdb"
    out = tmp_path / "out"
    result = CliRunner().invoke(app, _reading_commands(db, out)[command])
    message = _one_line_failure(result, 1, command)
    assert f"{db}: no such database" in message
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no database, lock, folder, output


def test_a_failed_run_leaves_the_database_as_it_was(
    copy: tuple[Path, Path], cli: CliRunner
) -> None:
    fleet_dir, db = copy
    files_before = sorted(p.name for p in db.parent.iterdir())
    assert db.with_name(db.name + ".lock") in db.parent.iterdir()  # as every writer leaves it
    _set_key(fleet_dir, "SGG-0002", "wheel_radius_m = 460")
    result = cli.invoke(app, ["run", str(fleet_dir), "--db", str(db)])
    _one_line_failure(result, 2, "run")
    assert sorted(p.name for p in db.parent.iterdir()) == files_before


def test_a_failed_run_on_a_new_path_creates_no_database(tmp_path: Path, cli: CliRunner) -> None:
    db = tmp_path / "warehouse" / "fleet.duckdb"
    result = cli.invoke(app, ["run", str(tmp_path / "no-fleet"), "--db", str(db)])
    assert result.exit_code == 1, result.output
    assert list(tmp_path.iterdir()) == []
