"""``fleetbrake demo``: the whole chain on a small synthetic fleet leaves every artefact, a
summary naming the effect, and a report whose pictures exist; an existing output directory
is never mixed into nor wiped unless it is a demo's and ``--force`` is given.

The reduced model is the session's (its refinement passed on, ``FLEETBRAKE_CACHE_DIR`` from
the conftest fixtures), so no test builds the default mesh.
"""

from __future__ import annotations

import io
import json
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from rich.console import Console
from typer.testing import CliRunner

from fleetbrake.app.demo import (
    MARKER,
    DemoConfig,
    DemoError,
    DemoExistsError,
    DemoResult,
    prepare_out_dir,
    run_demo,
)
from fleetbrake.cli.main import app


@pytest.fixture
def demo_env(
    monkeypatch: pytest.MonkeyPatch,
    rom_refinement: float,
    rom_cache_dir: Path,
    default_rom: object,  # built once per session, under the conftest's lock
) -> float:
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    return rom_refinement


def check_artefacts(out: Path) -> None:
    """Everything the demo promises in its directory, each non-empty."""
    expected = [
        "fleet/fleet.toml",
        "fleet/truth/truth.json",
        "fleet.duckdb",
        "close-loop.json",
        "close-loop.md",
        "report.md",
        "summary.txt",
    ]
    for name in expected:
        path = out / name
        assert path.is_file(), f"missing {name}"
        assert path.stat().st_size > 0, f"empty {name}"
    assert any((out / "fleet" / "logs").rglob("*.csv*")), "no log files generated"
    recordings = sorted((out / "recordings").glob("*.rrd"))
    assert len(recordings) == 2, recordings  # a wagon's timeline and one event
    assert all(r.stat().st_size > 1000 for r in recordings)
    assert any(r.name.endswith("-timeline.rrd") for r in recordings)

    report = (out / "report.md").read_text()
    pictures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report)
    assert len(pictures) >= 4, pictures  # closed loop, predictions, flags, contact
    for name in pictures:
        png = out / name
        assert png.is_file(), f"report.md references {name}, which is not there"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{name} is not a PNG"
    for heading in ("## Closed loop", "## Flags", "## Events per wagon", "## Hottest contact"):
        assert heading in report, heading

    loop = json.loads((out / "close-loop.json").read_text())
    for key in ("baseline_revision", "new_revision", "effect", "fit", "holdout", "candidates"):
        assert key in loop, key
    assert loop["baseline_revision"] == "declared"


# --------------------------------------------------------------------------------------------
# The whole demo


@dataclass
class SmallDemo:
    out: Path
    result: DemoResult
    progress: str


@pytest.fixture(scope="module")
def small_demo(
    tmp_path_factory: pytest.TempPathFactory,
    rom_refinement: float,
    rom_cache_dir: Path,
    default_rom: object,  # built once per session, under the conftest's lock
) -> Iterator[SmallDemo]:
    """The demo on 1 wagon x 2 days (about a minute), run once for the tests below."""
    out = tmp_path_factory.mktemp("demo") / "demo-out"
    text = io.StringIO()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        config = DemoConfig(wagons=1, days=2, refinement=rom_refinement)
        result = run_demo(out, config, console=Console(file=text, width=120), progress=False)
    yield SmallDemo(out, result, text.getvalue())


def test_demo_small(small_demo: SmallDemo) -> None:
    """Every artefact, the summary naming the effect, the report and its pictures."""
    out, result = small_demo.out, small_demo.result
    check_artefacts(out)
    assert result.report == out / "report.md"
    assert all(p.is_file() for p in result.pictures)
    assert "convection_speed" in result.summary  # the effect put in (and, found, named)
    assert re.search(r"MATCHED|PARTLY matched|NOT matched", result.summary)
    assert str(out / "report.md") in result.summary
    assert "took " in result.summary
    assert (out / "summary.txt").read_text().strip() == result.summary.strip()
    for number in range(1, 8):
        assert f"[{number}/7]" in small_demo.progress
    # every step that ran is timed, and the file says what the result says
    assert {"model", "generate", "run", "close_loop", "record", "report", "total"} <= set(
        result.timings
    )
    assert json.loads((out / "timings.json").read_text()) == result.timings


