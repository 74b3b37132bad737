"""A synthetic fleet, written exactly as ``shared/spec/fleet-data.md`` says, with its truth beside it.

::

    from fleetbrake.model.effects import ConvectionSpeed, EffectSet
    from fleetbrake.synth.generator import SynthConfig, generate_fleet, load_truth

    truth = generate_fleet("out", SynthConfig(seed=7, effects=EffectSet((ConvectionSpeed(),))))
    truth.events            # every true braking (start/end UTC, kind, target pressure, ...)
    truth.anomalies         # dragging_brake, weak_brake, sensor_fault (open/frozen/loose/drift)
    truth.files             # every log file written, what was done to it, and if it is bad
    truth.series("SGG-0001")    # per second: true pressure, force, heat input, temperatures
    load_truth("out")       # the same, read back from out/truth/

Layout written::

    out/fleet.toml                                   # the registry (fleet-data.md)
    out/logs/<wagon>/<wagon>_<YYYYMMDDTHHMMSSZ>.csv[.gz]
    out/truth/truth.json                             # everything but the series
    out/truth/series/<wagon>.parquet                 # 1 Hz over the whole period

**Operation** (per wagon, continuous over ``days`` UTC days at 1 Hz): the wagon stands at a
yard, runs trips of one to three legs between stations, and stands again. A leg accelerates
at 0.1-0.3 m/s^2 to a line speed of 60-100 km/h and cruises; on the way come slowdowns
(a service braking to 50-80 % of the speed), drag brakings downhill (0.5-0.85 bar for 2-10
minutes at constant speed, the grade balancing the brake), line-speed changes and signal
stops; a leg ends with a stop braking (0.8-2.5 bar, sometimes up to 3.8 bar), the brake held
10-60 s at standstill, then released. The cylinder fills as a UIC G-mode brake does (95 % of
the target in about 20 s) and releases in about 45 s. The train's deceleration follows from
the wagon's own declared force chain and mass (every wagon of the train brakes alike).

**Recording.** The unit wakes when the wagon moves and sleeps after standing
``sleep_after_s`` (4-10 minutes): one file per session, many per day, gaps between them. The
block is simulated *continuously* (``fleetbrake.model.timeline.simulate_timeline`` with the
reduced model), so it keeps cooling while the unit sleeps.

**Readings.** ``block_temp_c`` = noise-free sensor (effects included) + Gaussian noise
(``sensor_noise_k``, 0.1 K: the Pt1000's), to 0.01 K; pressure + 3 mbar noise, quantised to
7 mbar; GPS speed with 0.3 km/h noise; ``distance_m`` since the session began. The air
temperature follows a daily sine plus a weather drift; wagons with an ambient sensor log it,
the others have no ``ambient_temp_c`` column (or an empty one), and their truth is simulated
with the registry's ``ambient_temp_c``: the value the reader will use.

**Imperfections** (``SynthConfig``; each can be switched off, :meth:`SynthConfig.clean`
switches all off) come from ``fleetbrake.fleet.logfile``'s injectors: missing rows and gaps,
duplicated and swapped rows, empty cells, frozen and jumping GPS speed, files truncated
mid-row and gzip files cut mid-stream, garbage files, a wagon with logs but no registry
entry, a registry entry with a bad value (that wagon's logs exist too), and one wagon writing
its columns in another order with an extra column.

**Anomalies** (``anomalies=True``; wagon 1 of the fleet stays clean when there are two or
more): a dragging brake (block force with no cylinder pressure, 15-40 min), a weak brake (the
block force at 40-60 % of the declared for one UTC day), and sensor faults in single files:
``open`` (reads far out of range), ``frozen``, ``loose`` (relaxes towards ambient), ``drift``
(a growing offset).

Everything is drawn from ``numpy`` generators seeded from ``seed`` and a fixed purpose code,
so the same configuration writes byte-identical files.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from fleetbrake.fleet import logfile
from fleetbrake.fleet.registry import SPEC_DEFAULTS, WagonConfig, load_registry
from fleetbrake.model.effects import AmbientOffset, EffectSet
from fleetbrake.model.physics import block_force_n
from fleetbrake.model.rom import ReducedModel
from fleetbrake.model.timeline import simulate_timeline

__all__ = [
    "SENSOR_FAULT_SUBTYPES",
    "Anomaly",
    "FileTruth",
    "FleetTruth",
    "SynthConfig",
    "TrueEvent",
    "WagonTruth",
    "generate_fleet",
    "load_truth",
    "summary",
]

SENSOR_FAULT_SUBTYPES: tuple[str, ...] = ("open", "frozen", "loose", "drift")

TRUTH_DIR = "truth"
TRUTH_JSON = "truth.json"
SERIES_DIR = "series"
TRUTH_FORMAT_VERSION = 1

G_M_S2 = 9.81
RISE_TAU_S = 20.0 / 3.0
"""G-mode cylinder filling: 95 % of the target pressure in about 20 s."""
RELEASE_TAU_S = 45.0 / 3.0
"""Release: 95 % down in about 45 s."""
RESISTANCE_M_S2 = 0.01
"""Running resistance of a freight train (rolling and air), as a deceleration."""
BASELINE_BAR = 0.05
"""Pressure at or below which the cylinder counts as released (truth event edges)."""
PRESSURE_QUANTUM_BAR = 0.007
"""The pressure sensor's resolution (fleet-data.md)."""

_TIME_FMT = "%Y-%m-%dT%H:%M:%SZ"


