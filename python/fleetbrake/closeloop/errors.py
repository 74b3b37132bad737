"""The close loop's errors."""

from __future__ import annotations

from fleetbrake.errors import ConfigError, FleetbrakeError

__all__ = ["CloseLoopConfigError", "CloseLoopError"]


class CloseLoopError(FleetbrakeError, RuntimeError):
    """The closed loop cannot run (no events before the holdout date, no registry, ...)."""


class CloseLoopConfigError(ConfigError):
    """A close-loop configuration that cannot be used (the message names the key)."""
