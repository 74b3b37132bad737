"""The command line as users and schedulers meet it.

* One mapping of expected failures: a bad ``--flag-config``, ``--solver`` or
  ``--holdout-from``, an unknown revision, wagon or event, a database held by another writer
  and a benchmark without its extra each end in one line on stderr naming the command and
  what is wrong, and the contract's exit code (2 usage or configuration, 1 could not do its
  job, 75 locked), never a traceback.
* ``--json``: ``run`` and ``close-loop`` print one JSON summary as the last line of stdout,
  and it says what the database holds.
* Logging: ``--log-format json`` writes one JSON object per record on stderr, ``--quiet``
  leaves only errors, and a command leaves the process's logging as it found it.
* The runtime commands import neither the benchmarks' meters nor their peers.

The pipeline runs on the session's reduced model (``rom_refinement``, cached in
``rom_cache_dir``): the commands' ``run_fleet`` and ``run_close_loop`` are given its
refinement, so that no test builds the default mesh.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import duckdb
import pytest
from typer.testing import CliRunner, Result

from fleetbrake.cli.main import app

WAGON = "SGG-0001"
HOLDOUT = "2024-03-05"
"""The generated fleet's second day (the fleet starts on 2024-03-04)."""


def _use_refinement(monkeypatch: pytest.MonkeyPatch, refinement: float) -> list[dict[str, Any]]:
    """Make the commands' ``run_fleet`` and ``run_close_loop`` simulate at ``refinement``;
    returns the keyword arguments ``run_fleet`` was called with, call after call."""
    import fleetbrake.app.run as run_module
    import fleetbrake.closeloop.loop as loop_module
    from fleetbrake.closeloop.config import CloseLoopConfig
    from fleetbrake.simulation.config import SimulationConfig

    real_run, real_loop = run_module.run_fleet, loop_module.run_close_loop
    calls: list[dict[str, Any]] = []

    def run_fleet(*args: Any, simulation: Any = None, **kwargs: Any) -> Any:
        calls.append({"simulation": simulation, **kwargs})
        simulation = dataclasses.replace(simulation or SimulationConfig(), refinement=refinement)
        return real_run(*args, simulation=simulation, **kwargs)

    def run_close_loop(db: Any, holdout: Any, json_out: Any, **kwargs: Any) -> Any:
        config = CloseLoopConfig(
            holdout_from=holdout, simulation=SimulationConfig(refinement=refinement)
        )
        return real_loop(db, holdout, json_out, config=config, **kwargs)

    monkeypatch.setattr(run_module, "run_fleet", run_fleet)
    monkeypatch.setattr(loop_module, "run_close_loop", run_close_loop)
    return calls


@dataclasses.dataclass
class Fleet:
    root: Path
    fleet_dir: Path
    db: Path
    first_run: Result
    run_calls: list[dict[str, Any]]


@pytest.fixture(scope="module")
def fleet(
    tmp_path_factory: pytest.TempPathFactory,
    rom_refinement: float,
    rom_cache_dir: Path,
    reduced_model_for: Any,
) -> Iterator[Fleet]:
    """A generated fleet of 1 wagon x 2 days and the database of its first ``run --json``."""
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    root = tmp_path_factory.mktemp("cli")
    fleet_dir, db = root / "fleet", root / "fleet.duckdb"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        config = SynthConfig(wagons=1, days=2, seed=5, refinement=rom_refinement)
        generate_fleet(fleet_dir, config, rom=reduced_model_for)
        calls = _use_refinement(mp, rom_refinement)
        first = CliRunner().invoke(app, ["run", str(fleet_dir), "--db", str(db), "--json"])
    yield Fleet(root, fleet_dir, db, first, calls)


@pytest.fixture
def cli(monkeypatch: pytest.MonkeyPatch, rom_refinement: float, rom_cache_dir: Path) -> CliRunner:
    """A runner whose pipeline uses the session's reduced model."""
    monkeypatch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
    _use_refinement(monkeypatch, rom_refinement)
    return CliRunner()


def _last_json(result: Result) -> dict[str, Any]:
    summary: dict[str, Any] = json.loads(result.stdout.strip().splitlines()[-1])
    return summary


