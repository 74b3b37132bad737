"""What the generator knows about the fleet it wrote: the truth records and their files.

::

    truth = load_truth("out")   # read back from out/truth/truth.json
    truth.events                # every true braking
    truth.anomalies             # dragging_brake, weak_brake, sensor_fault (open/frozen/loose/drift)
    truth.files                 # every log file written, what was done to it, and if it is bad
    truth.series("SGG-0001")    # per second: true pressure, force, heat input, temperatures

Layout::

    out/truth/truth.json                             # everything but the series
    out/truth/series/<wagon>.parquet                 # 1 Hz over the whole period
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from fleetbrake.model.effects import EffectSet
from fleetbrake.synth.config import SynthConfig

__all__ = [
    "SERIES_COLUMNS",
    "SERIES_DIR",
    "TRUTH_DIR",
    "TRUTH_JSON",
    "Anomaly",
    "FileTruth",
    "FleetTruth",
    "TrueEvent",
    "WagonTruth",
    "format_utc",
    "jsonable",
    "load_truth",
]

TRUTH_DIR = "truth"
TRUTH_JSON = "truth.json"
SERIES_DIR = "series"
TRUTH_FORMAT_VERSION = 1

TIME_FORMAT = "%Y-%m-%dT%H:%M:%SZ"
"""UTC times in ``truth.json``."""


def format_utc(time_utc: dt.datetime | None) -> str | None:
    """A time as ``truth.json`` writes it (None stays None)."""
    return None if time_utc is None else time_utc.strftime(TIME_FORMAT)


def _parse(text: str | None) -> dt.datetime | None:
    return None if text is None else dt.datetime.strptime(text, TIME_FORMAT)


def jsonable(value: Any) -> Any:
    """``value`` as JSON can hold it: times as text, floats to 9 decimals, numpy scalars as
    Python's."""
    if isinstance(value, dt.datetime):
        return format_utc(value)
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, float):
        return round(value, 9)
    if isinstance(value, np.generic):
        return jsonable(value.item())
    return value


def _record_to_dict(record: Any) -> dict[str, Any]:
    return {f.name: jsonable(getattr(record, f.name)) for f in dataclasses.fields(record)}


def _parse_times(key: str, value: Any) -> Any:
    """``*_utc`` strings back to datetimes, also inside nested mappings."""
    if isinstance(value, Mapping):
        return {k: _parse_times(k, v) for k, v in value.items()}
    if key.endswith("_utc") and isinstance(value, str):
        return _parse(value)
    return value


def _record_from_dict(cls: type, data: Mapping[str, Any]) -> Any:
    values = {
        f.name: _parse_times(f.name, data[f.name])
        for f in dataclasses.fields(cls)
        if f.name in data
    }
    return cls(**values)


@dataclass(frozen=True)
class TrueEvent:
    """A braking as the generator made it.

    ``start_utc``: first second with the cylinder above ``BASELINE_BAR`` (activation);
    ``end_utc``: first second back at or below it after the release (the release).
    ``recorded``: the whole event lies in a session whose file is good (not truncated, not
    garbage); the file may still have the ordinary imperfections (missing rows, ...).
    """

    wagon_id: str
    kind: str
    """``stop`` (to standstill, held, released at rest), ``slowdown`` (to 50-80 % of the
    speed) or ``drag`` (a long low-pressure application at constant speed, downhill). What
    the generator meant: a long gentle slowdown may well meet the detector's drag rule."""
    start_utc: dt.datetime
    end_utc: dt.datetime
    command_utc: dt.datetime
    """When the brake valve was moved (the target pressure stepped up)."""
    release_command_utc: dt.datetime
    p_target_bar: float
    p_mean_bar: float
    """Time mean of the true pressure over [start, end] (eq. 1)."""
    v_start_kmh: float
    v_end_kmh: float
    recorded: bool
    file: str | None
    """Relative path of the log file holding it (None if the unit slept)."""
    detail: str | None = None
    """For a stop: ``station`` or ``signal``."""


@dataclass(frozen=True)
class Anomaly:
    """An injected anomaly and where it acts (UTC, end exclusive)."""

    wagon_id: str
    kind: str
    """``dragging_brake``, ``weak_brake`` or ``sensor_fault``."""
    start_utc: dt.datetime
    end_utc: dt.datetime
    subtype: str | None = None
    """For a sensor fault: ``open``, ``frozen``, ``loose`` or ``drift``."""
    file: str | None = None
    """For a sensor fault: the log file it is in."""
    parameters: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class FileTruth:
    """One file written under ``logs/``, what was done to it, and whether it is bad."""

    path: str
    wagon_id: str
    start_utc: dt.datetime
    """First sample of the session (the time in the name)."""
    end_utc: dt.datetime
    """Last sample of the session."""
    gzip: bool
    session_rows: int
    """Seconds of the session (rows before any imperfection)."""
    rows_written: int
    """Data rows in the file as written (complete ones, for a truncated file)."""
    imperfections: dict[str, Any] = field(default_factory=dict)
    bad: str | None = None
    """``truncated_mid_row``, ``truncated_gzip``, ``garbage``; None for a good file."""
    reason: str | None = None
    registered: bool = True
    """Whether the wagon has a good registry entry."""


