"""What ``fleetbrake demo`` generates and how, and the errors it raises."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from fleetbrake.errors import ConfigError, FleetbrakeError

__all__ = ["DEMO_EFFECT", "DemoConfig", "DemoConfigError", "DemoError", "DemoExistsError"]

DEMO_EFFECT = "convection_speed:gain=2.0,exponent=0.8"
"""The undeclared effect of the demo's fleet: forced convection growing with train speed,
``h(v) = h0 (1 + 2.0 (v / 100 km/h)^0.8)`` on every surface but the friction face."""


class DemoError(FleetbrakeError):
    """The demo cannot run (output directory unusable, a step failed); the message says why."""


class DemoExistsError(DemoError):
    """The output directory holds something already and ``force`` was not given."""


class DemoConfigError(DemoError, ConfigError):
    """A setting of :class:`DemoConfig` is not usable (exit 2); the message names it."""


@dataclass(frozen=True)
class DemoConfig:
    """What the demo generates and how.

    Read by: ``fleetbrake demo``.
    """

    wagons: int = 4
    """Registered, valid wagons (the generator adds one without a registry entry and one
    with a bad entry, whose files are quarantined)."""
    days: int = 2
    """UTC days of operation; the last is the closed loop's holdout (so at least 2)."""
    seed: int = 7
    """Seed of the generator: the same seed gives the same fleet."""
    effect: str = DEMO_EFFECT
    """The one undeclared effect, ``NAME[:key=value,...]`` as ``fleetbrake synth --effect``."""
    anomalies: bool = True
    """Inject anomalies (dragging brake, weak brake, sensor faults) for the flags to find."""
    start: dt.date = dt.date(2024, 3, 4)
    """The first UTC day of operation."""
    refinement: float = 1.0
    """Mesh refinement of the reduced model (1.0: the default mesh); every step (generation,
    run, closed loop) uses the model of this refinement."""
    recordings: bool = True
    """Write the rerun recordings of one wagon and one of its events."""

    def __post_init__(self) -> None:
        if self.wagons < 1:
            raise DemoConfigError(f"wagons must be >= 1, got {self.wagons}")
        if self.days < 2:
            raise DemoConfigError(
                f"days must be >= 2 (the last day is held out of the fit), got {self.days}"
            )
        if not self.refinement > 0:
            raise DemoConfigError(f"refinement must be > 0, got {self.refinement}")

    @property
    def holdout_from(self) -> dt.date:
        """The first day held out of the closed loop's fit: the last day."""
        return self.start + dt.timedelta(days=self.days - 1)