# --------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class SynthConfig:
    """What to generate. Rates are per row (fractions) or per file (probabilities)."""

    wagons: int = 4
    """Registered, well-formed wagons (the extra bad-registry wagons come on top)."""
    days: int = 2
    seed: int = 0
    start: dt.date = dt.date(2024, 3, 4)
    """First UTC day."""
    effects: EffectSet = field(default_factory=EffectSet)
    """Undeclared effects acting on every wagon."""
    anomalies: bool = True
    gzip_fraction: float = 0.5
    ambient_sensor_fraction: float = 0.5
    """Share of the wagons whose logs carry ``ambient_temp_c``."""
    ambient_mean_c: float = 8.0
    """Mean air temperature of the period."""
    sensor_noise_k: float = 0.1
    pressure_noise_bar: float = 0.003
    speed_noise_kmh: float = 0.3

    # imperfections of fleet-data.md
    missing_row_fraction: float = 0.001
    gap_probability: float = 0.15
    """Per file: one gap of 5-120 s."""
    duplicate_fraction: float = 0.0005
    swap_fraction: float = 0.0005
    empty_cell_fraction: float = 0.0002
    frozen_speed_probability: float = 0.1
    """Per file: GPS speed frozen for 20-120 s."""
    speed_jump_probability: float = 0.1
    """Per file: one or two GPS speed jumps of a few seconds."""
    truncated_files: int = 1
    """Plain CSV files cut mid-row (the unit lost power)."""
    truncated_gzip_files: int = 1
    """Gzip files cut mid-stream."""
    garbage_files: int = 1
    """Files that are not CSV at all (extra files, named as sessions)."""
    unregistered_wagon: bool = True
    """One more wagon with logs but no registry entry."""
    bad_registry_entry: bool = True
    """One more wagon with logs and a registry entry with a bad value."""
    odd_columns: bool = True
    """One wagon writes its columns in another order, with an extra unknown column."""

    refinement: float | None = None
    """Mesh refinement of the reduced model (None: ``$FLEETBRAKE_REFINEMENT`` or 1.0)."""

    def __post_init__(self) -> None:
        if isinstance(self.start, dt.datetime) or not isinstance(self.start, dt.date):
            raise ValueError(f"start must be a date, got {self.start!r}")
        if not isinstance(self.effects, EffectSet):
            object.__setattr__(self, "effects", EffectSet(tuple(self.effects)))
        for name in ("wagons", "days"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.wagons > 9000:
            raise ValueError("at most 9000 wagons")
        for name in (
            "gzip_fraction",
            "ambient_sensor_fraction",
            "missing_row_fraction",
            "gap_probability",
            "duplicate_fraction",
            "swap_fraction",
            "empty_cell_fraction",
            "frozen_speed_probability",
            "speed_jump_probability",
        ):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value!r}")
        for name in ("truncated_files", "truncated_gzip_files", "garbage_files"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")
        for name in ("sensor_noise_k", "pressure_noise_bar", "speed_noise_kmh"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0")

    @classmethod
    def clean(cls, **changes: Any) -> SynthConfig:
        """No imperfection and no anomaly (``changes`` on top)."""
        base = {
            "anomalies": False,
            "missing_row_fraction": 0.0,
            "gap_probability": 0.0,
            "duplicate_fraction": 0.0,
            "swap_fraction": 0.0,
            "empty_cell_fraction": 0.0,
            "frozen_speed_probability": 0.0,
            "speed_jump_probability": 0.0,
            "truncated_files": 0,
            "truncated_gzip_files": 0,
            "garbage_files": 0,
            "unregistered_wagon": False,
            "bad_registry_entry": False,
            "odd_columns": False,
        }
        return cls(**{**base, **changes})

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, EffectSet):
                value = value.to_list()
            elif isinstance(value, dt.date):
                value = value.isoformat()
            out[f.name] = value
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> SynthConfig:
        values = dict(data)
        if "effects" in values:
            values["effects"] = EffectSet.from_list(values["effects"])
        if "start" in values and isinstance(values["start"], str):
            values["start"] = dt.date.fromisoformat(values["start"])
        return cls(**values)


# --------------------------------------------------------------------------------------------
# Truth records


def _fmt(time_utc: dt.datetime | None) -> str | None:
    return None if time_utc is None else time_utc.strftime(_TIME_FMT)


def _parse(text: str | None) -> dt.datetime | None:
    return None if text is None else dt.datetime.strptime(text, _TIME_FMT)


def _jsonable(value: Any) -> Any:
    if isinstance(value, dt.datetime):
        return _fmt(value)
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, float):
        return round(value, 9)
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    return value


