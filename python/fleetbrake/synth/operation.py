"""How a wagon runs, second by second: the air around it, its train's driving (speed,
cylinder pressure, position), the recording sessions of its unit, and the true brakings.

The wagon stands at a yard, runs trips of one to three legs between stations, and stands
again. A leg accelerates at 0.1-0.3 m/s^2 to a line speed of 60-100 km/h and cruises; on the
way come slowdowns (a service braking to 50-80 % of the speed), drag brakings downhill
(0.5-0.85 bar for 2-10 minutes at constant speed, the grade balancing the brake), line-speed
changes and signal stops; a leg ends with a stop braking (0.8-2.5 bar, sometimes up to 3.8
bar), the brake held 10-60 s at standstill, then released. The cylinder fills as a UIC G-mode
brake does (95 % of the target in about 20 s) and releases in about 45 s. The train's
deceleration follows from the wagon's own declared force chain and mass (every wagon of the
train brakes alike).

The unit wakes when the wagon moves and sleeps after standing ``sleep_after_s``: one session
(one file) per waking.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass

import numpy as np

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.physics import block_force_n

__all__ = [
    "BASELINE_BAR",
    "Command",
    "Operation",
    "air_temperature",
    "operate",
    "sessions",
    "true_events",
]

G_M_S2 = 9.81
RISE_TAU_S = 20.0 / 3.0
"""G-mode cylinder filling: 95 % of the target pressure in about 20 s."""
RELEASE_TAU_S = 45.0 / 3.0
"""Release: 95 % down in about 45 s."""
RESISTANCE_M_S2 = 0.01
"""Running resistance of a freight train (rolling and air), as a deceleration."""
BASELINE_BAR = 0.05
"""Pressure at or below which the cylinder counts as released (truth event edges)."""

# --------------------------------------------------------------------------------------------
# Air temperature


def air_temperature(
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
class Command:
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
        self.commands: list[Command] = []
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
        command = Command(kind, self.t, p_target_bar=p_target)
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
        command = Command("drag", self.t, p_target_bar=p_target)
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
class Operation:
    speed_kmh: np.ndarray
    pressure_bar: np.ndarray
    elevation_m: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    distance_m: np.ndarray
    commands: list[Command]


def operate(
    rng: np.random.Generator,
    n_s: int,
    wagon: WagonConfig,
    mass_kg: float,
    position: tuple[float, float, float],
) -> Operation:
    driver = _Driver(rng, n_s, wagon, mass_kg, position)
    driver.operate()
    n = n_s
    speed_ms = np.asarray(driver.speed[:n])
    distance = np.concatenate(([0.0], np.cumsum(speed_ms[:-1])))
    return Operation(
        speed_kmh=speed_ms * 3.6,
        pressure_bar=np.asarray(driver.pressure[:n]),
        elevation_m=np.asarray(driver.elevation[:n]),
        lat_deg=np.asarray(driver.lats[:n]),
        lon_deg=np.asarray(driver.lons[:n]),
        distance_m=distance,
        commands=[c for c in driver.commands if c.release < n],
    )


def sessions(speed_kmh: np.ndarray, sleep_after_s: int) -> list[tuple[int, int]]:
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


def true_events(op: Operation) -> list[tuple[Command, int, int]]:
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
