"""What a recording holds: its one timeline and its entity paths (rerun's names for the things
logged), shared by the modules that log them and the blueprint that lays them out.

Every time is on one timeline, :data:`TIMELINE` (``time_utc``), a timestamp timeline of real
UTC time. Entities:

- ``wagon/speed_kmh``, ``wagon/brake_pressure_bar``: the samples (``Scalars``);
- ``wagon/temperature/measured_sensor_c``: the samples' valid sensor readings (a faulty
  reading is a broken wire, not a temperature: it is not drawn);
- ``wagon/temperature/predicted_sensor_c``, ``.../predicted_contact_mean_c``,
  ``.../predicted_contact_max_c``: the predictions of one model revision (sensor seat,
  friction face mean and maximum);
- ``wagon/temperature/estimated_contact_mean_c``, ``..._lo_c``, ``..._hi_c``: the virtual
  sensor's filtered estimate of the friction-face mean temperature (``v_contact_estimates``,
  the model and the reading together) and its 95 % band, against the open-loop prediction;
- ``wagon/unexplained_power/estimate_w``, ``.../lo_w``, ``.../hi_w``: the heat power on the
  friction face that the declared inputs do not explain, with its 95 % band (its own plot);
- ``wagon/residual_k``: measured - predicted sensor temperature, kelvin;
- ``state/events``, ``state/flags/<kind>``, ``state/faulty_readings``: ranges
  (``StateChange``): each event (state: its kind), each flag kind (state: the highest
  severity active), each run of faulty readings;
- ``log/events``, ``log/flags``, ``log/faulty_readings``, ``log/notes``: ``TextLog`` at
  each start and end with the attributes (flags: level ERROR, WARN, INFO by severity), and
  notes on the recording (what it lacks, how the block field was made);
- ``block/mesh`` (one event): the block's boundary, coloured by its temperature field
  every ~5 s (``Mesh3D``: geometry static, vertex colours on the timeline);
- ``block/sensor`` (one event): the sensor seat (``Points3D``).
"""

from __future__ import annotations

import numpy as np
import rerun as rr
from numpy.typing import NDArray

__all__ = [
    "BLOCK",
    "BLOCK_MESH",
    "BLOCK_SENSOR",
    "COLORMAP",
    "CONTACT_MAX",
    "CONTACT_MEAN",
    "ESTIMATE_HI",
    "ESTIMATE_LO",
    "ESTIMATE_MEAN",
    "LOG_EVENTS",
    "LOG_FAULTY_READINGS",
    "LOG_FLAGS",
    "LOG_NOTES",
    "MEASURED",
    "POWER",
    "POWER_HI",
    "POWER_LO",
    "PREDICTED",
    "PRESSURE",
    "RESIDUAL",
    "SPEED",
    "STATE_EVENTS",
    "STATE_FAULTY_READINGS",
    "STATE_FLAGS",
    "TIMELINE",
    "UNEXPLAINED_POWER",
    "Floats",
    "Times",
    "time_index",
]

TIMELINE = "time_utc"
"""The one timeline of every recording: real UTC time (a rerun timestamp timeline)."""

COLORMAP = "inferno"
"""Colours of the block's temperature field."""

SPEED = "wagon/speed_kmh"
PRESSURE = "wagon/brake_pressure_bar"
MEASURED = "wagon/temperature/measured_sensor_c"
PREDICTED = "wagon/temperature/predicted_sensor_c"
CONTACT_MEAN = "wagon/temperature/predicted_contact_mean_c"
CONTACT_MAX = "wagon/temperature/predicted_contact_max_c"
ESTIMATE_MEAN = "wagon/temperature/estimated_contact_mean_c"
ESTIMATE_LO = "wagon/temperature/estimated_contact_mean_lo_c"
ESTIMATE_HI = "wagon/temperature/estimated_contact_mean_hi_c"
UNEXPLAINED_POWER = "wagon/unexplained_power"
POWER = f"{UNEXPLAINED_POWER}/estimate_w"
POWER_LO = f"{UNEXPLAINED_POWER}/lo_w"
POWER_HI = f"{UNEXPLAINED_POWER}/hi_w"
RESIDUAL = "wagon/residual_k"
STATE_EVENTS = "state/events"
STATE_FLAGS = "state/flags"
STATE_FAULTY_READINGS = "state/faulty_readings"
LOG_EVENTS = "log/events"
LOG_FLAGS = "log/flags"
LOG_FAULTY_READINGS = "log/faulty_readings"
LOG_NOTES = "log/notes"
BLOCK = "block"
BLOCK_MESH = "block/mesh"
BLOCK_SENSOR = "block/sensor"

Times = NDArray[np.datetime64]
Floats = NDArray[np.float64]


def time_index(times: Times) -> list[rr.TimeColumn]:
    """The index of a column sent with ``send_columns``: ``times`` on :data:`TIMELINE`."""
    return [rr.TimeColumn(TIMELINE, timestamp=times)]