def _record_to_dict(record: Any) -> dict[str, Any]:
    return {f.name: _jsonable(getattr(record, f.name)) for f in dataclasses.fields(record)}


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
            "start_utc": _fmt(self.start_utc),
            "end_utc": _fmt(self.end_utc),
            "effects": self.effects.to_list(),
            "rom": _jsonable(self.rom),
            "wagons": [_record_to_dict(w) for w in self.wagons],
            "anomalies": [_record_to_dict(a) for a in self.anomalies],
            "events": [_record_to_dict(e) for e in self.events],
            "files": [_record_to_dict(f) for f in self.files],
            "registry_problems": _jsonable(self.registry_problems),
        }

    @classmethod
    def from_dict(cls, out_dir: Path, data: Mapping[str, Any]) -> FleetTruth:
        return cls(
            out_dir=Path(out_dir),
            config=SynthConfig.from_dict(data["config"]),
            start_utc=_parse(data["start_utc"]),  # type: ignore[arg-type]
            end_utc=_parse(data["end_utc"]),  # type: ignore[arg-type]
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


# --------------------------------------------------------------------------------------------
# Random streams: one per (wagon, purpose), so that switching one thing off leaves the rest


_PURPOSES = {
    "fleet": 0,
    "ambient": 1,
    "operation": 2,
    "readings": 3,
    "files": 4,
    "anomalies": 5,
    "bad_files": 6,
    "wagon": 7,
}


def _rng(seed: int, purpose: str, index: int = 0) -> np.random.Generator:
    return np.random.default_rng(
        np.random.SeedSequence(seed, spawn_key=(_PURPOSES[purpose], index))
    )


# --------------------------------------------------------------------------------------------
# Air temperature


def _air_temperature(
    rng: np.random.Generator, start_utc: dt.datetime, n_s: int, mean_c: float
) -> np.ndarray:
    """Daily sine (minimum near 04:00 UTC, maximum near 15:00) plus weather: a mean-reverting
    random walk on hourly knots, linear in between."""
    t = np.arange(n_s, dtype=np.float64)
    hour0 = start_utc.hour + start_utc.minute / 60.0
    hours = hour0 + t / 3600.0
    amplitude = rng.uniform(3.0, 6.0)
    daily = -amplitude * np.cos(2.0 * math.pi * (hours - 3.5) / 24.0)
    n_knots = math.ceil(n_s / 3600.0) + 2
    weather = np.zeros(n_knots)
    for k in range(1, n_knots):
        weather[k] = 0.97 * weather[k - 1] + rng.normal(0.0, 0.45)
    return mean_c + daily + np.interp(t / 3600.0, np.arange(n_knots), weather)


# --------------------------------------------------------------------------------------------
# Operation: speed, pressure, position, second by second


@dataclass
class _Command:
    kind: str
    command: int
    release: int = -1
    p_target_bar: float = 0.0


class _Driver:
    """Drives one wagon's train second by second: the plan's primitives append samples."""

    def __init__(
        self,
        rng: np.random.Generator,
        n_s: int,
        wagon: WagonConfig,
        mass_kg: float,
        position: tuple[float, float, float],
    ) -> None:
        self.rng = rng
        self.n_s = n_s
        # the declared block force is max(0, slope (p - p0)) (the chain of eqs. 2-4 above
        # both thresholds): read slope and p0 off physics.py
        f4, f5 = (float(block_force_n(wagon, p)) for p in (4.0, 5.0))
        slope = f5 - f4
        self._p0 = 4.0 - f4 / slope
        self._decel_per_bar = (
            2 * wagon.blocks_per_bogie * wagon.friction_coefficient * slope / mass_kg
        )
        self.v = 0.0
        self.p = 0.0
        self.target = 0.0
        self.lat, self.lon, self.elev = position
        self.heading = float(rng.uniform(0.0, 2.0 * math.pi))
        self.grade = 0.0
        self.speed: list[float] = []
        self.pressure: list[float] = []
        self.elevation: list[float] = []
        self.lats: list[float] = []
        self.lons: list[float] = []
        self.commands: list[_Command] = []
        self._rise = math.exp(-1.0 / RISE_TAU_S)
        self._release = math.exp(-1.0 / RELEASE_TAU_S)

    @property
    def t(self) -> int:
        return len(self.speed)

    def remaining(self) -> int:
        return self.n_s - self.t

    def decel(self, p_bar: float) -> float:
        """Deceleration of the train from this wagon's declared brake, m/s^2."""
        return max(p_bar - self._p0, 0.0) * self._decel_per_bar

    def _tick(
        self, a_drive: float, *, hold_speed: bool = False, grade: float | None = None
    ) -> None:
        keep = self._rise if self.target > self.p else self._release
        self.p = self.target + (self.p - self.target) * keep
        if hold_speed:
            brake = self.decel(self.p)
            self.grade = -brake / G_M_S2 if grade is None else grade
        else:
            self.v = max(self.v + a_drive - self.decel(self.p), 0.0)
            if grade is not None:
                self.grade = grade
        ds = self.v
        self.elev += self.grade * ds
        self.heading += float(self.rng.normal(0.0, 2e-4)) * ds
        self.lat += ds * math.cos(self.heading) / 111_320.0
        self.lon += ds * math.sin(self.heading) / (111_320.0 * math.cos(math.radians(self.lat)))
        self.speed.append(self.v)
        self.pressure.append(self.p)
        self.elevation.append(self.elev)
        self.lats.append(self.lat)
        self.lons.append(self.lon)

    def _run_grade(self) -> float:
        """A gentle line grade, pulled back towards 450 m above sea level."""
        return float(
            np.clip(2e-5 * (450.0 - self.elev) + self.rng.normal(0.0, 0.002), -0.006, 0.006)
        )

    # ---------------------------------------------------------------- primitives
    def stand(self, seconds: int) -> None:
        """Standing: the cylinder releases (if it was not yet), nothing moves."""
        n = int(seconds)
        self.target = 0.0
        self.v = 0.0
        self.grade = 0.0
        if n <= 0:
            return
        pressure = self.p * self._release ** np.arange(1, n + 1)
        self.p = float(pressure[-1])
        self.speed.extend([0.0] * n)
        self.pressure.extend(pressure.tolist())
        self.elevation.extend([self.elev] * n)
        self.lats.extend([self.lat] * n)
        self.lons.extend([self.lon] * n)

    def run(self, seconds: int, v_line_ms: float, a_acc: float) -> None:
        self.target = 0.0
        grade = self._run_grade()
        for i in range(int(seconds)):
            if i % 120 == 119:
                grade = self._run_grade()
            # traction up to the line speed (less at speed), coasting down to it
            if self.v < v_line_ms:
                a = min(a_acc * (1.0 - 0.5 * self.v / 30.0), v_line_ms - self.v)
            else:
                a = max(-0.04, v_line_ms - self.v)
            self._tick(a, grade=grade)

    def brake(self, kind: str, p_target: float, v_until_ms: float, hold_s: int = 0) -> None:
        command = _Command(kind, self.t, p_target_bar=p_target)
        self.commands.append(command)
        self.target = p_target
        for _ in range(900):
            if self.v <= v_until_ms:
                break
            self._tick(-RESISTANCE_M_S2)
        if v_until_ms <= 0.0:
            self.v = 0.0
            for _ in range(int(hold_s)):
                self._tick(0.0)
        command.release = self.t
        self.target = 0.0

    def drag(self, p_target: float, seconds: int) -> None:
        command = _Command("drag", self.t, p_target_bar=p_target)
        self.commands.append(command)
        self.target = p_target
        for _ in range(int(seconds)):
            self._tick(0.0, hold_speed=True)
        command.release = self.t
        self.target = 0.0
        while self.p > BASELINE_BAR:  # the descent goes on while the brake releases
            self._tick(0.0, hold_speed=True)

    # ---------------------------------------------------------------- plan
    def leg(self, budget_s: int) -> None:
        rng = self.rng
        a_acc = float(rng.uniform(0.1, 0.3))
        v_line = float(rng.uniform(60.0, 100.0)) / 3.6
        end = self.t + budget_s
        self.run(int(rng.integers(240, 600)), v_line, a_acc)
        while self.t < end:
            r = rng.random()
            v_kmh = self.v * 3.6
            if r < 0.35 and v_kmh > 35.0:
                p = float(rng.uniform(0.8, 1.4) if rng.random() < 0.6 else rng.uniform(1.4, 2.2))
                self.brake("slowdown", p, self.v * float(rng.uniform(0.5, 0.8)))
            elif r < 0.55 and v_kmh > 40.0:
                self.drag(float(rng.uniform(0.5, 0.85)), int(rng.integers(120, 600)))
            elif r < 0.9:
                v_line = float(rng.uniform(60.0, 100.0)) / 3.6
            else:
                self.brake(
                    "signal_stop", float(rng.uniform(1.0, 1.8)), 0.0, int(rng.integers(5, 30))
                )
                self.stand(int(rng.integers(60, 300)))  # released before it departs
            self.run(int(rng.integers(600, 1800)), v_line, a_acc)
        p_stop = float(rng.uniform(1.0, 2.5) if rng.random() < 0.85 else rng.uniform(2.5, 3.8))
        self.brake("stop", p_stop, 0.0, int(rng.integers(10, 60)))

    def operate(self) -> None:
        rng = self.rng
        self.stand(int(rng.integers(1800, 5 * 3600)))
        while True:
            n_legs = int(rng.integers(1, 4))
            for leg in range(n_legs):
                budget = int(rng.integers(25 * 60, 150 * 60))
                if self.remaining() < budget + 3600:
                    break
                if leg > 0:
                    self.stand(int(rng.integers(120, 1500)))  # station stop
                self.leg(budget)
            else:
                self.stand(int(rng.integers(3600, 6 * 3600)))  # yard
                if self.remaining() > 3 * 3600:
                    continue
            break
        self.stand(max(self.remaining(), 0))


@dataclass
class _Operation:
    speed_kmh: np.ndarray
    pressure_bar: np.ndarray
    elevation_m: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    distance_m: np.ndarray
    commands: list[_Command]


def _operate(
    rng: np.random.Generator,
    n_s: int,
    wagon: WagonConfig,
    mass_kg: float,
    position: tuple[float, float, float],
) -> _Operation:
    driver = _Driver(rng, n_s, wagon, mass_kg, position)
    driver.operate()
    n = n_s
    speed_ms = np.asarray(driver.speed[:n])
    distance = np.concatenate(([0.0], np.cumsum(speed_ms[:-1])))
    return _Operation(
        speed_kmh=speed_ms * 3.6,
        pressure_bar=np.asarray(driver.pressure[:n]),
        elevation_m=np.asarray(driver.elevation[:n]),
        lat_deg=np.asarray(driver.lats[:n]),
        lon_deg=np.asarray(driver.lons[:n]),
        distance_m=distance,
        commands=[c for c in driver.commands if c.release < n],
    )


def _sessions(speed_kmh: np.ndarray, sleep_after_s: int) -> list[tuple[int, int]]:
    """Recording sessions [first, stop): the unit wakes at the first sample of motion (one
    second before it) and sleeps after standing ``sleep_after_s``."""
    moving = speed_kmh > 0.5
    idx = np.flatnonzero(moving)
    if idx.size == 0:
        return []
    sessions: list[tuple[int, int]] = []
    # a new session where the standstill since the previous motion exceeded sleep_after_s
    breaks = np.flatnonzero(np.diff(idx) > sleep_after_s + 1)
    starts = np.concatenate(([idx[0]], idx[breaks + 1]))
    ends = np.concatenate((idx[breaks], [idx[-1]]))
    for a, b in zip(starts, ends, strict=True):
        first = max(int(a) - 1, 0)
        stop = min(int(b) + 1 + sleep_after_s, speed_kmh.size)
        sessions.append((first, stop))
    return sessions


def _true_events(op: _Operation) -> list[tuple[_Command, int, int]]:
    """Each command with its true edges (first sample above the baseline, first back at it)."""
    p = op.pressure_bar
    out = []
    n = p.size
    for c in op.commands:
        above = np.flatnonzero(p[c.command : c.release + 1] > BASELINE_BAR)
        if above.size == 0:
            continue
        start = c.command + int(above[0])
        back = np.flatnonzero(p[c.release :] <= BASELINE_BAR)
        if back.size == 0:
            continue
        end = c.release + int(back[0])
        if end >= n:
            continue
        out.append((c, start, end))
    return out


# --------------------------------------------------------------------------------------------
# The generator


def _registry_toml(
    defaults: Mapping[str, Any], entries: Sequence[tuple[str, str, Mapping[str, Any]]], seed: int
) -> str:
    def show(value: Any) -> str:
        if isinstance(value, str):
            return json.dumps(value)
        if isinstance(value, bool):
            return "true" if value else "false"
        return repr(value)

    lines = [
        f"# synthetic fleet written by `fleetbrake synth` (seed {seed})",
        "",
        "[defaults]",
    ]
    lines += [f"{key} = {show(value)}" for key, value in defaults.items()]
    for wagon_id, wagon_type, overrides in entries:
        lines += ["", "[[wagon]]", f"id = {show(wagon_id)}", f"type = {show(wagon_type)}"]
        lines += [f"{key} = {show(value)}" for key, value in overrides.items()]
    return "\n".join(lines) + "\n"


@dataclass
class _WagonPlan:
    index: int
    wagon_id: str
    registry: str  # ok / missing / bad
    overrides: dict[str, Any]
    wagon_type: str
    ambient_column: str
    mass_kg: float
    """Mass braked by the wagon's own brake: with the declared force chain it sets the
    train's deceleration (every wagon of the train brakes alike)."""
    sleep_after_s: int
    """The unit sleeps after the wagon has stood this long."""
    days: int


def _plan_wagons(config: SynthConfig) -> list[_WagonPlan]:
    rng = _rng(config.seed, "fleet")
    n_sensor = round(config.ambient_sensor_fraction * config.wagons)
    plans = []
    total = config.wagons + int(config.unregistered_wagon) + int(config.bad_registry_entry)
    without = 0
    for i in range(total):
        wagon_rng = _rng(config.seed, "wagon", i)
        registry = "ok"
        if i >= config.wagons:
            registry = "missing" if config.unregistered_wagon and i == config.wagons else "bad"
        overrides: dict[str, Any] = {}
        wagon_type = "Sggmrs"
        if i % 3 == 2:
            overrides["cylinder_diameter_m"] = 0.305
            wagon_type = "Rns"
        if registry == "bad":
            overrides["cylinder_diameter_m"] = -0.254  # the bad value (wrong sign)
        if i >= config.wagons:
            ambient_column = "values"
        elif i < n_sensor:
            ambient_column = "values"
        else:
            ambient_column = "absent" if without % 2 == 0 else "empty"
            without += 1
        plans.append(
            _WagonPlan(
                index=i,
                wagon_id=f"SGG-{i + 1:04d}",
                registry=registry,
                overrides=overrides,
                wagon_type=wagon_type,
                ambient_column=ambient_column,
                mass_kg=round(float(wagon_rng.uniform(55_000.0, 90_000.0)), -2),
                sleep_after_s=int(wagon_rng.integers(240, 600)),
                days=config.days if registry == "ok" else 1,
            )
        )
    del rng
    return plans


def generate_fleet(
    out_dir: str | Path,
    config: SynthConfig | None = None,
    *,
    rom: ReducedModel | Callable[[WagonConfig], ReducedModel] | None = None,
    progress: Callable[[str], None] | None = None,
) -> FleetTruth:
    """Write a synthetic fleet into ``out_dir`` (created; must be empty if it exists) and its
    truth into ``out_dir/truth``; return the truth.

    ``rom``: the reduced model to use (every wagon has the same block and sensor seat), or a
    function of the wagon giving it; default ``ReducedModel.for_wagon`` at
    ``config.refinement`` (cached on disk).
    """
    config = SynthConfig() if config is None else config
    out_dir = Path(out_dir)
    if out_dir.exists() and any(out_dir.iterdir()):
        raise FileExistsError(f"{out_dir}: not empty; give a new or empty directory")
    out_dir.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda _message: None)

    start_utc = dt.datetime.combine(config.start, dt.time())
    n_main = config.days * 86_400
    end_utc = start_utc + dt.timedelta(seconds=n_main)
    plans = _plan_wagons(config)

    # ---- registry
    air = _air_temperature(_rng(config.seed, "ambient"), start_utc, n_main, config.ambient_mean_c)
    defaults = dict(SPEC_DEFAULTS)
    defaults["ambient_temp_c"] = round(float(np.mean(air)), 1)
    entries = [
        (p.wagon_id, p.wagon_type, p.overrides) for p in plans if p.registry in ("ok", "bad")
    ]
    registry_path = out_dir / "fleet.toml"
    registry_path.write_text(_registry_toml(defaults, entries, config.seed), encoding="utf-8")
    registry = load_registry(registry_path)
    registry_problems = [
        {"file": "fleet.toml", "wagon_id": pr.wagon_id, "key": pr.key, "message": pr.message}
        for pr in registry.problems
    ]

    # ---- anomalies planned per wagon (physical ones; sensor faults go on files)
    ok = [p for p in plans if p.registry == "ok"]
    physical: dict[str, list[str]] = {p.wagon_id: [] for p in plans}
    fault_plan: dict[str, list[str]] = {p.wagon_id: [] for p in plans}
    if config.anomalies:
        # the first wagon stays clean; with 4 wagons: 2 drags, 3 is weak, faults on 2-4
        pool = ok[1:] if len(ok) > 1 else ok
        physical[pool[0].wagon_id].append("dragging_brake")
        physical[pool[1 % len(pool)].wagon_id].append("weak_brake")
        for number, subtype in enumerate(SENSOR_FAULT_SUBTYPES):
            # open -> third, frozen -> first, loose -> second, drift -> third of the pool
            fault_plan[pool[(number + 2) % len(pool)].wagon_id].append(subtype)

    roms: dict[tuple[Any, ...], ReducedModel] = {}

    def rom_for(wagon: WagonConfig) -> ReducedModel:
        if isinstance(rom, ReducedModel):
            return rom
        if rom is not None:
            return rom(wagon)
        key = (wagon.geometry, wagon.block, wagon.sensor_point_m)
        if key not in roms:
            roms[key] = ReducedModel.for_wagon(wagon, refinement=config.refinement)
        return roms[key]

    truth_dir = out_dir / TRUTH_DIR
    (truth_dir / SERIES_DIR).mkdir(parents=True, exist_ok=True)
    wagons: list[WagonTruth] = []
    anomalies: list[Anomaly] = []
    events: list[TrueEvent] = []
    files: list[FileTruth] = []
    session_frames: list[tuple[_WagonPlan, int, pl.DataFrame, dict[str, Any]]] = []
    rom_info: dict[str, Any] = {}

    for plan in plans:
        say(f"simulating {plan.wagon_id}")
        wagon = (
            registry.wagons[plan.wagon_id]
            if plan.registry == "ok"
            else WagonConfig(
                wagon_id=plan.wagon_id,
                type=plan.wagon_type,
                **{
                    **defaults,
                    **{k: v for k, v in plan.overrides.items() if plan.registry != "bad"},
                },
            )
        )
        n_s = plan.days * 86_400
        op_rng = _rng(config.seed, "operation", plan.index)
        position = (
            float(op_rng.uniform(46.0, 52.0)),
            float(op_rng.uniform(6.0, 15.0)),
            float(op_rng.uniform(150.0, 700.0)),
        )
        op = _operate(op_rng, n_s, wagon, plan.mass_kg, position)
        sessions = _sessions(op.speed_kmh, plan.sleep_after_s)
        awake = np.zeros(n_s, dtype=bool)
        for a, b in sessions:
            awake[a:b] = True

        # air: the wagon's own (a little off the region's), or the registry's
        wagon_air = air[:n_s] + float(_rng(config.seed, "ambient", plan.index + 1).normal(0.0, 0.7))
        if plan.ambient_column == "values":
            ambient_truth = wagon_air
            ambient_source = "log"
        else:
            ambient_truth = np.full(n_s, wagon.ambient_temp_c)
            ambient_source = "registry"

        # physical anomalies
        an_rng = _rng(config.seed, "anomalies", plan.index)
        drag_force = np.zeros(n_s)
        efficiency = np.ones(n_s)
        for kind in physical[plan.wagon_id]:
            if kind == "dragging_brake":
                running = np.flatnonzero((op.speed_kmh > 30.0) & (op.pressure_bar < 0.01) & awake)
                late = running[running >= n_s // 3]
                pick = late if late.size else running
                if pick.size == 0:
                    continue
                first = int(pick[int(an_rng.integers(0, pick.size))])
                stop = min(first + int(an_rng.integers(15 * 60, 40 * 60)), n_s)
                force_n = float(an_rng.uniform(150.0, 400.0))
                drag_force[first:stop] = force_n
                anomalies.append(
                    Anomaly(
                        plan.wagon_id,
                        "dragging_brake",
                        start_utc + dt.timedelta(seconds=first),
                        start_utc + dt.timedelta(seconds=stop),
                        parameters={"drag_force_n": force_n},
                    )
                )
            elif kind == "weak_brake":
                day = 1 if plan.days >= 2 else 0
                share = float(an_rng.uniform(0.4, 0.6))
                efficiency[day * 86_400 : (day + 1) * 86_400] = share
                anomalies.append(
                    Anomaly(
                        plan.wagon_id,
                        "weak_brake",
                        start_utc + dt.timedelta(days=day),
                        start_utc + dt.timedelta(days=day + 1),
                        parameters={"brake_efficiency": share},
                    )
                )

        # the block, continuously
        model = rom_for(wagon)
        rom_info = {"order": model.order, "cache_key": model.meta.get("cache_key")}
        offset = config.effects.get("ambient_offset")
        initial_c = float(ambient_truth[0]) + (
            offset.offset_k if isinstance(offset, AmbientOffset) else 0.0
        )
        result = simulate_timeline(
            model,
            wagon,
            dt_s=1.0,
            p_bar=op.pressure_bar,
            speed_kmh=op.speed_kmh,
            ambient_c=ambient_truth,
            initial_c=initial_c,
            effects=config.effects,
            drag_force_n=drag_force if drag_force.any() else None,
            brake_efficiency=efficiency if np.any(efficiency != 1.0) else 1.0,
            keep_state=False,
        )
        series_rel = f"{SERIES_DIR}/{plan.wagon_id}.parquet"
        times = pl.Series(
            "time_utc",
            (np.datetime64(start_utc, "s") + np.arange(n_s).astype("timedelta64[s]")).astype(
                "datetime64[us]"
            ),
        ).cast(pl.Datetime("us"))
        pl.DataFrame(
            {
                "time_utc": times,
                "awake": awake,
                # rounded far below any resolution that matters, so that it packs well
                "speed_kmh": np.round(op.speed_kmh, 4),
                "distance_m": np.round(op.distance_m, 3),
                "elevation_m": np.round(op.elevation_m, 3),
                "brake_pressure_bar": np.round(op.pressure_bar, 6),
                "block_force_n": np.round(result.block_force_n, 3),
                "heat_flux_w_m2": np.round(result.sample_flux_w_m2, 2),
                "ambient_c": np.round(ambient_truth, 4),
                "seat_c": np.round(result.seat_c, 4),
                "sensor_c": np.round(result.sensor_c, 4),
                "contact_mean_c": np.round(result.contact_mean_c, 4),
                "contact_max_c": np.round(result.contact_max_c, 4),
            }
        ).write_parquet(truth_dir / series_rel, compression="zstd", statistics=False)

        wagons.append(
            WagonTruth(
                wagon_id=plan.wagon_id,
                registry=plan.registry,
                registry_overrides=dict(plan.overrides),
                ambient_column=plan.ambient_column,
                ambient_source=ambient_source,
                registry_ambient_c=float(wagon.ambient_temp_c),
                mass_kg=plan.mass_kg,
                sleep_after_s=plan.sleep_after_s,
                days=plan.days,
                series=series_rel,
            )
        )

        # ---- readings and session frames
        rd = _rng(config.seed, "readings", plan.index)
        sensor_read = np.round(result.sensor_c + rd.normal(0.0, config.sensor_noise_k, n_s), 2)
        p_read = np.maximum(op.pressure_bar + rd.normal(0.0, config.pressure_noise_bar, n_s), 0.0)
        p_read = np.round(np.round(p_read / PRESSURE_QUANTUM_BAR) * PRESSURE_QUANTUM_BAR, 3)
        v_read = np.round(np.abs(op.speed_kmh + rd.normal(0.0, config.speed_noise_kmh, n_s)), 2)
        v_read = np.where(op.speed_kmh > 0.0, v_read, np.round(np.abs(rd.normal(0.0, 0.1, n_s)), 2))
        elev_read = np.round(op.elevation_m + rd.normal(0.0, 0.8, n_s), 1)
        lat_read = np.round(op.lat_deg + rd.normal(0.0, 2e-5, n_s), 6)
        lon_read = np.round(op.lon_deg + rd.normal(0.0, 2e-5, n_s), 6)
        air_read = np.round(wagon_air + rd.normal(0.0, 0.15, n_s), 1)
        extra_col = np.round(27.6 + rd.normal(0.0, 0.05, n_s), 2)

        odd = (
            config.odd_columns and plan.index == min(3, config.wagons - 1) and plan.registry == "ok"
        )
        for number, (a, b) in enumerate(sessions):
            columns: dict[str, Any] = {
                "time_utc": times[a:b],
                "speed_kmh": v_read[a:b],
                "distance_m": np.round(op.distance_m[a:b] - op.distance_m[a], 1),
                "elevation_m": elev_read[a:b],
                "lat_deg": lat_read[a:b],
                "lon_deg": lon_read[a:b],
                "brake_pressure_bar": p_read[a:b],
                "block_temp_c": sensor_read[a:b],
            }
            if plan.ambient_column == "values":
                columns["ambient_temp_c"] = air_read[a:b]
            elif plan.ambient_column == "empty":
                columns["ambient_temp_c"] = pl.Series([None] * (b - a), dtype=pl.Float64)
            frame = pl.DataFrame(columns)
            if odd:
                frame = frame.with_columns(pl.Series("battery_v", extra_col[a:b]))
                order = [
                    "time_utc",
                    "block_temp_c",
                    "brake_pressure_bar",
                    "speed_kmh",
                    "battery_v",
                    "distance_m",
                    "lat_deg",
                    "lon_deg",
                    "elevation_m",
                ]
                order += [c for c in frame.columns if c not in order]
                frame = frame.select(order)
            info = {
                "first": a,
                "stop": b,
                "odd_columns": odd,
                "ambient_c": None if plan.ambient_column == "values" else wagon.ambient_temp_c,
            }
            session_frames.append((plan, number, frame, info))

        # ---- true events
        for command, first, last in _true_events(op):
            window = op.pressure_bar[first : last + 1]
            p_mean = float(np.sum(window[1:] + window[:-1]) * 0.5 / max(last - first, 1))
            detail = {"stop": "station", "signal_stop": "signal"}.get(command.kind)
            events.append(
                TrueEvent(
                    wagon_id=plan.wagon_id,
                    kind="stop" if detail else command.kind,
                    detail=detail,
                    start_utc=start_utc + dt.timedelta(seconds=first),
                    end_utc=start_utc + dt.timedelta(seconds=last),
                    command_utc=start_utc + dt.timedelta(seconds=command.command),
                    release_command_utc=start_utc + dt.timedelta(seconds=command.release),
                    p_target_bar=round(command.p_target_bar, 4),
                    p_mean_bar=p_mean,
                    v_start_kmh=float(op.speed_kmh[first]),
                    v_end_kmh=float(op.speed_kmh[last]),
                    recorded=False,
                    file=None,
                )
            )

    # ---- files: choose the bad ones and the sensor faults, then write
    files, fault_anomalies = _write_files(
        out_dir, config, session_frames, fault_plan, start_utc, plans
    )
    anomalies += fault_anomalies
    events = _mark_recorded(events, files)
    anomalies.sort(key=lambda a: (a.wagon_id, a.start_utc, a.kind))

    truth = FleetTruth(
        out_dir=out_dir,
        config=config,
        start_utc=start_utc,
        end_utc=end_utc,
        wagons=wagons,
        effects=config.effects,
        anomalies=anomalies,
        events=events,
        files=files,
        registry_problems=registry_problems,
        rom=rom_info,
    )
    (truth_dir / TRUTH_JSON).write_text(
        json.dumps(truth.to_dict(), indent=1, sort_keys=True) + "\n", encoding="utf-8"
    )
    return load_truth(out_dir)  # exactly what is on disk (floats rounded as written)


def _mark_recorded(events: list[TrueEvent], files: list[FileTruth]) -> list[TrueEvent]:
    by_wagon: dict[str, list[FileTruth]] = {}
    for f in files:
        if f.bad != "garbage":
            by_wagon.setdefault(f.wagon_id, []).append(f)
    out = []
    for event in events:
        holder = next(
            (
                f
                for f in by_wagon.get(event.wagon_id, [])
                if f.start_utc <= event.start_utc and event.end_utc <= f.end_utc
            ),
            None,
        )
        recorded = holder is not None and holder.bad is None
        out.append(
            dataclasses.replace(
                event, recorded=recorded, file=holder.path if holder is not None else None
            )
        )
    return out


def _pt1000_drift(frame: pl.DataFrame, start: int, rate_k_per_h: float) -> pl.DataFrame:
    """A calibration drift: from row ``start`` on, an offset growing at ``rate_k_per_h``."""
    temp_c = frame["block_temp_c"].to_numpy().copy()
    elapsed_h = np.arange(frame.height - start, dtype=np.float64) / 3600.0
    temp_c[start:] = np.round(temp_c[start:] + rate_k_per_h * elapsed_h, 2)
    return frame.with_columns(pl.Series("block_temp_c", temp_c, dtype=pl.Float64))


def _write_files(
    out_dir: Path,
    config: SynthConfig,
    session_frames: list[tuple[_WagonPlan, int, pl.DataFrame, dict[str, Any]]],
    fault_plan: Mapping[str, list[str]],
    start_utc: dt.datetime,
    plans: list[_WagonPlan],
) -> tuple[list[FileTruth], list[Anomaly]]:
    rng = _rng(config.seed, "bad_files")
    long_enough = [
        i
        for i, (plan, _, frame, _) in enumerate(session_frames)
        if plan.registry == "ok" and frame.height >= 900
    ]
    # sensor faults: one file each, long sessions, never a file that is made bad
    fault_of: dict[int, str] = {}
    for wagon_id, subtypes in fault_plan.items():
        candidates = [i for i in long_enough if session_frames[i][0].wagon_id == wagon_id]
        if not candidates:
            continue
        chosen = rng.choice(candidates, size=min(len(subtypes), len(candidates)), replace=False)
        for index, subtype in zip(sorted(int(c) for c in chosen), subtypes, strict=False):
            fault_of[index] = subtype
    free = [i for i in long_enough if i not in fault_of]
    n_bad = min(config.truncated_files + config.truncated_gzip_files, len(free))
    bad_pick = [int(i) for i in rng.choice(free, size=n_bad, replace=False)] if n_bad else []
    bad_of = {i: "truncated_mid_row" for i in bad_pick[: config.truncated_files]}
    bad_of.update({i: "truncated_gzip" for i in bad_pick[config.truncated_files :]})

    files: list[FileTruth] = []
    faults: list[Anomaly] = []
    for i, (plan, number, frame, info) in enumerate(session_frames):
        frng = _rng(config.seed, "files", plan.index * 100_000 + number)
        session_rows = frame.height
        t_first = start_utc + dt.timedelta(seconds=info["first"])
        t_last = start_utc + dt.timedelta(seconds=info["stop"] - 1)
        imperfections: dict[str, Any] = {}
        if info["odd_columns"]:
            imperfections["odd_columns"] = list(frame.columns)
        # sensor fault (rows are seconds here)
        subtype = fault_of.get(i)
        if subtype is not None:
            frame, fault = _inject_fault(frame, frng, subtype, plan, t_first, info["ambient_c"])
        # GPS speed
        if frng.random() < config.frozen_speed_probability and frame.height > 200:
            seconds = int(frng.integers(20, 121))
            at = int(frng.integers(1, frame.height - seconds))
            frame = logfile.freeze_speed(frame, frng, seconds, start=at)
            imperfections["frozen_speed"] = {
                "start_utc": t_first + dt.timedelta(seconds=at),
                "seconds": seconds,
            }
        if frng.random() < config.speed_jump_probability and frame.height > 60:
            count = int(frng.integers(1, 3))
            frame = logfile.jump_speed(frame, frng, count)
            imperfections["speed_jumps"] = count
        # cells and rows
        if config.empty_cell_fraction > 0:
            before = frame.null_count().sum_horizontal().item()
            frame = logfile.blank_cells(frame, frng, config.empty_cell_fraction)
            imperfections["empty_cells"] = int(frame.null_count().sum_horizontal().item() - before)
        if frng.random() < config.gap_probability and frame.height > 400:
            seconds = int(frng.integers(5, 121))
            at = int(frng.integers(1, frame.height - seconds))
            frame = logfile.drop_gap(frame, frng, seconds, start=at)
            imperfections["gap"] = {
                "start_utc": t_first + dt.timedelta(seconds=at),
                "seconds": seconds,
            }
        if config.missing_row_fraction > 0:
            height = frame.height
            frame = logfile.drop_rows(frame, frng, config.missing_row_fraction)
            imperfections["missing_rows"] = height - frame.height
        if config.duplicate_fraction > 0:
            height = frame.height
            frame = logfile.duplicate_rows(frame, frng, config.duplicate_fraction)
            imperfections["duplicated_rows"] = frame.height - height
        if config.swap_fraction > 0:
            marker = pl.Series("__row", np.arange(frame.height))
            swapped = logfile.swap_neighbours(
                frame.with_columns(marker), frng, config.swap_fraction
            )
            rows = swapped["__row"].to_numpy()
            imperfections["swapped_pairs"] = int(np.sum(np.diff(rows) < 0))
            frame = swapped.drop("__row")
        imperfections = {k: v for k, v in imperfections.items() if v}

        bad = bad_of.get(i)
        gz = bool(frng.random() < config.gzip_fraction)
        if bad == "truncated_mid_row":
            gz = False
        elif bad == "truncated_gzip":
            gz = True
        rel = logfile.log_relpath(plan.wagon_id, t_first, gzip=gz)
        data = logfile.to_csv_bytes(frame)
        rows_written = logfile.complete_rows(data)
        reason = None
        if bad == "truncated_mid_row":
            data = logfile.truncate_mid_row(data, frng)
            rows_written = logfile.complete_rows(data)
            reason = f"cut inside data row {rows_written + 1} (the unit lost power)"
        elif bad == "truncated_gzip":
            packed = logfile.truncate_gzip(logfile.gzip_bytes(data), frng)
            readable = zlib.decompressobj(wbits=31).decompress(packed)
            rows_written = logfile.complete_rows(readable)
            reason = f"gzip stream cut after {len(packed)} bytes ({rows_written} complete rows)"
            data = packed
        if bad is not None:
            imperfections["last_complete_utc"] = _last_complete_time(
                data if bad != "truncated_gzip" else readable
            )
        logfile.write_log(out_dir / rel, data, gzip=gz and bad != "truncated_gzip")
        if subtype is not None:
            faults.append(dataclasses.replace(fault, file=rel.as_posix()))
        files.append(
            FileTruth(
                path=rel.as_posix(),
                wagon_id=plan.wagon_id,
                start_utc=t_first,
                end_utc=t_last,
                gzip=gz,
                session_rows=session_rows,
                rows_written=rows_written,
                imperfections=imperfections,
                bad=bad,
                reason=reason,
                registered=plan.registry == "ok",
            )
        )

    # garbage: extra files named as sessions of registered wagons, at times the unit slept
    ok_ids = [p.wagon_id for p in plans if p.registry == "ok"]
    taken = {f.path for f in files}
    kinds = ("binary", "text", "zeros")
    for g in range(config.garbage_files):
        wagon_id = ok_ids[int(rng.integers(0, len(ok_ids)))]
        own = sorted((f for f in files if f.wagon_id == wagon_id), key=lambda f: f.start_utc)
        slot = own[int(rng.integers(0, len(own)))].end_utc if own else start_utc
        when = slot + dt.timedelta(seconds=int(rng.integers(60, 300)))
        kind = kinds[g % len(kinds)]
        gz = bool(rng.random() < config.gzip_fraction)
        rel = logfile.log_relpath(wagon_id, when, gzip=gz)
        if rel.as_posix() in taken:
            continue
        data = logfile.garbage_bytes(rng, int(rng.integers(512, 8192)), kind=kind)
        logfile.write_log(out_dir / rel, data, gzip=False)
        taken.add(rel.as_posix())
        files.append(
            FileTruth(
                path=rel.as_posix(),
                wagon_id=wagon_id,
                start_utc=when,
                end_utc=when,
                gzip=gz,
                session_rows=0,
                rows_written=0,
                imperfections={"garbage_kind": kind},
                bad="garbage",
                reason=f"not CSV at all ({kind} bytes" + (", though named .csv.gz)" if gz else ")"),
                registered=True,
            )
        )
    files.sort(key=lambda f: (f.wagon_id, f.start_utc, f.path))
    return files, faults


def _last_complete_time(csv_bytes: bytes) -> dt.datetime | None:
    """Latest ``time_utc`` of the complete rows of plain CSV bytes (None if none)."""
    text = csv_bytes.decode("utf-8", errors="replace")
    lines = text.split("\n")
    header = lines[0].split(",")
    if "time_utc" not in header:
        return None
    col = header.index("time_utc")
    latest = None
    for line in lines[1:-1]:  # the last piece is partial (or empty)
        cells = line.split(",")
        if col < len(cells) and cells[col]:
            try:
                when = dt.datetime.strptime(cells[col], _TIME_FMT)
            except ValueError:
                continue
            latest = when if latest is None or when > latest else latest
    return latest


def _inject_fault(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    subtype: str,
    plan: _WagonPlan,
    t_first: dt.datetime,
    ambient_c: float | None,
) -> tuple[pl.DataFrame, Anomaly]:
    n = frame.height
    at = int(rng.integers(n // 5, n // 2))
    parameters: dict[str, float] = {}
    if subtype == "open":
        seconds = int(rng.integers(60, min(600, n - at)))
        frame = logfile.pt1000_open_circuit(frame, rng, seconds, start=at)
        parameters["reading_c"] = float(frame["block_temp_c"][at])
        stop = at + seconds
    elif subtype == "frozen":
        seconds = int(rng.integers(300, max(301, min(1800, n - at))))
        frame = logfile.pt1000_frozen(frame, rng, seconds, start=at)
        parameters["reading_c"] = float(frame["block_temp_c"][at])
        stop = at + seconds
    elif subtype == "loose":
        tau_s = float(rng.uniform(300.0, 900.0))
        # towards the air: the logged one, or the registry's where the wagon has no sensor
        frame = logfile.pt1000_drift_to_ambient(
            frame, rng, tau_s=tau_s, start=at, ambient_c=ambient_c
        )
        temp = np.round(frame["block_temp_c"].to_numpy(), 2)
        frame = frame.with_columns(pl.Series("block_temp_c", temp, dtype=pl.Float64))
        parameters["tau_s"] = tau_s
        stop = n
    elif subtype == "drift":
        rate = float(rng.uniform(3.0, 8.0)) * (1.0 if rng.random() < 0.5 else -1.0)
        frame = _pt1000_drift(frame, at, rate)
        parameters["rate_k_per_h"] = rate
        stop = n
    else:  # pragma: no cover - the subtypes are fixed
        raise ValueError(subtype)
    return frame, Anomaly(
        plan.wagon_id,
        "sensor_fault",
        t_first + dt.timedelta(seconds=at),
        t_first + dt.timedelta(seconds=stop),
        subtype=subtype,
        parameters=parameters,
    )


def summary(truth: FleetTruth) -> str:
    """A few lines on what was written."""
    good = [f for f in truth.files if f.bad is None]
    rows = sum(f.rows_written for f in truth.files)
    lines = [
        f"{truth.out_dir}: {len(truth.wagons)} wagons, {truth.start_utc:%Y-%m-%d} to "
        f"{truth.end_utc:%Y-%m-%d} (UTC, exclusive), {len(truth.files)} log files "
        f"({len(good)} good, {len(truth.files) - len(good)} bad), {rows:,} rows",
        f"braking events: {len(truth.events)} ({sum(e.recorded for e in truth.events)} recorded)",
        f"effects: {truth.effects}",
    ]
    for a in truth.anomalies:
        kind = a.kind + (f" ({a.subtype})" if a.subtype else "")
        lines.append(f"anomaly: {a.wagon_id} {kind} {_fmt(a.start_utc)} .. {_fmt(a.end_utc)}")
    for f in truth.bad_files():
        lines.append(f"bad file: {f.path}: {f.bad}")
    for p in truth.registry_problems:
        lines.append(f"registry: wagon {p['wagon_id']}, key {p['key']}: {p['message']}")
    missing = [w.wagon_id for w in truth.wagons if w.registry == "missing"]
    if missing:
        lines.append(f"logs without registry entry: {', '.join(missing)}")
    lines.append(f"truth: {truth.truth_dir}")
    return "\n".join(lines)
