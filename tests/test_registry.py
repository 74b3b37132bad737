"""Tests of fleetbrake.fleet.registry: the ``fleet.toml`` reader of fleet-data.md."""

from __future__ import annotations

import dataclasses
import math
import textwrap
from pathlib import Path

import pytest

from fleetbrake.fleet.block import BlockGeometry, sensor_point_m
from fleetbrake.fleet.registry import (
    CONFIG_KEYS,
    KEY_RANGES,
    SPEC_DEFAULTS,
    Registry,
    RegistryError,
    RegistryProblem,
    UnknownWagonError,
    WagonConfig,
    check_value,
    load_registry,
)

SPEC_EXAMPLE = """
[defaults]                          # every key here can be overridden per wagon
wheel_radius_m = 0.46               # 920 mm nominal wheel
blocks_per_bogie = 16               # 2Bgu: four blocks per wheel, four wheels per bogie
blocks_per_wheel = 4
cylinder_diameter_m = 0.254         # brake cylinder bore
rigging_ratio_total = 8.0           # i_tot = central rigging 2 x rigging after the central one 4
rigging_ratio_after_central = 4.0   # i_II
rigging_efficiency = 0.83           # eta_dyn
regulator_force_n = 2000.0          # F_s,rig
cylinder_spring_force_n = 1500.0    # F_s,cylinder
friction_coefficient = 0.15         # mean wheel-block friction coefficient
ambient_temp_c = 10.0               # used where a log has no ambient_temp_c
block = "cast-iron-bgu"             # reference block of block-model.md
sensor_depth_m = 0.055              # sensor seat: distance from the friction face, radial
sensor_theta_deg = 0.0              # angular position, 0 = middle of the block
sensor_z_m = 0.0                    # axial position, 0 = middle of the block width

[[wagon]]
id = "SGG-0001"
type = "Sggmrs"

[[wagon]]
id = "SGG-0002"
type = "Sggmrs"
cylinder_diameter_m = 0.305         # an override
"""

# The values of the [defaults] table of fleet-data.md, written out.
SPEC_VALUES = {
    "wheel_radius_m": 0.46,
    "blocks_per_bogie": 16,
    "blocks_per_wheel": 4,
    "cylinder_diameter_m": 0.254,
    "rigging_ratio_total": 8.0,
    "rigging_ratio_after_central": 4.0,
    "rigging_efficiency": 0.83,
    "regulator_force_n": 2000.0,
    "cylinder_spring_force_n": 1500.0,
    "friction_coefficient": 0.15,
    "ambient_temp_c": 10.0,
    "block": "cast-iron-bgu",
    "sensor_depth_m": 0.055,
    "sensor_theta_deg": 0.0,
    "sensor_z_m": 0.0,
}

GOOD_WAGON = '[[wagon]]\nid = "GOOD-1"\n'


