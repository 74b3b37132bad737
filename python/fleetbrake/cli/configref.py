"""The configuration reference (``docs/configuration.md``), generated from the classes.

Every configuration class documents itself: a class docstring whose last line names the
commands that read it (``Read by: ``fleetbrake run``, ``fleetbrake watch``.``), and an
attribute docstring after each field. This module holds the list of those classes
(:data:`CONFIG_CLASSES`, with how a user sets each), reads their fields (name, type, default)
and docstrings, takes each field's unit from its name's suffix (:data:`UNIT_SUFFIXES`) and
renders one Markdown page: one section and one table per class. ``fleetbrake config`` prints
it; ``make docs`` writes it to ``docs/configuration.md``, and a test fails when that file
differs from what this module renders.
"""

from __future__ import annotations

import ast
import dataclasses
import datetime as dt
import enum
import importlib
import inspect
import json
import re
import textwrap
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import PurePath
from types import MappingProxyType

__all__ = [
    "CONFIG_CLASSES",
    "EXCLUDED",
    "UNIT_SUFFIXES",
    "ClassDoc",
    "ConfigEntry",
    "FieldDoc",
    "class_path",
    "describe",
    "entries",
    "render",
    "unit_of",
]

REFERENCE_PATH = "docs/configuration.md"
"""Where the rendered reference lives in the repository."""


@dataclass(frozen=True)
class ConfigEntry:
    """One configuration class of the reference and how a user sets it."""

    path: str
    """``module:Class``, the class's import path."""
    set_by: str
    """How a user sets it: one Markdown sentence, ``Set by ...`` or ``Set in ...``."""
    options: Mapping[str, str] = field(default_factory=dict)
    """Field name -> the command-line option that sets it."""


_RUN_OPTIONS = MappingProxyType({"solver": "--solver", "refinement": "--refinement"})

CONFIG_CLASSES: tuple[ConfigEntry, ...] = (
    ConfigEntry(
        "fleetbrake.fleet.registry:WagonConfig",
        "Set in the fleet directory's `fleet.toml`: a key of `[defaults]` applies to every "
        "wagon, the same key in a `[[wagon]]` entry to that wagon (`id` for `wagon_id`).",
    ),
    ConfigEntry(
        "fleetbrake.flags.config:FlagConfig",
        "Set in the TOML file of `--flag-config FILE` (`run`, `watch`): top-level keys named "
        "as the fields; a key the file omits keeps its default.",
    ),
    ConfigEntry(
        "fleetbrake.ingest.config:IngestConfig",
        "Set in code; the commands use the defaults.",
    ),
    ConfigEntry(
        "fleetbrake.ingest.config:EventConfig",
        "Set in code; the commands use the defaults.",
    ),
    ConfigEntry(
        "fleetbrake.simulation.config:SimulationConfig",
        "Set by `--solver` (`run`, `watch`) and `--refinement` (`watch`); the rest in code.",
        _RUN_OPTIONS,
    ),
    ConfigEntry(
        "fleetbrake.simulation.estimates.config:EstimationConfig",
        "Set in code; the commands use the defaults.",
    ),
    ConfigEntry(
        "fleetbrake.closeloop.config:CloseLoopConfig",
        "Set by `--holdout-from` of `close-loop`; the rest in code.",
        MappingProxyType({"holdout_from": "--holdout-from"}),
    ),
    ConfigEntry(
        "fleetbrake.app.watch.service:WatchConfig",
        "Set by the options of `fleetbrake watch`; the rest in code.",
        MappingProxyType(
            {
                "poll_s": "--poll",
                "settle_s": "--settle",
                "rescan_s": "--rescan",
                "wait_s": "--wait",
                "flag_config_path": "--flag-config",
                "engine": "--engine",
                "workers": "--workers",
                "address": "--address",
                "rerun": "--rerun",
            }
        ),
    ),
    ConfigEntry(
        "fleetbrake.bridge.config:BridgeConfig",
        "Set by the options of `fleetbrake bridge mqtt`; the rest in code.",
        MappingProxyType(
            {
                "broker": "--broker",
                "landing": "--landing",
                "topic": "--topic",
                "wagon_level": "--wagon-level",
                "client_id": "--client-id",
                "protocol": "--protocol",
                "password_file": "--password-file",
                "session_expiry_s": "--session-expiry",
                "gap_s": "--gap",
                "max_file_s": "--max-file",
                "idle_s": "--idle",
                "max_unacked": "--max-unacked",
                "gzip": "--gzip",
            }
        ),
    ),
    ConfigEntry(
        "fleetbrake.synth.config:SynthConfig",
        "Set by the options of `fleetbrake synth` (`--no-imperfections`: every imperfection "
        "off); the rest in code.",
        MappingProxyType(
            {
                "wagons": "--wagons",
                "days": "--days",
                "seed": "--seed",
                "start": "--start",
                "effects": "--effect",
                "anomalies": "--anomalies",
                "gzip_fraction": "--gzip-fraction",
                "solver": "--solver",
                "refinement": "--refinement",
                "solar_heating_w_m2": "--solar-heating",
            }
        ),
    ),
    ConfigEntry(
        "fleetbrake.app.demo.config:DemoConfig",
        "Set by the options of `fleetbrake demo`; the rest in code.",
        MappingProxyType(
            {
                "wagons": "--wagons",
                "days": "--days",
                "seed": "--seed",
                "refinement": "--refinement",
            }
        ),
    ),
    ConfigEntry(
        "fleetbrake.paper.settings:RunSettings",
        "Set in code (`fleetbrake.paper.reproduction`); the command uses the defaults.",
    ),
)
"""The configuration classes of the reference, in the order of its sections. A class that is
the default of a field of one of them (``SimulationConfig.chain``) has its section after its
first holder's, found from the fields (:func:`entries`)."""