def _one_line_failure(result: Result, exit_code: int, command: str) -> str:
    """The failure's single line on stderr (checked: exit code, no traceback)."""
    assert result.exit_code == exit_code, (result.exit_code, result.output, result.exception)
    assert isinstance(result.exception, SystemExit), result.exception  # nothing escaped
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.output
    assert lines[0].startswith(f"fleetbrake {command}: "), lines[0]
    return lines[0]


# --------------------------------------------------------------------------------------------
# run --json


def test_run_prints_a_json_summary_of_what_it_stored(fleet: Fleet) -> None:
    result = fleet.first_run
    assert result.exit_code == 0, result.output
    summary = _last_json(result)
    con = duckdb.connect(str(fleet.db), read_only=True)
    try:
        files = dict(con.sql("SELECT status, count(*) FROM v_files GROUP BY status").fetchall())
        ((events,),) = con.sql("SELECT count(*) FROM v_events").fetchall()
        ((predictions,),) = con.sql("SELECT count(*) FROM v_predictions").fetchall()
        ((simulated,),) = con.sql("SELECT count(DISTINCT event_id) FROM v_predictions").fetchall()
        flags = dict(con.sql("SELECT kind, count(*) FROM v_flags GROUP BY kind").fetchall())
        ((rows,),) = con.sql("SELECT sum(rows) FROM v_files WHERE status = 'ingested'").fetchall()
        ((rejected,),) = con.sql(
            "SELECT coalesce(sum(rows_rejected), 0) FROM v_files WHERE status = 'ingested'"
        ).fetchall()
    finally:
        con.close()
    assert summary["command"] == "run"
    assert summary["revision"] == "declared"
    assert summary["files"]["ingested"] == files["ingested"] > 0
    assert summary["files"]["quarantined"] == files.get("quarantined", 0) > 0  # bad files made
    assert summary["files"]["seen"] == sum(files.values())
    assert summary["rows"] == rows
    assert summary["rows_rejected"] == rejected
    assert summary["events"] == events > 0
    assert summary["events_simulated"] == simulated
    assert summary["prediction_rows"] == predictions
    assert summary["flags"] == flags
    assert summary["wagons_judged"] > 0
    assert set(summary["stage_s"]) == {
        "ingest",
        "write",
        "events",
        "simulate",
        "estimate",
        "flags",
    }
    # stdout is not a terminal here: no progress bars
    assert fleet.run_calls[0]["progress"] is False


def test_a_second_run_adds_nothing(fleet: Fleet, cli: CliRunner) -> None:
    result = cli.invoke(app, ["run", str(fleet.fleet_dir), "--db", str(fleet.db), "--json"])
    assert result.exit_code == 0, result.output
    summary = _last_json(result)
    assert summary["files"]["ingested"] == summary["files"]["quarantined"] == 0
    assert summary["rows"] == summary["events_simulated"] == summary["prediction_rows"] == 0
    assert summary["events"] == _last_json(fleet.first_run)["events"]
    # no wagon judged again, and the fleet's flags still reported
    assert summary["wagons_judged"] == 0
    assert summary["flags"] == _last_json(fleet.first_run)["flags"]


# --------------------------------------------------------------------------------------------
# Expected failures: one line, the contract's exit code


def _flag_configs(tmp: Path) -> dict[str, tuple[Path, str]]:
    """Bad flag configurations: (file, what the message must name)."""
    from fleetbrake.flags import FlagConfig

    number_key = next(f.name for f in dataclasses.fields(FlagConfig) if type(f.default) is float)
    texts = {
        "not_toml": ("threshold = = 1\n", "not a valid TOML file"),
        "unknown_key": ("no_such_threshold = 1.0\n", "no_such_threshold"),
        "bad_value": (f'{number_key} = "high"\n', number_key),
    }
    out = {"missing": (tmp / "missing.toml", "not found")}
    for name, (text, named) in texts.items():
        path = tmp / f"{name}.toml"
        path.write_text(text, encoding="utf-8")
        out[name] = (path, named)
    return out


