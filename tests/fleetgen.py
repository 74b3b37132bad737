"""Test helpers: synthetic sessions with known braking, small fleets, table snapshots.

Not the project's fleet generator (that one is written elsewhere on top of
``fleetbrake.fleet.logfile``); just what the ingestion and event tests need, with the truth kept.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path

import duckdb
import numpy as np
import polars as pl

from fleetbrake.fleet.logfile import COLUMNS, log_relpath, write_log

T0_UTC = dt.datetime(2024, 3, 1, 6, 0, 0)

RISE_TAU_S = 20.0 / 3.0
"""Brake cylinder filling: 95 % of the target pressure in about 20 s."""
RELEASE_TAU_S = 45.0 / 3.0
"""Release: 95 % down in about 45 s."""
DECEL_PER_BAR = 0.12
"""Train deceleration per bar of cylinder pressure, m/s^2."""


@dataclass(frozen=True)
class TrueEvent:
    """A braking the generator made: when the pressure started rising, and what it was."""

    onset_utc: dt.datetime
    kind: str
    """stop, slowdown or drag."""
    p_target_bar: float
    release_utc: dt.datetime


@dataclass
class Session:
    """A generated session: the frame as a unit would write it, and the truth."""

    frame: pl.DataFrame
    events: list[TrueEvent]
    quiet: list[tuple[int, int]]
    """Row ranges [a, b) with no pressure above 0.01 bar (cruising), where gaps may go."""


def make_session(
    rng: np.random.Generator,
    start_utc: dt.datetime = T0_UTC,
    *,
    n_events: int = 12,
    kinds: tuple[str, ...] = ("slowdown", "stop", "drag"),
    p_range_bar: tuple[float, float] = (0.4, 3.8),
    ambient_c: float = 8.0,
    noise: bool = True,
) -> Session:
    """A session of ``n_events`` brakings (kinds drawn from ``kinds``) between cruising stretches.

    Pressure rises in about 20 s, either as a first-order lag or as a linear ramp (then the
    first 0.05 bar take up to 2.5 s), releases in about 45 s, is quantised to 7 mbar with a
    little noise; speed follows from the pressure; the block heats while braking and cools
    towards ambient.
    """
    target_bar: list[float] = []
    rise_tau_s: list[float] = []
    phase: list[str] = []
    events: list[tuple[int, str, float, int]] = []
    quiet: list[tuple[int, int]] = []

    def add(seconds: int, p_bar: float, name: str) -> None:
        if p_bar > 0 and rng.random() < 0.5:  # a linear ramp over 20 s
            target_bar.extend(p_bar * min(1.0, (k + 1) / 20.0) for k in range(seconds))
            rise_tau_s.extend([1.0] * seconds)
        else:
            target_bar.extend([p_bar] * seconds)
            rise_tau_s.extend([RISE_TAU_S] * seconds)
        phase.extend([name] * seconds)

    def cruise(seconds: int) -> None:
        quiet.append((len(target_bar) + 90, len(target_bar) + seconds - 10))
        add(seconds, 0.0, "cruise")

    cruise(int(rng.integers(150, 300)))
    for _ in range(n_events):
        kind = str(rng.choice(kinds))
        onset = len(target_bar)
        if kind == "drag":
            p = float(rng.uniform(0.45, 0.9))
            add(int(rng.integers(180, 420)), p, "drag")
        elif kind == "stop":
            p = float(rng.uniform(max(p_range_bar[0], 1.0), p_range_bar[1]))
            add(int(rng.integers(120, 200)), p, "stop")
        else:
            p = float(rng.uniform(*p_range_bar))
            add(int(rng.integers(15, 45)), p, "slowdown")
        events.append((onset, kind, p, len(target_bar)))
        if kind == "stop":
            add(int(rng.integers(60, 120)), 0.0, "stand")
        cruise(int(rng.integers(150, 300)))

    n = len(target_bar)
    target = np.asarray(target_bar)
    pressure = np.zeros(n)
    for i in range(1, n):
        tau = rise_tau_s[i] if target[i] > pressure[i - 1] else RELEASE_TAU_S
        pressure[i] = target[i] + (pressure[i - 1] - target[i]) * np.exp(-1.0 / tau)

    speed_ms = np.zeros(n)
    cruise_ms = float(rng.uniform(70, 95)) / 3.6
    v = v_floor = cruise_ms
    for i in range(n):
        if phase[i] == "stop":
            if i == 0 or phase[i - 1] != "stop":
                run = phase[i:].index("stand") if "stand" in phase[i:] else 100
                step = v / max(run - 20, 1)
            v = max(v - step, 0.0)
        elif phase[i] == "stand":
            v = 0.0
        elif phase[i] == "slowdown" or (phase[i] == "cruise" and pressure[i] > 0.05 and v > 0):
            if i == 0 or phase[i - 1] not in ("slowdown", "cruise") or v_floor is None:
                v_floor = 0.4 * v
            v = max(v - DECEL_PER_BAR * pressure[i], v_floor)
        elif phase[i] == "cruise":
            v_floor = None
            v = min(v + 0.25, cruise_ms)
        speed_ms[i] = v  # drag: speed held (a descent)
    speed_kmh = speed_ms * 3.6

    block_c = ambient_c + 15 + _cooling(pressure * speed_ms, ambient_c)
    noise_bar = rng.normal(0, 0.004, n) if noise else np.zeros(n)
    pressure_out = np.round(np.maximum(pressure + noise_bar, 0.0) / 0.007) * 0.007
    speed_out = np.maximum(speed_kmh + (rng.normal(0, 0.3, n) if noise else 0.0), 0.0)
    times = [start_utc + dt.timedelta(seconds=i) for i in range(n)]
    frame = pl.DataFrame(
        {
            "time_utc": pl.Series(times, dtype=pl.Datetime("us")),
            "speed_kmh": np.round(speed_out, 2),
            "distance_m": np.round(np.cumsum(speed_ms), 1),
            "elevation_m": np.round(420 + 30 * np.sin(np.arange(n) / 700), 1),
            "lat_deg": np.round(46.2 + np.cumsum(speed_ms) * 6e-6, 6),
            "lon_deg": np.round(7.9 + np.cumsum(speed_ms) * 4e-6, 6),
            "brake_pressure_bar": np.round(pressure_out, 3),
            "block_temp_c": np.round(block_c + (rng.normal(0, 0.1, n) if noise else 0.0), 1),
            "ambient_temp_c": np.full(n, ambient_c),
        }
    )
    truth = [
        TrueEvent(times[onset], kind, p, times[min(release, n - 1)])
        for onset, kind, p, release in events
    ]
    return Session(frame, truth, quiet)


def _cooling(power: np.ndarray, ambient_c: float) -> np.ndarray:
    """A block temperature rise: heated by ``power``, cooling with a 900 s time constant."""
    rise = np.zeros(len(power))
    for i in range(1, len(power)):
        rise[i] = rise[i - 1] * np.exp(-1.0 / 900.0) + power[i] * 0.0015
    return rise


def simple_session(
    start_utc: dt.datetime = T0_UTC, rows: int = 600, *, seed: int = 0
) -> pl.DataFrame:
    """A plain session of ``rows`` seconds: every cell valid, one braking in the middle."""
    rng = np.random.default_rng(seed)
    i = np.arange(rows)
    braking = (i > rows // 3) & (i < rows // 3 + 40)
    return pl.DataFrame(
        {
            "time_utc": pl.Series(
                [start_utc + dt.timedelta(seconds=int(k)) for k in i], dtype=pl.Datetime("us")
            ),
            "speed_kmh": np.round(60 + 10 * np.sin(i / 50) + rng.normal(0, 0.2, rows), 2),
            "distance_m": np.round(np.cumsum(np.full(rows, 16.7)), 1),
            "elevation_m": np.round(400 + rng.normal(0, 0.5, rows), 1),
            "lat_deg": np.round(46.0 + i * 1e-5, 6),
            "lon_deg": np.round(8.0 + i * 1e-5, 6),
            "brake_pressure_bar": np.where(braking, 1.505, 0.0),
            "block_temp_c": np.round(20 + 0.05 * i + rng.normal(0, 0.1, rows), 1),
            "ambient_temp_c": np.round(10 + rng.normal(0, 0.1, rows), 1),
        }
    ).select(COLUMNS)


def registry_text(wagon_ids: list[str], extra: str = "") -> str:
    """A ``fleet.toml`` declaring ``wagon_ids`` (defaults of the spec), plus ``extra`` TOML."""
    entries = "".join(f'[[wagon]]\nid = "{w}"\ntype = "Sggmrs"\n\n' for w in wagon_ids)
    return "[defaults]\nambient_temp_c = 10.0\n\n" + entries + extra


def write_registry(fleet_dir: Path, wagon_ids: list[str], extra: str = "") -> None:
    """Write ``fleet_dir/fleet.toml``."""
    fleet_dir.mkdir(parents=True, exist_ok=True)
    (fleet_dir / "fleet.toml").write_text(registry_text(wagon_ids, extra), encoding="utf-8")


def write_session(
    fleet_dir: Path,
    wagon_id: str,
    frame: pl.DataFrame | bytes,
    start_utc: dt.datetime,
    *,
    gzip: bool = True,
    compress: bool | None = None,
) -> Path:
    """Write a session at its conventional path (``.csv.gz`` if ``gzip``); ``compress`` as
    :func:`~fleetbrake.fleet.logfile.write_log`'s ``gzip`` (None: by the name). Returns the path."""
    return write_log(fleet_dir / log_relpath(wagon_id, start_utc, gzip=gzip), frame, gzip=compress)