EXCLUDED: Mapping[str, str] = MappingProxyType(
    {
        "fleetbrake.model.effects.effect_set:EffectSet": "a value (the effects of a synthetic fleet, "
        "given with `--effect`), not a group of settings",
    }
)
"""Dataclasses that are not in the reference although named ``...Config`` or ``...Settings``
or held by a field of a listed class, each with the reason (``module:Class`` -> why)."""

UNIT_SUFFIXES: tuple[tuple[str, str], ...] = (
    ("_k_per_sqrt_s", "K/√s"),
    ("_w_per_sqrt_s", "W/√s"),
    ("_per_sqrt_s", "1/√s"),
    ("_k_per_h", "K/h"),
    ("_w_m2k", "W/(m² K)"),
    ("_w_m2", "W/m²"),
    ("_kmh", "km/h"),
    ("_mps", "m/s"),
    ("_bar", "bar"),
    ("_deg", "°"),
    ("_kj", "kJ"),
    ("_pa", "Pa"),
    ("_mk", "mK"),
    ("_bytes", "bytes"),
    ("_j", "J"),
    ("_n", "N"),
    ("_w", "W"),
    ("_c", "°C"),
    ("_k", "K"),
    ("_m", "m"),
    ("_s", "s"),
)
"""A field name's suffix -> the unit of its value (the longest matching suffix counts)."""

_READ_BY = re.compile(r"Read by: ((?:``fleetbrake[a-z -]*``)(?:, ``fleetbrake[a-z -]*``)*)\.")


def unit_of(name: str) -> str:
    """The unit a field name's suffix gives (``settle_s`` -> ``s``); empty when none."""
    for suffix, unit in UNIT_SUFFIXES:
        if name.endswith(suffix):
            return unit
    return ""


@dataclass(frozen=True)
class FieldDoc:
    """One row of a class's table."""

    name: str
    type: str
    """The annotation as written in the source."""
    unit: str
    default: str
    """The default as a reader would write it; ``required`` when there is none."""
    meaning: str
    """The attribute docstring on one line; empty when the field has none."""