def write(tmp_path: Path, text: str, name: str = "fleet.toml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text), encoding="utf-8")
    return path


def load(tmp_path: Path, text: str) -> Registry:
    return load_registry(write(tmp_path, text))


def only_problem(registry: Registry) -> RegistryProblem:
    assert len(registry.problems) == 1, [str(p) for p in registry.problems]
    return registry.problems[0]


# --------------------------------------------------------------------------------------------
# Good input, defaults and overrides


def test_spec_example_loads_without_problems(tmp_path: Path) -> None:
    registry = load(tmp_path, SPEC_EXAMPLE)
    assert registry.problems == []
    assert sorted(registry.wagons) == ["SGG-0001", "SGG-0002"]
    assert registry.path == tmp_path / "fleet.toml"
    first, second = registry.wagon("SGG-0001"), registry.wagon("SGG-0002")
    assert first.type == "Sggmrs"
    assert first.cylinder_diameter_m == 0.254
    assert second.cylinder_diameter_m == 0.305  # the override
    assert second.friction_coefficient == 0.15  # the rest from [defaults]
    assert "SGG-0001" in registry
    assert "SGG-9999" not in registry


def test_spec_defaults_apply_without_a_defaults_table(tmp_path: Path) -> None:
    registry = load(tmp_path, '[[wagon]]\nid = "SGG-0001"\n')
    assert registry.problems == []
    wagon = registry.wagon("SGG-0001")
    assert wagon.type is None
    for key, value in SPEC_VALUES.items():
        assert getattr(wagon, key) == value, key
        assert type(getattr(wagon, key)) is type(value), key
    assert dict(SPEC_DEFAULTS) == SPEC_VALUES
    assert set(CONFIG_KEYS) == set(SPEC_VALUES)
    assert WagonConfig(wagon_id="X") == dataclasses.replace(wagon, wagon_id="X", type=None)


def test_defaults_table_applies_and_wagon_overrides_it(tmp_path: Path) -> None:
    registry = load(
        tmp_path,
        """
        [defaults]
        friction_coefficient = 0.2
        ambient_temp_c = -5
        blocks_per_bogie = 8
        blocks_per_wheel = 2

        [[wagon]]
        id = "A"

        [[wagon]]
        id = "B"
        friction_coefficient = 0.25
        blocks_per_wheel = 1
        """,
    )
    assert registry.problems == []
    a, b = registry.wagon("A"), registry.wagon("B")
    assert (a.friction_coefficient, a.ambient_temp_c, a.blocks_per_bogie, a.blocks_per_wheel) == (
        0.2,
        -5.0,
        8,
        2,
    )
    assert (b.friction_coefficient, b.blocks_per_bogie, b.blocks_per_wheel) == (0.25, 8, 1)
    assert b.cylinder_diameter_m == 0.254  # neither section sets it: the spec's value
    assert registry.defaults["friction_coefficient"] == 0.2


def test_integer_is_fine_for_a_float_key_and_is_stored_as_float(tmp_path: Path) -> None:
    registry = load(tmp_path, '[[wagon]]\nid = "A"\nregulator_force_n = 2500\nambient_temp_c = 0\n')
    assert registry.problems == []
    wagon = registry.wagon("A")
    assert wagon.regulator_force_n == 2500.0
    assert isinstance(wagon.regulator_force_n, float)
    assert isinstance(wagon.ambient_temp_c, float)


def test_geometry_and_sensor_point_follow_the_registry(tmp_path: Path) -> None:
    registry = load(
        tmp_path,
        """
        [[wagon]]
        id = "A"
        wheel_radius_m = 0.42
        sensor_depth_m = 0.030
        sensor_theta_deg = 10.0
        sensor_z_m = 0.01
        """,
    )
    assert registry.problems == []
    wagon = registry.wagon("A")
    assert wagon.geometry == dataclasses.replace(BlockGeometry(), wheel_radius_m=0.42)
    r_m = 0.42 + 0.030
    x_m, y_m, z_m = wagon.sensor_point_m
    assert x_m == pytest.approx(r_m * math.sin(math.radians(10.0)), rel=1e-15)
    assert y_m == pytest.approx(r_m * math.cos(math.radians(10.0)), rel=1e-15)
    assert z_m == 0.01
    default = WagonConfig(wagon_id="B")
    assert default.geometry == BlockGeometry()
    assert default.sensor_point_m == sensor_point_m(BlockGeometry(), 0.055, 0.0, 0.0)
    assert default.sensor_point_m == pytest.approx((0.0, 0.515, 0.0))


def test_wagon_config_is_frozen_and_checks_itself() -> None:
    wagon = WagonConfig(wagon_id="A")
    with pytest.raises(dataclasses.FrozenInstanceError):
        wagon.friction_coefficient = 0.3  # type: ignore[misc]
    with pytest.raises(ValueError, match="cylinder_diameter_m") as caught:
        WagonConfig(wagon_id="A", cylinder_diameter_m=-0.3, friction_coefficient=True)
    assert "friction_coefficient" in str(caught.value)  # every problem named
    with pytest.raises(ValueError, match="wagon_id"):
        WagonConfig(wagon_id="has space")
    with pytest.raises(ValueError, match="blocks_per_wheel"):
        dataclasses.replace(wagon, blocks_per_wheel=17)


def test_check_value() -> None:
    assert check_value("cylinder_diameter_m", 0.3) is None
    assert check_value("regulator_force_n", 2500) is None  # an integer for a float key
    assert "in [0.1, 0.6] m" in str(check_value("cylinder_diameter_m", 0.0))
    assert "in [0.1, 0.6] m" in str(check_value("cylinder_diameter_m", 1))  # 1 m: a slip
    assert "number" in str(check_value("cylinder_diameter_m", False))
    assert "integer" in str(check_value("blocks_per_bogie", 16.0))
    assert "unknown key" in str(check_value("nonsense", 1))


# --------------------------------------------------------------------------------------------
# Bad wagon entries: one case per kind; the file, the wagon and the key are named, the bad
# wagon is left out, the good one beside it loads.

BAD_WAGON_CASES = {
    "unknown-key": ("cylinder_diamter_m = 0.3", "cylinder_diamter_m", "unknown key"),
    "bool-for-number": ("friction_coefficient = true", "friction_coefficient", "a boolean"),
    "string-for-number": ('wheel_radius_m = "0.46"', "wheel_radius_m", "must be a number"),
    "table-for-number": ("cylinder_diameter_m = {a = 1}", "cylinder_diameter_m", "a table"),
    "float-for-count": ("blocks_per_bogie = 16.0", "blocks_per_bogie", "must be an integer"),
    "bool-for-count": ("blocks_per_wheel = false", "blocks_per_wheel", "must be an integer"),
    "negative-diameter": ("cylinder_diameter_m = -0.3", "cylinder_diameter_m", "[0.1, 0.6] m"),
    "zero-radius": ("wheel_radius_m = 0", "wheel_radius_m", "[0.3, 0.65] m"),
    "nan-radius": ("wheel_radius_m = nan", "wheel_radius_m", "[0.3, 0.65] m"),
    "inf-radius": ("wheel_radius_m = inf", "wheel_radius_m", "[0.3, 0.65] m"),
    "negative-ratio": ("rigging_ratio_total = -8.0", "rigging_ratio_total", "(0, 40]"),
    "zero-ratio-ii": (
        "rigging_ratio_after_central = 0.0",
        "rigging_ratio_after_central",
        "(0, 40]",
    ),
    "zero-count": ("blocks_per_bogie = 0", "blocks_per_bogie", "[1, 64]"),
    "zero-efficiency": ("rigging_efficiency = 0.0", "rigging_efficiency", "(0, 1]"),
    "efficiency-above-1": ("rigging_efficiency = 1.2", "rigging_efficiency", "(0, 1]"),
    "zero-friction": ("friction_coefficient = 0.0", "friction_coefficient", "(0, 1)"),
    "friction-of-1": ("friction_coefficient = 1.0", "friction_coefficient", "(0, 1)"),
    "negative-regulator": ("regulator_force_n = -1.0", "regulator_force_n", "[0, 50000] N"),
    "negative-spring": (
        "cylinder_spring_force_n = -1500.0",
        "cylinder_spring_force_n",
        "[0, 50000] N",
    ),
    "ambient-too-cold": ("ambient_temp_c = -61.0", "ambient_temp_c", "[-60, 60] degC"),
    "ambient-too-hot": ("ambient_temp_c = 60.5", "ambient_temp_c", "[-60, 60] degC"),
    "unknown-block": ('block = "disc"', "block", "cast-iron-bgu"),
    "block-not-string": ("block = 3", "block", "must be a string"),
    "more-per-wheel-than-per-bogie": ("blocks_per_wheel = 17", "blocks_per_wheel", "exceeds"),
    "sensor-at-friction-face": ("sensor_depth_m = 0.0", "sensor_depth_m", "(0, 0.07)"),
    "sensor-negative-depth": ("sensor_depth_m = -0.01", "sensor_depth_m", "(0, 0.07)"),
    "sensor-behind-block": ("sensor_depth_m = 0.070", "sensor_depth_m", "(0, 0.07)"),
    "sensor-depth-string": ('sensor_depth_m = "deep"', "sensor_depth_m", "must be a number"),
    "sensor-beside-lug": ("sensor_theta_deg = 5.0", "sensor_theta_deg", "lug"),
    "sensor-beside-body": (
        "sensor_depth_m = 0.02\nsensor_theta_deg = 15.0",
        "sensor_theta_deg",
        "body",
    ),
    "sensor-axially-outside-lug": ("sensor_z_m = 0.021", "sensor_z_m", "lug"),
    "sensor-axially-outside-body": (
        "sensor_depth_m = 0.02\nsensor_z_m = -0.041",
        "sensor_z_m",
        "body",
    ),
    "type-not-string": ("type = 7", "type", "must be a string"),
}


@pytest.mark.parametrize(
    ("lines", "key", "says"), list(BAD_WAGON_CASES.values()), ids=list(BAD_WAGON_CASES)
)
def test_bad_wagon_entry_is_reported_and_left_out(
    tmp_path: Path, lines: str, key: str, says: str
) -> None:
    registry = load(tmp_path, f'{GOOD_WAGON}\n[[wagon]]\nid = "SGG-0002"\n{lines}\n')
    problem = only_problem(registry)
    assert (problem.file, problem.wagon_id, problem.key) == (
        str(tmp_path / "fleet.toml"),
        "SGG-0002",
        key,
    )
    text = str(problem)
    assert "fleet.toml" in text
    assert "wagon SGG-0002" in text
    assert f"key {key}:" in text
    assert says in text
    assert "left out" in text
    assert list(registry.wagons) == ["GOOD-1"]
    with pytest.raises(UnknownWagonError, match=r"SGG-0002.*left out"):
        registry.wagon("SGG-0002")


def test_problem_reads_like_the_brief(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    write(tmp_path, '[[wagon]]\nid = "SGG-0002"\ncylinder_diameter_m = -0.3\n')
    monkeypatch.chdir(tmp_path)
    problem = only_problem(load_registry("fleet.toml"))
    assert problem.file == "fleet.toml"
    assert str(problem).startswith(
        "fleet.toml: wagon SGG-0002, key cylinder_diameter_m: must be a number in [0.1, 0.6] m, "
        "got -0.3; the wagon is left out"
    )


def test_every_problem_of_a_wagon_is_reported(tmp_path: Path) -> None:
    registry = load(
        tmp_path,
        """
        [[wagon]]
        id = "SGG-0002"
        cylinder_diameter_m = -0.3
        blocks_per_bogie = 16.0
        sensor_theta_deg = 5.0
        colour = "red"
        """,
    )
    keys = sorted(p.key or "" for p in registry.problems)
    assert keys == ["blocks_per_bogie", "colour", "cylinder_diameter_m", "sensor_theta_deg"]
    assert all(p.wagon_id == "SGG-0002" for p in registry.problems)
    assert registry.wagons == {}


def test_unknown_key_suggests_the_known_one(tmp_path: Path) -> None:
    registry = load(tmp_path, '[[wagon]]\nid = "A"\ncylinder_diamter_m = 0.3\n')
    assert "did you mean cylinder_diameter_m?" in str(only_problem(registry))


def test_wagon_without_id(tmp_path: Path) -> None:
    registry = load(tmp_path, f'{GOOD_WAGON}\n[[wagon]]\ntype = "Sggmrs"\n')
    problem = only_problem(registry)
    assert (problem.wagon_id, problem.key) == (None, "id")
    text = str(problem)
    assert "fleet.toml" in text
    assert "key id" in text
    assert "entry #2 has no id" in text
    assert list(registry.wagons) == ["GOOD-1"]


def test_wagon_id_not_a_string(tmp_path: Path) -> None:
    registry = load(tmp_path, f"{GOOD_WAGON}\n[[wagon]]\nid = 7\n")
    problem = only_problem(registry)
    assert (problem.wagon_id, problem.key) == (None, "id")
    assert "fleet.toml" in str(problem)
    assert "entry #2" in str(problem)
    assert "got 7 (an integer)" in str(problem)
    assert list(registry.wagons) == ["GOOD-1"]


@pytest.mark.parametrize("bad_id", ["SGG 0003", "", "x" * 65, "SGG/0003", "SGG-0003\n"])
def test_wagon_id_not_matching_the_pattern(tmp_path: Path, bad_id: str) -> None:
    toml_id = bad_id.replace("\n", "\\n")
    registry = load(tmp_path, f'{GOOD_WAGON}\n[[wagon]]\nid = "{toml_id}"\n')
    problem = only_problem(registry)
    assert (problem.wagon_id, problem.key) == (bad_id, "id")
    text = str(problem)
    assert "fleet.toml" in text
    assert f'wagon "{toml_id}"' in text  # quoted, so the id's odd characters show
    assert "[A-Za-z0-9_-]{1,64}" in text
    assert list(registry.wagons) == ["GOOD-1"]


def test_id_of_64_characters_is_fine(tmp_path: Path) -> None:
    registry = load(tmp_path, f'[[wagon]]\nid = "{"A_b-9" * 12 + "abcd"}"\n')
    assert registry.problems == []
    assert len(next(iter(registry.wagons))) == 64


def test_duplicated_id_leaves_every_entry_with_it_out(tmp_path: Path) -> None:
    registry = load(
        tmp_path,
        f"""
        [[wagon]]
        id = "SGG-0002"
        {GOOD_WAGON}
        [[wagon]]
        id = "SGG-0002"
        cylinder_diameter_m = 0.305
        """,
    )
    problem = only_problem(registry)
    assert (problem.wagon_id, problem.key) == ("SGG-0002", "id")
    text = str(problem)
    assert "fleet.toml" in text
    assert "wagon SGG-0002" in text
    assert "#1, #3" in text
    assert list(registry.wagons) == ["GOOD-1"]


# --------------------------------------------------------------------------------------------
# Bad [defaults]: reported, the spec's default used instead, the fleet loads.


@pytest.mark.parametrize(
    ("line", "key"),
    [
        ("cylinder_diameter_m = -0.3", "cylinder_diameter_m"),
        ("friction_coefficient = true", "friction_coefficient"),
        ("blocks_per_bogie = 16.5", "blocks_per_bogie"),
        ('block = "disc"', "block"),
        ("ambient_temp_c = 99.0", "ambient_temp_c"),
        ("sensor_depth_m = 0.1", "sensor_depth_m"),
    ],
)
def test_bad_default_is_reported_and_the_spec_default_used(
    tmp_path: Path, line: str, key: str
) -> None:
    registry = load(tmp_path, f"[defaults]\n{line}\n\n{GOOD_WAGON}")
    problem = only_problem(registry)
    assert (problem.wagon_id, problem.key) == (None, f"defaults.{key}")
    text = str(problem)
    assert "fleet.toml" in text
    assert f"key defaults.{key}" in text
    assert "the spec's default" in text
    assert "used instead" in text
    assert getattr(registry.wagon("GOOD-1"), key) == SPEC_VALUES[key]


def test_inconsistent_defaults_revert_the_key_the_file_sets(tmp_path: Path) -> None:
    registry = load(tmp_path, f"[defaults]\nblocks_per_bogie = 2\n\n{GOOD_WAGON}")
    problem = only_problem(registry)
    assert problem.key == "defaults.blocks_per_bogie"
    assert "exceeds" in str(problem)
    wagon = registry.wagon("GOOD-1")
    assert (wagon.blocks_per_bogie, wagon.blocks_per_wheel) == (16, 4)


def test_unknown_key_in_defaults_is_ignored(tmp_path: Path) -> None:
    registry = load(tmp_path, f"[defaults]\nwheel_diameter_m = 0.92\n\n{GOOD_WAGON}")
    problem = only_problem(registry)
    assert (problem.wagon_id, problem.key) == (None, "defaults.wheel_diameter_m")
    assert "unknown key" in str(problem)
    assert "fleet.toml" in str(problem)
    assert registry.wagon("GOOD-1").wheel_radius_m == 0.46


def test_defaults_that_are_not_a_table(tmp_path: Path) -> None:
    registry = load(tmp_path, f"defaults = 3\n{GOOD_WAGON}")
    problem = only_problem(registry)
    assert problem.key == "defaults"
    assert "fleet.toml" in str(problem)
    assert registry.wagon("GOOD-1") == WagonConfig(wagon_id="GOOD-1")


def test_unknown_top_level_key(tmp_path: Path) -> None:
    registry = load(tmp_path, f'fleet_name = "north"\n{GOOD_WAGON}')
    problem = only_problem(registry)
    assert (problem.wagon_id, problem.key) == (None, "fleet_name")
    assert "fleet.toml" in str(problem)
    assert list(registry.wagons) == ["GOOD-1"]


def test_wagon_that_is_not_an_array_of_tables(tmp_path: Path) -> None:
    registry = load(tmp_path, "wagon = 3\n")
    assert only_problem(registry).key == "wagon"
    assert registry.wagons == {}
    registry = load(tmp_path, 'wagon = [{id = "A"}, 3]\n')
    problem = only_problem(registry)
    assert problem.key == "wagon"
    assert "entry #2" in str(problem)
    assert list(registry.wagons) == ["A"]


def test_empty_file_is_an_empty_fleet(tmp_path: Path) -> None:
    registry = load(tmp_path, "")
    assert registry.wagons == {}
    assert registry.problems == []


# --------------------------------------------------------------------------------------------
# Nothing can go on: RegistryError naming the file.


def test_missing_file_raises(tmp_path: Path) -> None:
    path = tmp_path / "nowhere" / "fleet.toml"
    with pytest.raises(RegistryError, match="not found") as caught:
        load_registry(path)
    assert str(path) in str(caught.value)


def test_not_toml_raises(tmp_path: Path) -> None:
    path = write(tmp_path, "id,type\nSGG-0001,Sggmrs\n")
    with pytest.raises(RegistryError, match="not a valid TOML") as caught:
        load_registry(path)
    assert str(path) in str(caught.value)


def test_not_utf8_raises(tmp_path: Path) -> None:
    path = tmp_path / "fleet.toml"
    path.write_bytes(b'[[wagon]]\nid = "\xff\xfe"\n')
    with pytest.raises(RegistryError, match="UTF-8") as caught:
        load_registry(path)
    assert str(path) in str(caught.value)


def test_directory_raises(tmp_path: Path) -> None:
    with pytest.raises(RegistryError) as caught:
        load_registry(tmp_path)
    assert str(tmp_path) in str(caught.value)


def test_unknown_wagon_lookup(tmp_path: Path) -> None:
    registry = load(tmp_path, GOOD_WAGON)
    with pytest.raises(UnknownWagonError) as caught:
        registry.wagon("SGG-0099")
    assert isinstance(caught.value, RegistryError)
    assert "fleet.toml" in str(caught.value)
    assert "SGG-0099" in str(caught.value)
    assert "no entry" in str(caught.value)


def test_each_key_documents_the_range_it_is_checked_against() -> None:
    """The configuration reference states each key's allowed values as the table has them."""
    from fleetbrake.cli.configref import CONFIG_CLASSES, describe

    (entry,) = [e for e in CONFIG_CLASSES if e.path.endswith(":WagonConfig")]
    meanings = {f.name: " ".join(f.meaning.split()) for f in describe(entry).fields}
    for key, allowed in KEY_RANGES.items():
        assert f"Allowed: {allowed.allowed()}" in meanings[key], key