def relpath_of(wagon_id: str, start_utc: dt.datetime, *, gzip: bool = True) -> str:
    """Conventional relative path of a session's file, as ``files.path`` holds it."""
    return log_relpath(wagon_id, start_utc, gzip=gzip).as_posix()


def snapshot(db_path: Path, *, ignore: tuple[str, ...] = ()) -> dict[str, list[tuple]]:
    """Full contents of every table of the warehouse, sorted, minus the ``ignore`` columns."""
    con = duckdb.connect(str(db_path), read_only=True)
    try:
        tables = [
            r[0]
            for r in con.execute(
                "SELECT table_name FROM information_schema.tables "
                "WHERE table_type = 'BASE TABLE' ORDER BY table_name"
            ).fetchall()
        ]
        out: dict[str, list[tuple]] = {}
        for table in tables:
            columns = [
                r[0]
                for r in con.execute(
                    "SELECT column_name FROM information_schema.columns WHERE table_name = $t "
                    "ORDER BY ordinal_position",
                    {"t": table},
                ).fetchall()
                if r[0] not in ignore
            ]
            quoted = ", ".join(f'"{c}"' for c in columns)
            rows = con.execute(f'SELECT {quoted} FROM "{table}"').fetchall()
            out[table] = sorted(rows, key=repr)
        return out
    finally:
        con.close()
