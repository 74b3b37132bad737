"""How the reproduction is run: the simulation settings, the wagon, the studied values.

The defaults are the reproduction's (``docs/paper-reproduction.md``): the registry's default
wagon, a hex20 mesh graded towards its sensor seat, Crank-Nicolson with dt = 1 s over 1200 s.
"""

from __future__ import annotations

from dataclasses import dataclass

from fleetbrake.errors import ConfigError
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.thermal import Element

__all__ = [
    "CALIBRATION_RANGE_M",
    "DEFAULT_SETTINGS",
    "MANOEUVRE_NAMES",
    "STUDY_BORES_M",
    "STUDY_CONVECTION_W_M2K",
    "STUDY_DEPTHS_M",
    "RunSettings",
    "paper_wagon",
]

MANOEUVRE_NAMES = ("A", "B")
"""The paper's manoeuvres, in its order."""

STUDY_DEPTHS_M = (0.045, 0.050, 0.055, 0.060, 0.065, 0.070)
STUDY_CONVECTION_W_M2K = (5.0, 10.0, 20.0, 50.0)
STUDY_BORES_M = (0.203, 0.254, 0.305, 0.356)
"""8, 10, 12 and 14 inch brake cylinders (the registry default is 10 inch, 0.254 m)."""

CALIBRATION_RANGE_M = (0.030, 0.070)
"""Depths the calibration may choose from: the lower half of the body to the lug's back."""


@dataclass(frozen=True)
class RunSettings:
    """How the manoeuvres are simulated. The defaults are the reproduction's.

    Read by: ``fleetbrake paper``.
    """

    element: Element = "hex20"
    """Finite element of the mesh: ``hex20`` (quadratic) or ``hex8`` (linear)."""
    refinement: float = 1.0
    """Mesh refinement (1.0: the default mesh, graded towards the sensor seat)."""
    dt_s: float = 1.0
    """Time step of the Crank-Nicolson integration."""
    horizon_s: float = 1200.0
    """Simulated time of each manoeuvre, from the brake's activation."""
    probe_spacing_m: float = 0.0005
    """Spacing of the probed depths along the sensor's radial line, from the friction face to
    the deepest seat inside the block (the temperatures by depth and the calibration)."""
    field_every: int = 10
    """Whole fields kept every k steps (fields between are recomputed from the nearest one)."""
    workers: int = 2
    """Simulations run side by side in threads (the core releases the GIL)."""

    def __post_init__(self) -> None:
        if not self.dt_s > 0 or not self.horizon_s >= self.dt_s:
            raise ConfigError("RunSettings: dt_s must be > 0 and horizon_s >= dt_s")
        if not self.probe_spacing_m > 0 or self.field_every < 1 or self.workers < 1:
            raise ConfigError("RunSettings: probe_spacing_m > 0, field_every >= 1, workers >= 1")

    @property
    def n_steps(self) -> int:
        return round(self.horizon_s / self.dt_s)


DEFAULT_SETTINGS = RunSettings()
"""The reproduction's settings (every default)."""


def paper_wagon() -> WagonConfig:
    """The wagon of the reproduction: every value the registry's default (fleet-data.md)."""
    return WagonConfig(wagon_id="paper-default")