def test_demo_refuses_to_mix(small_demo: SmallDemo) -> None:
    """A second run into the same directory is refused and leaves it as it was."""
    out = small_demo.out
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(DemoExistsError, match="--force"):
        run_demo(out, small_demo.result.config, console=Console(file=io.StringIO()))
    assert sorted(p.name for p in out.iterdir()) == before


def test_demo_queries_on_its_database(small_demo: SmallDemo) -> None:
    """The analyst page's queries on a database with a closed loop in it (two revisions)."""
    from test_analyst_queries import (
        check_effect_history,
        check_generic,
        doc_queries,
        run_query,
    )

    loop = small_demo.result.close_loop
    revisions = {"declared"} | ({loop.get("new_revision")} - {None})
    for title, sql in doc_queries().items():
        frame = run_query(small_demo.out / "fleet.duckdb", sql)
        check_generic(title, frame)
        if title in ("Effect history", "Error by wagon and model revision"):
            assert set(frame["model_revision"].to_list()) == revisions, title
        if title == "Effect history":
            check_effect_history(frame)


@pytest.mark.slow
def test_demo_command(tmp_path: Path, demo_env: float) -> None:
    """The command as a user runs it (the default fleet, 4 wagons x 2 days; a few minutes):
    the effect is found and matched; a re-run is refused, then --force replaces the results
    (with a smaller fleet)."""
    out = tmp_path / "demo-out"
    runner = CliRunner()
    args = ["demo", "--out", str(out), "--refinement", str(demo_env)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    check_artefacts(out)
    assert "convection_speed" in result.output
    assert "MATCHED" in result.output
    loop = json.loads((out / "close-loop.json").read_text())
    assert loop["effect"] == "convection_speed"
    assert loop["holdout"]["rmse_after_k"] < 0.5 * loop["holdout"]["rmse_before_k"]

    again = runner.invoke(app, args)
    assert again.exit_code == 1
    assert "--force" in again.output

    (out / "stale.txt").write_text("from the first run")
    smaller = [*args, "--wagons", "1", "--days", "2", "--force"]
    forced = runner.invoke(app, smaller)
    assert forced.exit_code == 0, forced.output
    assert not (out / "stale.txt").exists()
    check_artefacts(out)


# --------------------------------------------------------------------------------------------
# The output directory


def test_out_dir_new_and_empty(tmp_path: Path) -> None:
    assert (prepare_out_dir(tmp_path / "a" / "b") / MARKER).is_file()
    empty = tmp_path / "empty"
    empty.mkdir()
    assert (prepare_out_dir(empty) / MARKER).is_file()


def test_out_dir_of_an_earlier_demo(tmp_path: Path) -> None:
    out = prepare_out_dir(tmp_path / "demo")
    (out / "report.md").write_text("old results")
    with pytest.raises(DemoExistsError, match=r"earlier demo.*--force"):
        prepare_out_dir(out)
    assert (out / "report.md").read_text() == "old results"
    prepare_out_dir(out, force=True)
    assert sorted(p.name for p in out.iterdir()) == [MARKER]


def test_out_dir_not_a_demo_is_never_wiped(tmp_path: Path) -> None:
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("precious")
    with pytest.raises(DemoExistsError, match="not a demo"):
        prepare_out_dir(mine)
    with pytest.raises(DemoExistsError, match="marker"):
        prepare_out_dir(mine, force=True)
    assert (mine / "thesis.tex").read_text() == "precious"
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(DemoError, match="not a directory"):
        prepare_out_dir(a_file, force=True)


def test_command_refuses_an_existing_demo(tmp_path: Path) -> None:
    out = prepare_out_dir(tmp_path / "demo")
    (out / "report.md").write_text("old results")
    result = CliRunner().invoke(app, ["demo", "--out", str(out)])
    assert result.exit_code == 1
    assert "--force" in result.output
    assert (out / "report.md").read_text() == "old results"


def test_config_needs_a_holdout_day() -> None:
    with pytest.raises(ValueError, match="days must be >= 2"):
        DemoConfig(days=1)