@pytest.mark.parametrize("case", ["missing", "not_toml", "unknown_key", "bad_value"])
def test_a_bad_flag_config_is_a_configuration_error(
    fleet: Fleet, cli: CliRunner, tmp_path: Path, case: str
) -> None:
    path, named = _flag_configs(tmp_path)[case]
    db = tmp_path / "untouched.duckdb"
    args = ["run", str(fleet.fleet_dir), "--db", str(db), "--flag-config", str(path)]
    line = _one_line_failure(cli.invoke(app, args), 2, "run")
    assert str(path) in line and named in line
    assert not db.exists()  # refused before anything was written


def test_a_bad_solver_is_a_usage_error(fleet: Fleet, cli: CliRunner, tmp_path: Path) -> None:
    args = ["run", str(fleet.fleet_dir), "--db", str(tmp_path / "x.duckdb"), "--solver", "fem"]
    line = _one_line_failure(cli.invoke(app, args), 2, "run")
    assert "--solver" in line and "'fem'" in line


@pytest.mark.parametrize("text", ["2024-13-01", "05.03.2024", "tomorrow"])
def test_a_bad_holdout_date_is_a_usage_error(fleet: Fleet, cli: CliRunner, text: str) -> None:
    args = ["close-loop", "--db", str(fleet.db), "--holdout-from", text, "--json", "x.json"]
    line = _one_line_failure(cli.invoke(app, args), 2, "close-loop")
    assert "--holdout-from" in line and text in line


@pytest.mark.parametrize(
    ("option", "value"),
    [("--revision", "r99-nothing"), ("--wagon", "NOPE-0001"), ("--event", "NOPE-0001-x")],
)
def test_an_unknown_key_in_record_names_it(
    fleet: Fleet, cli: CliRunner, tmp_path: Path, option: str, value: str
) -> None:
    args = ["record", "--db", str(fleet.db), "--wagon", WAGON, "--out", str(tmp_path / "r.rrd")]
    args += [option, value]
    line = _one_line_failure(cli.invoke(app, args), 1, "record")
    assert value in line
    assert not (tmp_path / "r.rrd").exists()


def test_a_database_held_by_another_writer_exits_75(fleet: Fleet, cli: CliRunner) -> None:
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(fleet.db):
        result = cli.invoke(app, ["run", str(fleet.fleet_dir), "--db", str(fleet.db)])
    line = _one_line_failure(result, 75, "run")
    assert str(fleet.db) in line


@pytest.mark.parametrize(("command", "module"), [("fleet", "psutil"), ("ingest", "psutil")])
def test_a_benchmark_without_the_bench_extra_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch, command: str, module: str, tmp_path: Path
) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # as if it were not installed
    args = ["bench", command, "--workdir", str(tmp_path)]
    line = _one_line_failure(CliRunner().invoke(app, args), 2, f"bench {command}")
    assert module in line and 'pip install "fleetbrake[bench]"' in line


def test_quiet_and_verbose_together_are_refused() -> None:
    _one_line_failure(CliRunner().invoke(app, ["-q", "-v", "run", "x"]), 2, "run")


# --------------------------------------------------------------------------------------------
# Logging


def test_json_log_format_writes_one_object_per_record(fleet: Fleet, cli: CliRunner) -> None:
    args = ["--log-format", "json", "-v", "run", str(fleet.fleet_dir), "--db", str(fleet.db)]
    result = cli.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    records = [json.loads(line) for line in result.stderr.strip().splitlines()]
    assert records, "no log record at --verbose"
    for record in records:
        assert {"time", "level", "logger", "message"} <= set(record), record
        assert record["time"].endswith("Z")
    stages = [r for r in records if r["logger"] == "fleetbrake.app.run"]
    assert {r["level"] for r in stages} == {"INFO"}
    assert _last_json(result)["command"] == "run"  # stdout keeps the summary last


def test_an_error_in_json_log_format_is_one_record(fleet: Fleet, cli: CliRunner) -> None:
    args = ["--log-format", "json", "run", str(fleet.fleet_dir), "--solver", "fem"]
    result = cli.invoke(app, args)
    assert result.exit_code == 2
    (line,) = result.stderr.strip().splitlines()
    record = json.loads(line)
    assert record["level"] == "ERROR"
    assert record["command"] == "fleetbrake run" and record["exit_code"] == 2
    assert "--solver" in record["message"]