@dataclass(frozen=True)
class ClassDoc:
    """One section of the reference."""

    entry: ConfigEntry
    name: str
    summary: str
    """The class docstring's first paragraph, on one line."""
    read_by: tuple[str, ...]
    """The commands of its ``Read by:`` line (empty when it has none)."""
    fields: tuple[FieldDoc, ...]

    @property
    def where(self) -> str:
        """``module.Class``."""
        return self.entry.path.replace(":", ".")


def resolve(path: str) -> type:
    """The class at ``module:Class``."""
    module, _, name = path.partition(":")
    cls = getattr(importlib.import_module(module), name)
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise TypeError(f"{path} is not a dataclass")
    return cls


def _class_node(cls: type) -> ast.ClassDef:
    node = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0]
    assert isinstance(node, ast.ClassDef)
    return node


def _source_fields(cls: type) -> dict[str, tuple[str, str]]:
    """Field name -> (annotation, attribute docstring) from the class's source (its bases'
    first, as :func:`dataclasses.fields` orders them)."""
    out: dict[str, tuple[str, str]] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        body = _class_node(klass).body
        for i, statement in enumerate(body):
            if not (
                isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name)
            ):
                continue
            doc = ""
            after = body[i + 1] if i + 1 < len(body) else None
            if (
                isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)
            ):
                doc = after.value.value
            out[statement.target.id] = (ast.unparse(statement.annotation), doc)
    return out


_ROLE = re.compile(r":[a-z]+:`~?([^`]+)`")
"""A Sphinx cross-reference (``:class:`~a.B```); rendered as its target in code."""


def _escaped(text: str) -> str:
    """``text`` for a Markdown table cell."""
    return text.replace("|", "\\|")


def markdown(text: str) -> str:
    """A docstring's text on one line, in Markdown (Sphinx roles and double backquotes as
    code), ready for a table cell."""
    text = " ".join(inspect.cleandoc(text).split())
    text = _ROLE.sub(lambda m: f"``{m[1]}``", text).replace("``", "`")
    return _escaped(text)


def _without_unit(meaning: str, unit: str) -> str:
    """``meaning`` without a leading ``unit: `` (the table has a unit column)."""
    for prefix in {unit, unit.replace("°C", "degC")} - {""}:
        if meaning.startswith(f"{prefix}: "):
            rest = meaning[len(prefix) + 2 :]
            return rest[:1].upper() + rest[1:]
    return meaning


def shown(value: object) -> str:
    """A default value as a reader writes it."""
    if isinstance(value, enum.Enum):
        value = value.value
    if isinstance(value, PurePath):
        value = str(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, dt.date):
        return value.isoformat()
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{k}: {shown(v)}" for k, v in value.items()) + "}"
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10_000:
        return f"{value:_}"
    return repr(value)


def _default(spec: dataclasses.Field[object]) -> str:
    if spec.default is not dataclasses.MISSING:
        return shown(spec.default)
    factory = spec.default_factory
    if factory is dataclasses.MISSING:
        return "required"
    if isinstance(factory, type):
        made = factory()
        if dataclasses.is_dataclass(made) or not isinstance(made, tuple | list | dict):
            return f"{factory.__name__}()"
        return shown(made)
    return shown(factory())


def describe(entry: ConfigEntry) -> ClassDoc:
    """The section of one configuration class."""
    cls = resolve(entry.path)
    doc = ast.get_docstring(_class_node(cls)) or ""
    paragraphs = [" ".join(p.split()) for p in doc.split("\n\n")]
    found = _READ_BY.fullmatch(paragraphs[-1]) if paragraphs else None
    read_by = tuple(c.strip("`") for c in found.group(1).split(", ")) if found else ()
    summary = paragraphs[0] if len(paragraphs) > 1 or not found else ""
    source = _source_fields(cls)
    rows = []
    for spec in dataclasses.fields(cls):
        annotation, meaning = source.get(spec.name, (str(spec.type), ""))
        unit = unit_of(spec.name)
        rows.append(
            FieldDoc(
                name=spec.name,
                type=annotation,
                unit=unit,
                default=_default(spec),
                meaning=_without_unit(markdown(meaning), unit),
            )
        )
    return ClassDoc(
        entry=entry,
        name=cls.__name__,
        summary=markdown(summary),
        read_by=read_by,
        fields=tuple(rows),
    )


