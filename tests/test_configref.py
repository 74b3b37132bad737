"""The configuration reference: ``docs/configuration.md`` is what the configuration classes
say, every configuration class is in it (or excluded with a reason), every field has a
meaning and every class names the commands that read it; ``fleetbrake config`` prints it and
the help points to it."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from fleetbrake.cli.configref import (
    CONFIG_CLASSES,
    EXCLUDED,
    ConfigEntry,
    class_path,
    describe,
    entries,
    render,
    resolve,
    unit_of,
)
from fleetbrake.cli.main import app

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "python" / "fleetbrake"
REFERENCE = ROOT / "docs" / "configuration.md"

ENTRIES = entries()


def _is_dataclass(node: ast.ClassDef) -> bool:
    for decorator in node.decorator_list:
        target = decorator.func if isinstance(decorator, ast.Call) else decorator
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name == "dataclass":
            return True
    return False


def _configuration_classes() -> set[str]:
    """``module:Class`` of every dataclass of the package named ``...Config`` or
    ``...Settings`` (read from the source, so that nothing needs importing)."""
    found = set()
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        module = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (
                isinstance(node, ast.ClassDef)
                and node.name.endswith(("Config", "Settings"))
                and _is_dataclass(node)
            ):
                found.add(f"{module}:{node.name}")
    return found


def test_the_reference_file_is_what_the_classes_say() -> None:
    assert REFERENCE.read_text(encoding="utf-8") == render(), (
        "docs/configuration.md is out of date: run `make docs`"
    )


def test_every_configuration_class_is_in_the_reference_or_excluded() -> None:
    listed = {entry.path for entry in ENTRIES}
    missing = _configuration_classes() - listed - set(EXCLUDED)
    assert not missing, f"add to CONFIG_CLASSES or EXCLUDED (with the reason): {sorted(missing)}"
    assert "fleetbrake.fleet.registry:WagonConfig" in listed


@pytest.mark.parametrize("path", [*(entry.path for entry in CONFIG_CLASSES), *EXCLUDED])
def test_each_listed_class_lives_where_the_list_says(path: str) -> None:
    assert class_path(resolve(path)) == path


@pytest.mark.parametrize("entry", ENTRIES, ids=lambda entry: entry.path.rpartition(":")[2])
def test_each_class_names_its_readers_and_each_field_its_meaning(entry: ConfigEntry) -> None:
    doc = describe(entry)
    undocumented = [row.name for row in doc.fields if not row.meaning]
    assert doc.read_by, f"{doc.name}: no last line `Read by: ``fleetbrake ...``.`"
    assert not undocumented, f"{doc.name}: fields without an attribute docstring: {undocumented}"


def _options(command: Any) -> set[str]:
    """Every option name of ``command`` and its sub-commands (typer's own click classes)."""
    names = {opt for param in command.params for opt in (*param.opts, *param.secondary_opts)}
    for sub in getattr(command, "commands", {}).values():
        names |= _options(sub)
    return names


def test_the_options_named_in_the_reference_exist() -> None:
    known = _options(typer.main.get_command(app))
    named = {option for entry in CONFIG_CLASSES for option in entry.options.values()}
    assert named - known == set()
    for entry in CONFIG_CLASSES:
        fields = {spec.name for spec in dataclasses.fields(resolve(entry.path))}
        assert set(entry.options) <= fields, entry.path


@pytest.mark.parametrize(
    ("name", "unit"),
    [
        ("settle_s", "s"),
        ("frozen_noise_k", "K"),
        ("drift_max_rate_k_per_h", "K/h"),
        ("power_noise_w_per_sqrt_s", "W/√s"),
        ("contact_limit_c", "°C"),
        ("solar_heating_w_m2", "W/m²"),
        ("speed_noise_kmh", "km/h"),
        ("weak_ratio", ""),
        ("max_payload_bytes", "bytes"),
    ],
)
def test_the_unit_comes_from_the_name(name: str, unit: str) -> None:
    assert unit_of(name) == unit


def test_the_config_command_prints_the_reference_and_checks_a_file(tmp_path: Path) -> None:
    cli = CliRunner()
    printed = cli.invoke(app, ["config"])
    assert printed.exit_code == 0, printed.output
    assert printed.stdout == render()
    good, stale = tmp_path / "good.md", tmp_path / "stale.md"
    good.write_text(printed.stdout, encoding="utf-8")
    stale.write_text(printed.stdout.replace("| `", "| `x", 1), encoding="utf-8")
    assert cli.invoke(app, ["config", "--check", str(good)]).exit_code == 0
    for path in (stale, tmp_path / "absent.md"):
        result = cli.invoke(app, ["config", "--check", str(path)])
        assert result.exit_code == 1
        assert str(path) in result.stderr


@pytest.mark.parametrize(
    "command", [[], ["run"], ["watch"], ["synth"], ["demo"], ["bridge", "mqtt"]]
)
def test_the_help_points_to_the_reference(command: list[str]) -> None:
    result = CliRunner().invoke(app, [*command, "--help"], terminal_width=200)
    assert result.exit_code == 0, result.output
    assert "docs/configuration.md" in result.stdout
    assert "fleetbrake config" in result.stdout
