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
* a file that is missing, unreadable, not UTF-8 or not TOML raises :class:`RegistryError`;
* a problem touching a wagon whose results a warehouse holds is a configuration error
  (:meth:`Registry.check_held`, :class:`InvalidRegistryError`, exit 2): ``run`` checks every
  such wagon's entry, whole, at every run and writes nothing when one is invalid.

The allowed values of every key (type, unit, physical range) are in one table,
:data:`KEY_RANGES`, and each message about a value states its range.

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
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from types import MappingProxyType
from typing import Any

from fleetbrake.errors import EXIT_USAGE, ConfigError, FleetbrakeError, UnknownKeyError
from fleetbrake.fleet.block import BLOCK_MATERIAL, BlockGeometry, Material
from fleetbrake.fleet.block import sensor_point_m as _sensor_point_m

__all__ = [
    "CONFIG_KEYS",
    "KEY_RANGES",
    "KNOWN_BLOCKS",
    "SPEC_DEFAULTS",
    "WAGON_ID_PATTERN",
    "BlockType",
    "InvalidRegistryError",
    "KeyRange",
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


class InvalidRegistryError(RegistryError, ConfigError):
    """A registry value that makes a command's work impossible: a configuration error (exit 2)
    naming the file, wagon, key and allowed range, raised before anything is written."""

    exit_code = EXIT_USAGE


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
    """What is wrong, with the allowed values."""
    outcome: str = ""
    """What the reader does about it (``the wagon is left out``); empty for nothing."""

    def __str__(self) -> str:
        if self.outcome:
            return f"{self.where()}: {self.message}; {self.outcome}"
        return f"{self.where()}: {self.message}"

    def where(self) -> str:
        """The file, and the wagon and key when the problem has them."""
        where = []
        if self.wagon_id is not None:
            shown = self.wagon_id
            if not WAGON_ID_PATTERN.fullmatch(shown):
                shown = _show(shown)  # quoted, so that spaces or an empty id can be seen
            where.append(f"wagon {shown}")
        if self.key is not None:
            where.append(f"key {self.key}")
        return ": ".join([self.file, ", ".join(where)]) if where else self.file


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


@dataclass(frozen=True)
class KeyRange:
    """What one registry key may hold: its type, unit and physical range.

    ``low`` and ``high`` bound a number or a count (None: unbounded on that side, the value
    still finite); ``low_open`` / ``high_open`` exclude the bound itself. A ``name`` key
    (``block``) has no bounds: it must name one of :data:`KNOWN_BLOCKS`.
    """

    kind: str
    """``number`` (a TOML integer or float), ``count`` (a TOML integer) or ``name``."""
    unit: str = ""
    """The unit the key's name carries (``m``, ``N``, ``degC``, ``deg``); empty for none."""
    low: float | None = None
    """Lower bound of the range; None for no lower bound."""
    high: float | None = None
    """Upper bound of the range; None for no upper bound."""
    low_open: bool = False
    """True when ``low`` itself is outside the range."""
    high_open: bool = False
    """True when ``high`` itself is outside the range."""

    def allowed(self) -> str:
        """The range as a message states it: ``in (0.05, 0.6] m``, ``a known block (...)``."""
        if self.kind == "name":
            return f"a known block ({', '.join(_show(n) for n in KNOWN_BLOCKS)})"
        what = "an integer" if self.kind == "count" else "a number"
        if self.low is None and self.high is None:
            return f"a finite {what.split()[-1]}"
        else:
            low = "-inf" if self.low is None else f"{self.low:g}"
            high = "inf" if self.high is None else f"{self.high:g}"
            opening = "(" if self.low is None or self.low_open else "["
            closing = ")" if self.high is None or self.high_open else "]"
            text = f"{what} in {opening}{low}, {high}{closing}"
        return f"{text} {self.unit}" if self.unit else text

    def holds(self, value: Any) -> bool:
        """True when ``value`` (of the right type) lies in the range."""
        if self.kind == "name":
            return value in KNOWN_BLOCKS
        try:
            number = float(value)
        except OverflowError:  # a TOML integer of hundreds of digits
            return False
        if not math.isfinite(number):
            return False
        if self.low is not None and (number < self.low or (self.low_open and number == self.low)):
            return False
        return self.high is None or not (
            number > self.high or (self.high_open and number == self.high)
        )


KEY_RANGES: Mapping[str, KeyRange] = MappingProxyType(
    {
        # 680 to 1,000 mm freight wheels, worn to new, with a margin
        "wheel_radius_m": KeyRange("number", "m", 0.3, 0.65),
        "blocks_per_bogie": KeyRange("count", "", 1, 64),
        "blocks_per_wheel": KeyRange("count", "", 1, 64),
        # 4 to 24 inch brake cylinders (the reference is 10 inch, 0.254 m)
        "cylinder_diameter_m": KeyRange("number", "m", 0.1, 0.6),
        "rigging_ratio_total": KeyRange("number", "", 0.0, 40.0, low_open=True),
        "rigging_ratio_after_central": KeyRange("number", "", 0.0, 40.0, low_open=True),
        "rigging_efficiency": KeyRange("number", "", 0.0, 1.0, low_open=True),
        "regulator_force_n": KeyRange("number", "N", 0.0, 50_000.0),
        "cylinder_spring_force_n": KeyRange("number", "N", 0.0, 50_000.0),
        "friction_coefficient": KeyRange("number", "", 0.0, 1.0, low_open=True, high_open=True),
        "ambient_temp_c": KeyRange("number", "degC", -60.0, 60.0),
        "block": KeyRange("name"),
        # the seat's range is the named block's (checked between keys, the message states it)
        "sensor_depth_m": KeyRange("number", "m"),
        "sensor_theta_deg": KeyRange("number", "deg"),
        "sensor_z_m": KeyRange("number", "m"),
    }
)
"""Every key of ``[defaults]`` and ``[[wagon]]`` with its type, unit and physical range
(reference values: ``shared/spec/block-model.md``); the one table every registry value is
judged by, in the reader and in :class:`WagonConfig`. The ranges hold every wagon a freight
fleet may have, not only the reference's: a value outside one is a typing or unit slip
(a bore in mm, a sign lost)."""

CONFIG_KEYS: tuple[str, ...] = tuple(KEY_RANGES)
"""The keys of ``[defaults]``, each of which a ``[[wagon]]`` entry may override."""

_WAGON_ONLY_KEYS = ("id", "type")

_LEFT_OUT = "the wagon is left out"


def check_value(key: str, value: object) -> str | None:
    """Judge one registry value on its own: ``None`` if good, else what is wrong with it.

    Relations between keys (blocks per wheel against blocks per bogie, the sensor seat inside
    the block) are judged by :class:`WagonConfig` and :func:`load_registry`.
    """
    rule = KEY_RANGES.get(key)
    if rule is None:
        return f"unknown key (known: {', '.join(CONFIG_KEYS)})"
    if rule.kind == "number" and not _is_number(value):
        return f"must be a number, {_got(value)}"
    if rule.kind == "count" and not _is_count(value):
        return f"must be an integer, {_got(value)}"
    if rule.kind == "name" and not isinstance(value, str):
        return f"must be a string, {_got(value)}"
    if rule.holds(value):
        return None
    return f"must be {rule.allowed()}, got {_show(value)}"


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
    """Wheel radius (920 mm nominal wheel). Allowed: a number in [0.3, 0.65] m."""
    blocks_per_bogie: int = 16
    """Brake blocks of one bogie (2Bgu: four blocks per wheel, four wheels). Allowed: an
    integer in [1, 64]."""
    blocks_per_wheel: int = 4
    """Brake blocks acting on one wheel. Allowed: an integer in [1, 64], at most
    ``blocks_per_bogie``."""
    cylinder_diameter_m: float = 0.254
    """Bore of the brake cylinder. Allowed: a number in [0.1, 0.6] m."""
    rigging_ratio_total: float = 8.0
    """Total rigging ratio i_tot (central rigging 2 x rigging after the central one 4).
    Allowed: a number in (0, 40]."""
    rigging_ratio_after_central: float = 4.0
    """Rigging ratio after the central rigging, i_II. Allowed: a number in (0, 40]."""
    rigging_efficiency: float = 0.83
    """Dynamic efficiency of the rigging, eta_dyn. Allowed: a number in (0, 1]."""
    regulator_force_n: float = 2000.0
    """Spring force of the brake regulator (slack adjuster), F_s,rig, subtracted after the
    central rigging (block-model.md, eq. 3). Allowed: a number in [0, 50000] N."""
    cylinder_spring_force_n: float = 1500.0
    """Force of the brake cylinder's return spring, F_s,cylinder, subtracted from the
    pressure's (block-model.md, eq. 4). Allowed: a number in [0, 50000] N."""
    friction_coefficient: float = 0.15
    """Mean wheel-block friction coefficient. Allowed: a number in (0, 1)."""
    ambient_temp_c: float = 10.0
    """Air temperature used where a log has no ``ambient_temp_c``. Allowed: a number in
    [-60, 60] degC."""
    block: str = "cast-iron-bgu"
    """The reference block (geometry and material, block-model.md). Allowed: a known block
    ("cast-iron-bgu")."""
    sensor_depth_m: float = 0.055
    """Sensor seat: radial distance from the friction face. Allowed: a finite number, the
    seat inside the block (the message of a value outside states the block's range)."""
    sensor_theta_deg: float = 0.0
    """Sensor seat: angular position, 0 the middle of the block. Allowed: a finite number,
    the seat inside the block."""
    sensor_z_m: float = 0.0
    """Sensor seat: axial position, 0 the middle of the block width. Allowed: a finite
    number, the seat inside the block."""

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
            if KEY_RANGES[key].kind == "number":
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
    {f.name: f.default for f in fields(WagonConfig) if f.name in KEY_RANGES}
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

    def check_held(self, held: Collection[str]) -> None:
        """Refuse the registry when a problem touches a wagon in ``held`` (those whose results
        a warehouse holds): :class:`InvalidRegistryError` naming the first such problem.

        Such a wagon can neither be left out (its stored results would stand for a
        configuration the file no longer states) nor re-simulated (its entry is not usable).
        A problem of ``[defaults]`` touches every held wagon. A wagon not held is left out as
        :func:`load_registry` says, its files quarantined until its entry is fixed.
        """
        held = set(held)
        blocking = [
            p
            for p in self.problems
            if (p.wagon_id is not None and p.wagon_id in held)
            or (p.wagon_id is None and held and (p.key or "").startswith("defaults"))
        ]
        if not blocking:
            return
        first = blocking[0]
        more = f" ({len(blocking) - 1} more such problems)" if len(blocking) > 1 else ""
        raise InvalidRegistryError(
            f"{first.where()}: {first.message}{more}; the warehouse holds results of "
            f"{'this wagon' if first.wagon_id else 'the wagons'}: fix the registry, "
            "nothing was written"
        )


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
    except ValueError as error:  # an integer of more digits than Python converts
        raise RegistryError(f"{path}: not a usable TOML file: {error}") from None
    except RecursionError:
        raise RegistryError(
            f"{path}: not a usable TOML file: arrays or tables nested too deeply"
        ) from None


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
        if key not in KEY_RANGES:
            problems.append(
                RegistryProblem(
                    file,
                    None,
                    f"defaults.{key}",
                    f"unknown key{_suggest(key, CONFIG_KEYS)}",
                    "ignored",
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
                    problem,
                    f"the spec's default {_show(SPEC_DEFAULTS[key])} is used instead",
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
                message,
                f"the spec's default {_show(SPEC_DEFAULTS[culprit])} is used instead",
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
                f"must match {WAGON_ID_PATTERN.pattern} ({label})",
                _LEFT_OUT,
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
                        f"must be a string, {_got(value)}",
                        _LEFT_OUT,
                    )
                )
            continue
        if key not in KEY_RANGES:
            found.append(
                RegistryProblem(
                    file,
                    wagon_id,
                    key,
                    f"unknown key{_suggest(key, CONFIG_KEYS + _WAGON_ONLY_KEYS)}",
                    _LEFT_OUT,
                )
            )
            continue
        problem = check_value(key, value)
        if problem is not None:
            found.append(RegistryProblem(file, wagon_id, key, problem, _LEFT_OUT))
            continue
        overrides[key] = value
    # Keys between them, the good overrides over the defaults in force (which are consistent,
    # so a problem here always involves a key of this entry).
    for keys, message in _cross_problems({**defaults, **overrides}):
        culprit = next((k for k in keys if k in overrides), None)
        if culprit is not None:
            found.append(RegistryProblem(file, wagon_id, culprit, message, _LEFT_OUT))
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
                    "cannot be told",
                    _LEFT_OUT,
                )
            )

    return Registry(
        path=path, wagons=wagons, problems=problems, defaults=MappingProxyType(defaults)
    )
