"""Reader of the fleet registry ``fleet.toml`` (``shared/spec/fleet-data.md``, "Registry").

Usage::

    from fleetbrake.fleet.registry import load_registry

    registry = load_registry("fleet/fleet.toml")    # RegistryError if missing or not TOML
    for problem in registry.problems:               # bad entries: reported, the rest goes on
        print(problem)   # fleet.toml: wagon SGG-0002, key cylinder_diameter_m: must be ...
    wagon = registry.wagon("SGG-0001")              # UnknownWagonError if absent or left out
    wagon.cylinder_diameter_m                       # 0.254 (SI, checked)
    wagon.geometry                                  # BlockGeometry with the wagon's wheel radius
    wagon.sensor_point_m                            # (x, y, z) of the sensor seat, metres

Every value is checked here, once: a :class:`WagonConfig` cannot hold a value of the wrong
type, sign or range (its constructor runs the same checks as the reader), so code downstream
trusts it. What happens to bad input:

* a bad key in ``[defaults]`` (unknown, wrong type, impossible value) is reported and ignored:
  the spec's default is used instead;
* a bad ``[[wagon]]`` entry (unknown key, wrong type, impossible value, no id, an id that does
  not match ``[A-Za-z0-9_-]{1,64}``) is reported, every problem of it, and the wagon is left out;
* an id given by more than one entry is reported and every entry with it is left out (which one
  is meant cannot be told, and a wrong brake rigging gives wrong predictions and flags);
* a file that is missing, unreadable, not UTF-8 or not TOML raises :class:`RegistryError`.

Types: a number (float key) may be written as a TOML integer or float, never as a boolean;
a count (``blocks_per_bogie``, ``blocks_per_wheel``) must be a TOML integer (``16``, not ``16.0``).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import difflib
import json
import math
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from types import MappingProxyType
from typing import Any

from fleetbrake.errors import FleetbrakeError, UnknownKeyError
from fleetbrake.fleet.block import BLOCK_MATERIAL, BlockGeometry, Material
from fleetbrake.fleet.block import sensor_point_m as _sensor_point_m

__all__ = [
    "CONFIG_KEYS",
    "KNOWN_BLOCKS",
    "SPEC_DEFAULTS",
    "WAGON_ID_PATTERN",
    "BlockType",
    "Registry",
    "RegistryError",
    "RegistryProblem",
    "UnknownWagonError",
    "WagonConfig",
    "check_value",
    "load_registry",
]

WAGON_ID_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,64}")
"""What a wagon id must match, whole (fleet-data.md)."""


@dataclass(frozen=True)
class BlockType:
    """A block the registry's ``block`` key may name: geometry (on the spec's wheel), material."""

    geometry: BlockGeometry
    material: Material


KNOWN_BLOCKS: Mapping[str, BlockType] = MappingProxyType(
    {"cast-iron-bgu": BlockType(geometry=BlockGeometry(), material=BLOCK_MATERIAL)}
)
"""Block names a registry may use; the geometry's wheel radius is replaced by the wagon's."""


class RegistryError(FleetbrakeError):
    """The registry cannot be used at all (missing, unreadable, not TOML), or a lookup failed."""


class UnknownWagonError(RegistryError, UnknownKeyError):
    """A wagon id that the registry does not hold (absent, or left out because of its problems)."""


@dataclass(frozen=True)
class RegistryProblem:
    """One bad entry of the registry: where it is and what is wrong with it.

    ``key`` is relative to the wagon entry when ``wagon_id`` is set, otherwise to the file
    (``defaults.cylinder_diameter_m``, ``wagon``).
    """

    file: str
    wagon_id: str | None
    key: str | None
    message: str

    def __str__(self) -> str:
        where = []
        if self.wagon_id is not None:
            shown = self.wagon_id
            if not WAGON_ID_PATTERN.fullmatch(shown):
                shown = _show(shown)  # quoted, so that spaces or an empty id can be seen
            where.append(f"wagon {shown}")
        if self.key is not None:
            where.append(f"key {self.key}")
        if where:
            return f"{self.file}: {', '.join(where)}: {self.message}"
        return f"{self.file}: {self.message}"


# --------------------------------------------------------------------------------------------
# Value checks: the one place where registry values are judged.


def _show(value: object) -> str:
    """A value as the TOML file spells it, for messages."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # TOML basic-string escapes
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dt.date | dt.time):
        return f"{value.isoformat()} (a date/time)"
    return repr(value)