def test_quiet_leaves_only_errors(fleet: Fleet, cli: CliRunner) -> None:
    run = ["run", str(fleet.fleet_dir), "--db", str(fleet.db)]
    quiet = cli.invoke(app, ["-q", *run])
    assert quiet.exit_code == 0, quiet.output
    assert quiet.stderr == ""
    verbose = cli.invoke(app, ["-v", *run])
    assert "fleetbrake.app.run" in verbose.stderr  # the same run logs at --verbose


def test_a_command_leaves_logging_as_it_found_it(fleet: Fleet, cli: CliRunner) -> None:
    root, ours = logging.getLogger(), logging.getLogger("fleetbrake")
    before = (list(root.handlers), root.level, ours.level)
    result = cli.invoke(app, ["-v", "run", str(fleet.fleet_dir), "--db", str(fleet.db)])
    assert result.exit_code == 0, result.output
    assert (list(root.handlers), root.level, ours.level) == before


# --------------------------------------------------------------------------------------------
# close-loop: the report's file, and its summary last on stdout


def test_close_loop_prints_its_summary_last(fleet: Fleet, cli: CliRunner, tmp_path: Path) -> None:
    db = tmp_path / "fleet.duckdb"
    shutil.copy(fleet.db, db)
    report_path = tmp_path / "close-loop.json"
    args = ["close-loop", "--db", str(db), "--holdout-from", HOLDOUT, "--json", str(report_path)]
    result = cli.invoke(app, args)
    assert result.exit_code == 0, result.output
    summary = _last_json(result)
    report = json.loads(report_path.read_text())
    assert summary["command"] == "close-loop"
    assert summary["report"] == str(report_path)
    for key in ("new_revision", "effect"):
        assert summary[key] == report[key]
    assert summary["parameters"] == (report["parameters"] or {})
    for part in ("fit", "holdout"):
        for key in ("events", "rmse_before_k", "rmse_after_k"):
            assert summary[part][key] == report[part].get(key), (part, key)
    for key in ("adequate", "noise_k"):
        assert (key in summary) == (key in report)


@pytest.mark.parametrize("command", ["run", "watch"])
def test_an_engine_that_cannot_be_had_is_a_usage_error(
    fleet: Fleet, cli: CliRunner, tmp_path: Path, command: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # Ray not installed: `import ray` fails
    db = tmp_path / "fleet.duckdb"
    result = cli.invoke(app, [command, str(fleet.fleet_dir), "--db", str(db), "--engine", "ray"])
    line = _one_line_failure(result, 2, command)
    assert "--engine ray" in line and 'pip install "fleetbrake[ray]"' in line
    assert not db.exists()  # refused before anything was written


def test_synth_with_an_unknown_solver_is_a_usage_error(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "fleet"), "--solver", "fem"])
    line = _one_line_failure(result, 2, "synth")
    assert "fem" in line and "full" in line
    assert not (tmp_path / "fleet").exists()


# --------------------------------------------------------------------------------------------
# report


def test_report_writes_markdown_and_plots_from_the_views(fleet: Fleet, tmp_path: Path) -> None:
    out = tmp_path / "report"
    result = CliRunner().invoke(app, ["report", "--db", str(fleet.db), "--out", str(out)])
    assert result.exit_code == 0, result.output
    text = (out / "report.md").read_text()
    pictures = sorted(out.glob("*.png"))
    assert pictures and all(p.stat().st_size > 0 for p in pictures)
    for picture in pictures:  # every picture written is referenced from the Markdown
        assert picture.name in text
    assert WAGON in text


@pytest.mark.parametrize("what", ["missing database", "bad close-loop report"])
def test_report_on_unreadable_input_names_the_file(fleet: Fleet, tmp_path: Path, what: str) -> None:
    args = ["report", "--out", str(tmp_path / "report")]
    if what == "missing database":
        bad = tmp_path / "nowhere.duckdb"
        args += ["--db", str(bad)]
    else:
        bad = tmp_path / "close-loop.json"
        bad.write_text("{not json")
        args += ["--db", str(fleet.db), "--close-loop", str(bad)]
    line = _one_line_failure(CliRunner().invoke(app, args), 1, "report")
    assert str(bad) in line


