"""The effects on the sensor's output: ``sensor_lag`` (the thermistor lags its seat, in one
stage or two)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from fleetbrake.model.effects.base import Effect, FloatArray
from fleetbrake.model.rom import first_order_lag

__all__ = ["SensorLag", "SensorLagTwoStage"]


@dataclass(frozen=True)
class SensorLag(Effect):
    """The thermistor lags the block temperature at its seat (contact resistance of the
    seat): a first-order lag ``tau y' = x - y`` with time constant ``tau_s`` on the sensor
    output (the response of a lumped sensor, e.g. Doebelin, *Measurement Systems*, ch. 3).
    Free parameter: ``tau_s``."""

    name: ClassVar[str] = "sensor_lag"
    law: ClassVar[str] = "first_order"
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {"tau_s": (15.0, 120.0)}
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {"tau_s": (0.0, 3600.0)}

    tau_s: float = 40.0

    def apply_to_sensor(self, sensor_c: FloatArray, dt_s: float) -> FloatArray:
        return first_order_lag(np.asarray(sensor_c, dtype=np.float64), dt_s, self.tau_s)


@dataclass(frozen=True)
class SensorLagTwoStage(Effect):
    """Two lags in series: the seat's contact resistance (``tau_contact_s``) brings the heat
    to the thermistor's body, whose own capacity lags it again (``tau_body_s``), the
    two-time-constant model of a sheathed sensor in a seat (Doebelin, *Measurement Systems*,
    ch. 3: second-order, overdamped). Free parameters: ``tau_contact_s``, ``tau_body_s``.

    Simulated by :func:`~fleetbrake.model.timeline.simulate_timeline` and the synthetic
    generator; the chain simulation (``fleetbrake.simulation``) carries one lag state, so
    this law is not a close-loop candidate, and asking the chain for its single ``tau_s``
    is an error rather than a silently dropped lag."""

    name: ClassVar[str] = "sensor_lag"
    law: ClassVar[str] = "two_stage"
    candidate: ClassVar[bool] = False
    PARAMETER_RANGES: ClassVar[Mapping[str, tuple[float, float]]] = {
        "tau_contact_s": (15.0, 90.0),
        "tau_body_s": (5.0, 40.0),
    }
    LIMITS: ClassVar[Mapping[str, tuple[float | None, float | None]]] = {
        "tau_contact_s": (0.0, 3600.0),
        "tau_body_s": (0.0, 3600.0),
    }

    tau_contact_s: float = 40.0
    tau_body_s: float = 10.0

    @property
    def tau_s(self) -> float:
        raise ValueError(
            "sensor_lag (two_stage) has two time constants; the chain simulation carries "
            "one lag state and cannot simulate it"
        )

    def apply_to_sensor(self, sensor_c: FloatArray, dt_s: float) -> FloatArray:
        x = np.asarray(sensor_c, dtype=np.float64)
        return first_order_lag(first_order_lag(x, dt_s, self.tau_contact_s), dt_s, self.tau_body_s)