def _kind(value: object) -> str:
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a float"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, dt.date | dt.time):
        return "a date/time"
    return type(value).__name__


def _got(value: object) -> str:
    shown = _show(value)
    if isinstance(value, dict | list) or shown.endswith("(a date/time)"):
        return f"got {shown}"
    return f"got {shown} ({_kind(value)})"


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _is_count(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _positive(value: float) -> str | None:
    return None if math.isfinite(value) and value > 0 else "must be a positive number"


def _not_negative(value: float) -> str | None:
    return None if math.isfinite(value) and value >= 0 else "must be a number >= 0"


def _finite(value: float) -> str | None:
    return None if math.isfinite(value) else "must be a finite number"


def _efficiency(value: float) -> str | None:
    return None if math.isfinite(value) and 0 < value <= 1 else "must be in (0, 1]"


def _friction(value: float) -> str | None:
    return None if math.isfinite(value) and 0 < value < 1 else "must be in (0, 1)"


def _ambient(value: float) -> str | None:
    if math.isfinite(value) and -60.0 <= value <= 60.0:
        return None
    return "must be between -60 and 60 degC"


def _positive_count(value: int) -> str | None:
    return None if value > 0 else "must be a positive integer"


def _block_name(value: str) -> str | None:
    if value in KNOWN_BLOCKS:
        return None
    return f"must name a known block ({', '.join(_show(n) for n in KNOWN_BLOCKS)})"


@dataclass(frozen=True)
class _Rule:
    kind: str  # "number", "count" or "name"
    check: Callable[[Any], str | None]


_RULES: Mapping[str, _Rule] = MappingProxyType(
    {
        "wheel_radius_m": _Rule("number", _positive),
        "blocks_per_bogie": _Rule("count", _positive_count),
        "blocks_per_wheel": _Rule("count", _positive_count),
        "cylinder_diameter_m": _Rule("number", _positive),
        "rigging_ratio_total": _Rule("number", _positive),
        "rigging_ratio_after_central": _Rule("number", _positive),
        "rigging_efficiency": _Rule("number", _efficiency),
        "regulator_force_n": _Rule("number", _not_negative),
        "cylinder_spring_force_n": _Rule("number", _not_negative),
        "friction_coefficient": _Rule("number", _friction),
        "ambient_temp_c": _Rule("number", _ambient),
        "block": _Rule("name", _block_name),
        "sensor_depth_m": _Rule("number", _finite),
        "sensor_theta_deg": _Rule("number", _finite),
        "sensor_z_m": _Rule("number", _finite),
    }
)

CONFIG_KEYS: tuple[str, ...] = tuple(_RULES)
"""The keys of ``[defaults]``, each of which a ``[[wagon]]`` entry may override."""

_WAGON_ONLY_KEYS = ("id", "type")


def check_value(key: str, value: object) -> str | None:
    """Judge one registry value on its own: ``None`` if good, else what is wrong with it.

    Relations between keys (blocks per wheel against blocks per bogie, the sensor seat inside
    the block) are judged by :class:`WagonConfig` and :func:`load_registry`.
    """
    rule = _RULES.get(key)
    if rule is None:
        return f"unknown key (known: {', '.join(CONFIG_KEYS)})"
    if rule.kind == "number" and not _is_number(value):
        return f"must be a number, {_got(value)}"
    if rule.kind == "count" and not _is_count(value):
        return f"must be an integer, {_got(value)}"
    if rule.kind == "name" and not isinstance(value, str):
        return f"must be a string, {_got(value)}"
    problem = rule.check(value)
    return None if problem is None else f"{problem}, got {_show(value)}"


def _cross_problems(values: Mapping[str, Any]) -> list[tuple[tuple[str, ...], str]]:
    """Problems between keys of a set of individually good values.

    Each problem comes with the keys involved, the first being the one to blame when the
    section at hand sets it.
    """
    problems: list[tuple[tuple[str, ...], str]] = []
    per_wheel, per_bogie = values["blocks_per_wheel"], values["blocks_per_bogie"]
    if per_wheel > per_bogie:
        problems.append(
            (
                ("blocks_per_wheel", "blocks_per_bogie"),
                f"blocks_per_wheel ({per_wheel}) exceeds blocks_per_bogie ({per_bogie})",
            )
        )
    geometry = KNOWN_BLOCKS[values["block"]].geometry
    depth_m, theta_deg, z_m = (
        values[k] for k in ("sensor_depth_m", "sensor_theta_deg", "sensor_z_m")
    )
    back_m = geometry.body_thickness_m + geometry.lug_height_m
    if not 0.0 < depth_m < back_m:
        problems.append(
            (
                ("sensor_depth_m",),
                f"the sensor seat must lie inside the block {_show(values['block'])}: depth in "
                f"(0, {back_m:g}) m from the friction face, got {depth_m!r}",
            )
        )
        return problems
    if depth_m < geometry.body_thickness_m:
        part, half_angle_deg, half_width_m = (
            "body",
            geometry.contact_angle_deg / 2,
            geometry.block_width_m / 2,
        )
    else:
        part, half_angle_deg, half_width_m = (
            "lug",
            geometry.lug_angle_deg / 2,
            geometry.lug_width_m / 2,
        )
    where = f"at depth {depth_m:g} m the sensor seat is in the {part}, which spans"
    if not abs(theta_deg) < half_angle_deg:
        problems.append(
            (
                ("sensor_theta_deg", "sensor_depth_m"),
                f"{where} theta in (-{half_angle_deg:g}, {half_angle_deg:g}) deg, "
                f"got {theta_deg!r}",
            )
        )
    if not abs(z_m) < half_width_m:
        problems.append(
            (
                ("sensor_z_m", "sensor_depth_m"),
                f"{where} z in (-{half_width_m:g}, {half_width_m:g}) m, got {z_m!r}",
            )
        )
    return problems


# --------------------------------------------------------------------------------------------
# One wagon's configuration.


@dataclass(frozen=True)
class WagonConfig:
    """The registry entry of one wagon, ``[defaults]`` applied; SI, checked on construction.

    Defaults are the values of fleet-data.md; every field but ``wagon_id`` (the entry's
    ``id``) is a key of ``fleet.toml``. Constructing one directly runs the same checks as
    :func:`load_registry` and raises ``ValueError`` naming every problem; integers given for
    float keys are stored as floats.

    Read by: ``fleetbrake ingest``, ``fleetbrake run``, ``fleetbrake watch``,
    ``fleetbrake close-loop``, ``fleetbrake record``, ``fleetbrake paper``,
    ``fleetbrake demo``.
    """

    wagon_id: str
    """The wagon's id (``id`` of its ``[[wagon]]`` entry), matching ``[A-Za-z0-9_-]{1,64}``."""
    type: str | None = None
    """The wagon type (``Sggmrs``); informative only."""
    wheel_radius_m: float = 0.46
    """Wheel radius (920 mm nominal wheel)."""
    blocks_per_bogie: int = 16
    """Brake blocks of one bogie (2Bgu: four blocks per wheel, four wheels)."""
    blocks_per_wheel: int = 4
    """Brake blocks acting on one wheel."""
    cylinder_diameter_m: float = 0.254
    """Bore of the brake cylinder."""
    rigging_ratio_total: float = 8.0
    """Total rigging ratio i_tot (central rigging 2 x rigging after the central one 4)."""
    rigging_ratio_after_central: float = 4.0
    """Rigging ratio after the central rigging, i_II."""
    rigging_efficiency: float = 0.83
    """Dynamic efficiency of the rigging, eta_dyn, in (0, 1]."""
    regulator_force_n: float = 2000.0
    """Spring force of the brake regulator (slack adjuster), F_s,rig, subtracted after the
    central rigging (block-model.md, eq. 3)."""
    cylinder_spring_force_n: float = 1500.0
    """Force of the brake cylinder's return spring, F_s,cylinder, subtracted from the
    pressure's (block-model.md, eq. 4)."""
    friction_coefficient: float = 0.15
    """Mean wheel-block friction coefficient, in (0, 1)."""
    ambient_temp_c: float = 10.0
    """Air temperature used where a log has no ``ambient_temp_c``."""
    block: str = "cast-iron-bgu"
    """The reference block (geometry and material, block-model.md)."""
    sensor_depth_m: float = 0.055
    """Sensor seat: radial distance from the friction face."""
    sensor_theta_deg: float = 0.0
    """Sensor seat: angular position, 0 the middle of the block."""
    sensor_z_m: float = 0.0
    """Sensor seat: axial position, 0 the middle of the block width."""

    def __post_init__(self) -> None:
        problems: list[str] = []
        if not isinstance(self.wagon_id, str) or not WAGON_ID_PATTERN.fullmatch(self.wagon_id):
            problems.append(
                f"wagon_id must match {WAGON_ID_PATTERN.pattern}, {_got(self.wagon_id)}"
            )
        wagon_type: object = self.type  # a registry file can hold anything here
        if wagon_type is not None and not isinstance(wagon_type, str):
            problems.append(f"type must be a string, {_got(wagon_type)}")
        values = {key: getattr(self, key) for key in CONFIG_KEYS}
        for key, value in values.items():
            problem = check_value(key, value)
            if problem is not None:
                problems.append(f"{key} {problem}")
        if not problems:
            problems.extend(message for _, message in _cross_problems(values))
        if problems:
            raise ValueError(f"WagonConfig {self.wagon_id!r}: " + "; ".join(problems))
        for key in CONFIG_KEYS:
            if _RULES[key].kind == "number":
                object.__setattr__(self, key, float(getattr(self, key)))

    @property
    def block_type(self) -> BlockType:
        """The reference block named by ``block``."""
        return KNOWN_BLOCKS[self.block]

    @property
    def geometry(self) -> BlockGeometry:
        """The wagon's block: the named block's geometry on this wagon's wheel radius."""
        return dataclasses.replace(self.block_type.geometry, wheel_radius_m=self.wheel_radius_m)

    @property
    def block_material(self) -> Material:
        """Thermal properties of the named block."""
        return self.block_type.material

    @property
    def sensor_point_m(self) -> tuple[float, float, float]:
        """Cartesian position (x, y, z) of the sensor seat, metres (block.py coordinates)."""
        return _sensor_point_m(
            self.geometry,
            depth_m=self.sensor_depth_m,
            theta_deg=self.sensor_theta_deg,
            z_m=self.sensor_z_m,
        )


SPEC_DEFAULTS: Mapping[str, Any] = MappingProxyType(
    {f.name: f.default for f in fields(WagonConfig) if f.name in _RULES}
)
"""The ``[defaults]`` of fleet-data.md: what applies where the registry says nothing valid."""


# --------------------------------------------------------------------------------------------
# The registry file.


@dataclass(frozen=True)
class Registry:
    """A loaded ``fleet.toml``: the good wagons, and every problem found on the way."""

    path: Path
    wagons: dict[str, WagonConfig]
    problems: list[RegistryProblem] = field(default_factory=list)
    defaults: Mapping[str, Any] = field(default_factory=lambda: SPEC_DEFAULTS)
    """The defaults in force: the spec's, overridden by the good keys of ``[defaults]``."""

    def wagon(self, wagon_id: str) -> WagonConfig:
        """The configuration of one wagon; :class:`UnknownWagonError` if the registry lacks it."""
        config = self.wagons.get(wagon_id)
        if config is not None:
            return config
        own = [p for p in self.problems if p.wagon_id == wagon_id]
        if own:
            raise UnknownWagonError(
                f"{self.path}: wagon {wagon_id} is in the registry but was left out: "
                + " | ".join(f"key {p.key}: {p.message}" for p in own)
            )
        raise UnknownWagonError(f"{self.path}: wagon {wagon_id} has no entry in the registry")

    def __contains__(self, wagon_id: object) -> bool:
        return wagon_id in self.wagons


def _suggest(key: str, known: tuple[str, ...]) -> str:
    close = difflib.get_close_matches(key, known, n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise RegistryError(f"{path}: registry file not found") from None
    except IsADirectoryError:
        raise RegistryError(f"{path}: is a directory, not a registry file") from None
    except OSError as error:
        raise RegistryError(
            f"{path}: cannot read the registry: {error.strerror or error}"
        ) from None
    except UnicodeDecodeError as error:
        raise RegistryError(f"{path}: not a TOML file (not UTF-8 text: {error.reason})") from None
    except tomllib.TOMLDecodeError as error:
        raise RegistryError(f"{path}: not a valid TOML file: {error}") from None


def _read_defaults(file: str, table: object, problems: list[RegistryProblem]) -> dict[str, Any]:
    defaults = dict(SPEC_DEFAULTS)
    if not isinstance(table, dict):
        problems.append(
            RegistryProblem(
                file,
                None,
                "defaults",
                f"must be a table [defaults], {_got(table)}; the spec's defaults are used",
            )
        )
        return defaults
    set_here: set[str] = set()
    for key, value in table.items():
        if key not in _RULES:
            problems.append(
                RegistryProblem(
                    file,
                    None,
                    f"defaults.{key}",
                    f"unknown key{_suggest(key, CONFIG_KEYS)}; ignored",
                )
            )
            continue
        problem = check_value(key, value)
        if problem is not None:
            problems.append(
                RegistryProblem(
                    file,
                    None,
                    f"defaults.{key}",
                    f"{problem}; the spec's default {_show(SPEC_DEFAULTS[key])} is used instead",
                )
            )
            continue
        defaults[key] = value
        set_here.add(key)
    # Keys between them: revert the culprit to the spec's value until consistent (the spec's
    # defaults are consistent, so this ends).
    while True:
        cross = _cross_problems(defaults)
        if not cross:
            return defaults
        keys, message = cross[0]
        culprit = next((k for k in keys if k in set_here), keys[0])
        problems.append(
            RegistryProblem(
                file,
                None,
                f"defaults.{culprit}",
                f"{message}; the spec's default {_show(SPEC_DEFAULTS[culprit])} is used instead",
            )
        )
        defaults[culprit] = SPEC_DEFAULTS[culprit]
        set_here.discard(culprit)


def _read_wagon(
    file: str,
    number: int,
    entry: object,
    defaults: Mapping[str, Any],
    problems: list[RegistryProblem],
) -> tuple[str | None, WagonConfig | None]:
    """One ``[[wagon]]`` entry: (its id if it has a usable one, its config if it is good)."""
    label = f"[[wagon]] entry #{number}"
    if not isinstance(entry, dict):
        problems.append(
            RegistryProblem(file, None, "wagon", f"{label} must be a table, {_got(entry)}")
        )
        return None, None
    raw_id = entry.get("id")
    if raw_id is None:
        problems.append(
            RegistryProblem(file, None, "id", f"{label} has no id; the entry is left out")
        )
        return None, None
    if not isinstance(raw_id, str):
        problems.append(
            RegistryProblem(
                file,
                None,
                "id",
                f"{label}: the id must be a string, {_got(raw_id)}; the entry is left out",
            )
        )
        return None, None
    wagon_id = raw_id
    if not WAGON_ID_PATTERN.fullmatch(wagon_id):
        problems.append(
            RegistryProblem(
                file,
                wagon_id,
                "id",
                f"must match {WAGON_ID_PATTERN.pattern} ({label}); the wagon is left out",
            )
        )
        return None, None
    found: list[RegistryProblem] = []
    overrides: dict[str, Any] = {}
    for key, value in entry.items():
        if key == "id":
            continue
        if key == "type":
            if not isinstance(value, str):
                found.append(
                    RegistryProblem(
                        file,
                        wagon_id,
                        key,
                        f"must be a string, {_got(value)}; the wagon is left out",
                    )
                )
            continue
        if key not in _RULES:
            found.append(
                RegistryProblem(
                    file,
                    wagon_id,
                    key,
                    f"unknown key{_suggest(key, CONFIG_KEYS + _WAGON_ONLY_KEYS)}; "
                    "the wagon is left out",
                )
            )
            continue
        problem = check_value(key, value)
        if problem is not None:
            found.append(RegistryProblem(file, wagon_id, key, f"{problem}; the wagon is left out"))
            continue
        overrides[key] = value
    # Keys between them, the good overrides over the defaults in force (which are consistent,
    # so a problem here always involves a key of this entry).
    for keys, message in _cross_problems({**defaults, **overrides}):
        culprit = next((k for k in keys if k in overrides), None)
        if culprit is not None:
            found.append(
                RegistryProblem(file, wagon_id, culprit, f"{message}; the wagon is left out")
            )
    problems.extend(found)
    if found:
        return wagon_id, None
    return wagon_id, WagonConfig(
        wagon_id=wagon_id, type=entry.get("type"), **{**defaults, **overrides}
    )


def load_registry(path: str | Path) -> Registry:
    """Read and check a ``fleet.toml``.

    Raises :class:`RegistryError` (naming the file) only when nothing can go on: the file is
    missing, unreadable, or not TOML. Every bad entry inside a readable file is reported in
    ``Registry.problems`` (file, wagon, key, message) and the rest of the fleet is loaded.
    """
    path = Path(path)
    file = str(path)
    document = _read_toml(path)
    problems: list[RegistryProblem] = []

    for key, value in document.items():
        if key not in ("defaults", "wagon"):
            problems.append(
                RegistryProblem(
                    file,
                    None,
                    key,
                    f"unknown top-level key ({_got(value)}); ignored: a registry holds "
                    "[defaults] and [[wagon]] entries",
                )
            )

    defaults = _read_defaults(file, document.get("defaults", {}), problems)

    entries = document.get("wagon", [])
    if not isinstance(entries, list):
        problems.append(
            RegistryProblem(
                file, None, "wagon", f"must be an array of tables [[wagon]], {_got(entries)}"
            )
        )
        entries = []

    numbers_by_id: dict[str, list[int]] = {}
    wagons: dict[str, WagonConfig] = {}
    for number, entry in enumerate(entries, start=1):
        wagon_id, config = _read_wagon(file, number, entry, defaults, problems)
        if wagon_id is None:
            continue
        numbers_by_id.setdefault(wagon_id, []).append(number)
        if config is not None and wagon_id not in wagons:
            wagons[wagon_id] = config

    for wagon_id, numbers in numbers_by_id.items():
        if len(numbers) > 1:
            wagons.pop(wagon_id, None)
            listed = ", ".join(f"#{n}" for n in numbers)
            problems.append(
                RegistryProblem(
                    file,
                    wagon_id,
                    "id",
                    f"given by {len(numbers)} [[wagon]] entries ({listed}); which one is meant "
                    "cannot be told, so the wagon is left out",
                )
            )

    return Registry(
        path=path, wagons=wagons, problems=problems, defaults=MappingProxyType(defaults)
    )