@dataclass(frozen=True)
class WagonTruth:
    """One wagon: its registry status and what the generator chose for it."""

    wagon_id: str
    registry: str
    """``ok``, ``missing`` (logs, no entry) or ``bad`` (an entry with a bad value)."""
    registry_overrides: dict[str, Any]
    ambient_column: str
    """``values``, ``empty`` or ``absent``."""
    ambient_source: str
    """``log`` (truth simulated with the true air temperature) or ``registry``."""
    registry_ambient_c: float
    mass_kg: float
    """Mass braked by the wagon's own brake: with the declared force chain it sets the
    train's deceleration (every wagon of the train brakes alike)."""
    sleep_after_s: int
    """The unit sleeps after the wagon has stood this long."""
    days: int
    series: str
    """Relative path of the truth series (parquet)."""


@dataclass
class FleetTruth:
    """Everything the generator knows about the fleet it wrote."""

    out_dir: Path
    config: SynthConfig
    start_utc: dt.datetime
    end_utc: dt.datetime
    wagons: list[WagonTruth]
    effects: EffectSet
    anomalies: list[Anomaly]
    events: list[TrueEvent]
    files: list[FileTruth]
    registry_problems: list[dict[str, Any]]
    rom: dict[str, Any]

    @property
    def fleet_dir(self) -> Path:
        return self.out_dir

    @property
    def truth_dir(self) -> Path:
        return self.out_dir / TRUTH_DIR

    def wagon(self, wagon_id: str) -> WagonTruth:
        for wagon in self.wagons:
            if wagon.wagon_id == wagon_id:
                return wagon
        raise KeyError(wagon_id)

    def series(self, wagon_id: str) -> pl.DataFrame:
        """The wagon's 1 Hz truth (see :data:`SERIES_COLUMNS`)."""
        return pl.read_parquet(self.truth_dir / self.wagon(wagon_id).series)

    def bad_files(self) -> list[FileTruth]:
        return [f for f in self.files if f.bad is not None]

    def to_dict(self) -> dict[str, Any]:
        return {
            "format_version": TRUTH_FORMAT_VERSION,
            "generator": "fleetbrake synth",
            "config": self.config.to_dict(),
            "start_utc": format_utc(self.start_utc),
            "end_utc": format_utc(self.end_utc),
            "effects": self.effects.to_list(),
            "rom": jsonable(self.rom),
            "wagons": [_record_to_dict(w) for w in self.wagons],
            "anomalies": [_record_to_dict(a) for a in self.anomalies],
            "events": [_record_to_dict(e) for e in self.events],
            "files": [_record_to_dict(f) for f in self.files],
            "registry_problems": jsonable(self.registry_problems),
        }

    @classmethod
    def from_dict(cls, out_dir: Path, data: Mapping[str, Any]) -> FleetTruth:
        return cls(
            out_dir=Path(out_dir),
            config=SynthConfig.from_dict(data["config"]),
            start_utc=dt.datetime.strptime(data["start_utc"], TIME_FORMAT),
            end_utc=dt.datetime.strptime(data["end_utc"], TIME_FORMAT),
            wagons=[_record_from_dict(WagonTruth, w) for w in data["wagons"]],
            effects=EffectSet.from_list(data["effects"]),
            anomalies=[_record_from_dict(Anomaly, a) for a in data["anomalies"]],
            events=[_record_from_dict(TrueEvent, e) for e in data["events"]],
            files=[_record_from_dict(FileTruth, f) for f in data["files"]],
            registry_problems=list(data["registry_problems"]),
            rom=dict(data["rom"]),
        )


SERIES_COLUMNS: tuple[str, ...] = (
    "time_utc",
    "awake",
    "speed_kmh",
    "distance_m",
    "elevation_m",
    "brake_pressure_bar",
    "block_force_n",
    "heat_flux_w_m2",
    "ambient_c",
    "seat_c",
    "sensor_c",
    "contact_mean_c",
    "contact_max_c",
)
"""Columns of a truth series: ``awake`` (the unit was recording), true speed, cumulative
distance, elevation, cylinder pressure; the block force (anomalies included); the heat flux
into the friction face at the sample (effects included; step n of the simulation is the mean
of samples n and n+1); the air temperature as the reader should take it (the log's, or the
registry's for a wagon without the sensor; before any ``ambient_offset`` effect); the block
temperature at the sensor seat, the noise-free sensor reading (sensor effects included,
sensor faults not), the friction-face (wheel-block contact) mean and maximum."""


def load_truth(out_dir: str | Path) -> FleetTruth:
    """The truth of a fleet written by :func:`generate_fleet`."""
    out_dir = Path(out_dir)
    data = json.loads((out_dir / TRUTH_DIR / TRUTH_JSON).read_text(encoding="utf-8"))
    return FleetTruth.from_dict(out_dir, data)