_HEADER = """\
# Configuration

Every setting of fleetbrake, one section per configuration class: where it lives, how it is
set, the commands that read it, and a table of its fields. A field's unit is its name's
suffix; the command-line option that sets a field stands beside its name. Generated from
the classes' docstrings by `fleetbrake config`; `make docs` writes this file and a test
fails when it is out of date, so change the docstrings, not this file.

Units: {suffixes}.
"""


def _cell(text: str) -> str:
    return f"`{_escaped(text)}`"


def _section(doc: ClassDoc) -> list[str]:
    read_by = ", ".join(f"`{c}`" for c in doc.read_by) or "(not stated)"
    lines = [
        f"## {doc.name}",
        " ".join(filter(None, (f"`{doc.where}`.", doc.summary, doc.entry.set_by)))
        + f" Read by {read_by}.",
        "",
        "| field | type | unit | default | meaning |",
        "|---|---|---|---|---|",
    ]
    for row in doc.fields:
        option = doc.entry.options.get(row.name)
        name = f"`{row.name}`" + (f" (`{option}`)" if option else "")
        default = _cell(row.default) if row.default != "required" else "required"
        lines.append(f"| {name} | {_cell(row.type)} | {row.unit} | {default} | {row.meaning} |")
    return [*lines, ""]


def class_path(cls: type) -> str:
    """``module:Class`` of the module that defines ``cls``."""
    return f"{cls.__module__}:{cls.__qualname__}"


def _nested(cls: type) -> list[tuple[str, type]]:
    """(field, class) of the fields of ``cls`` whose default is a dataclass instance."""
    out: list[tuple[str, type]] = []
    for spec in dataclasses.fields(cls):
        factory: object = spec.default_factory
        inner = factory if isinstance(factory, type) else type(spec.default)
        if dataclasses.is_dataclass(inner) and class_path(inner) not in EXCLUDED:
            out.append((spec.name, inner))
    return out


def entries(listed: tuple[ConfigEntry, ...] = CONFIG_CLASSES) -> tuple[ConfigEntry, ...]:
    """The sections' classes: ``listed``, each followed by the classes its fields hold by
    default that ``listed`` does not name (depth first), "set in code, as ``Holder.field``"."""
    named = {entry.path for entry in listed}
    order: list[str] = []
    holders: dict[str, list[str]] = {}

    def visit(path: str) -> None:
        if path in order:
            return
        order.append(path)
        cls = resolve(path)
        for name, inner in _nested(cls):
            inner_path = class_path(inner)
            holders.setdefault(inner_path, []).append(f"{cls.__name__}.{name}")
            if inner_path not in named:
                visit(inner_path)

    for entry in listed:
        visit(entry.path)
    given = {entry.path: entry for entry in listed}
    return tuple(
        given.get(path)
        or ConfigEntry(path, "Set in code, as " + ", ".join(f"`{h}`" for h in holders[path]) + ".")
        for path in order
    )


def render(listed: tuple[ConfigEntry, ...] = CONFIG_CLASSES) -> str:
    """The reference: a header, then one section per class of :func:`entries`."""
    sections = [describe(entry) for entry in entries(listed)]
    used = {row.unit for section in sections for row in section.fields}
    suffixes = ", ".join(f"`{s}` {u}" for s, u in UNIT_SUFFIXES if u in used)
    lines = [_HEADER.format(suffixes=suffixes)]
    for section in sections:
        lines.extend(_section(section))
    return "\n".join(lines).rstrip("\n") + "\n"


if __name__ == "__main__":
    print(render(), end="")