# --------------------------------------------------------------------------------------------
# The benchmarks' meters and peers stay out of the runtime path

BENCH_EXTRA = ("psutil", "skfem")


def test_no_runtime_module_imports_the_bench_extra() -> None:
    """Every module the command line can reach, the benchmarks aside, without psutil or
    scikit-fem among its imports (function-level imports included)."""
    grimp = pytest.importorskip("grimp")
    graph = grimp.build_graph("fleetbrake", include_external_packages=True)
    bench = ("fleetbrake.bench", "fleetbrake.cli.bench")
    seen: set[str] = set()
    todo = ["fleetbrake.cli.main"]
    offenders = []
    while todo:
        module = todo.pop()
        if module in seen or module.startswith(bench):
            continue
        seen.add(module)
        parts = module.split(".")
        todo += [".".join(parts[:k]) for k in range(1, len(parts)) if parts[0] == "fleetbrake"]
        for imported in graph.find_modules_directly_imported_by(module):
            if imported.split(".")[0] in BENCH_EXTRA:
                offenders.append(f"{module} imports {imported}")
            elif imported.startswith("fleetbrake"):
                todo.append(imported)
    assert "fleetbrake.app.run" in seen and "fleetbrake.viz.record" in seen
    assert not offenders, offenders


_IMPORTS_SCRIPT = """
import dataclasses, inspect, json, sys
sys.path.insert(0, {tests!r})
import pytest
from typer.testing import CliRunner
import fleetbrake.paper.reproduction as paper
from fleetbrake.cli.main import app
from test_cli import _use_refinement

coarse = dataclasses.replace(
    inspect.signature(paper.reproduce_paper).parameters["settings"].default,
    element="hex8", refinement=0.5, workers=1,
)
real_paper = paper.reproduce_paper
paper.reproduce_paper = lambda *a, **k: real_paper(settings=coarse)
with pytest.MonkeyPatch.context() as mp:
    _use_refinement(mp, {refinement!r})
    codes = [CliRunner().invoke(app, args).exit_code for args in {commands!r}]
print(json.dumps({{"codes": codes, "loaded": [m for m in {extra!r} if m in sys.modules]}}))
"""


def _commands_in_a_fresh_process(
    commands: list[list[str]], cache: Path, refinement: float
) -> dict[str, Any]:
    script = _IMPORTS_SCRIPT.format(
        tests=str(Path(__file__).parent),
        refinement=refinement,
        commands=commands,
        extra=BENCH_EXTRA,
    )
    env = {"FLEETBRAKE_CACHE_DIR": str(cache), "RAYON_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        capture_output=True,
        text=True,
        check=False,
        env={**os.environ, **env},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def test_run_close_loop_and_paper_import_neither_psutil_nor_skfem(
    fleet: Fleet, tmp_path: Path, rom_cache_dir: Path, rom_refinement: float
) -> None:
    db = tmp_path / "fleet.duckdb"
    shutil.copy(fleet.db, db)
    commands = [
        ["run", str(fleet.fleet_dir), "--db", str(db), "--json"],
        # every event is after the holdout date: the loop stops early, as it may
        ["close-loop", "--db", str(db), "--holdout-from", "2000-01-01", "--json", "x.json"],
        ["paper", "--json"],
    ]
    outcome = _commands_in_a_fresh_process(commands, rom_cache_dir, rom_refinement)
    assert outcome["codes"] == [0, 1, 0]
    assert outcome["loaded"] == []


def test_record_and_demo_do_not_import_skfem(
    fleet: Fleet, tmp_path: Path, rom_cache_dir: Path, rom_refinement: float
) -> None:
    commands = [
        ["record", "--db", str(fleet.db), "--wagon", WAGON, "--out", str(tmp_path / "w.rrd")],
        ["demo", "--out", str(tmp_path / "demo"), "--days", "1"],  # refused: no holdout day
    ]
    outcome = _commands_in_a_fresh_process(commands, rom_cache_dir, rom_refinement)
    assert outcome["codes"] == [0, 2]
    # rerun-sdk itself depends on psutil (a recording imports it); scikit-fem never
    assert "skfem" not in outcome["loaded"]
