"""The message format: what one MQTT message on a wagon's topic carries.

Topic: the subscribed filter (``fleet/+/samples`` by default) with the wagon id at one level
(``fleet/SGG-0001/samples``); the id must match ``[A-Za-z0-9_-]{1,64}`` (fleet-data.md).

Payload: UTF-8 JSON, either one sample (an object) or a batch of samples of that wagon (a
non-empty array of objects). A sample has the log format's columns as keys::

    {"time_utc": "2024-03-01T06:00:00Z", "speed_kmh": 61.2, "distance_m": 1503.1,
     "elevation_m": 402.5, "lat_deg": 46.01, "lon_deg": 8.01, "brake_pressure_bar": 0.0,
     "block_temp_c": 23.4, "ambient_temp_c": 9.5}

* ``time_utc``: required, a string ``YYYY-MM-DDTHH:MM:SSZ`` (UTC, whole seconds);
* ``speed_kmh``, ``distance_m``, ``elevation_m``, ``lat_deg``, ``lon_deg``,
  ``brake_pressure_bar``, ``block_temp_c``: required keys, each a JSON number or ``null``
  (an empty cell of the log file: no fix, no reading);
* ``ambient_temp_c``: optional, a number or ``null``;
* ``wagon_id``: optional; when present it must be the topic's wagon;
* any other key is ignored (as the log format ignores unknown columns).

Values are taken as they are: a reading out of its plausible range (a broken Pt1000 wire at
850 °C) is data, which the ingestion judges. A message that breaks these rules (not UTF-8,
not JSON, ``NaN``, a missing key, a value that is not a number, a time that is not one, a wagon
id that is not one) is rejected whole, with a :class:`PayloadError` naming the topic, the
sample and the reason.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import re
from dataclasses import dataclass
from typing import Any

from fleetbrake.errors import FleetbrakeError
from fleetbrake.fleet.logfile import FLOAT_COLUMNS, OPTIONAL_COLUMNS, WAGON_ID_PATTERN

__all__ = [
    "EPOCH_UTC",
    "Batch",
    "PayloadError",
    "Row",
    "parse_message",
    "utc_of",
    "wagon_of_topic",
]

EPOCH_UTC = dt.datetime(1970, 1, 1)
"""Samples are keyed by whole seconds since this (naive UTC)."""

_TIME_PATTERN = re.compile(r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}Z")
_REQUIRED_FLOATS = tuple(name for name in FLOAT_COLUMNS if name not in OPTIONAL_COLUMNS)

Row = tuple[float | None, ...]
"""One sample's values, in the order of :data:`fleetbrake.fleet.logfile.FLOAT_COLUMNS`."""


def utc_of(second: int) -> dt.datetime:
    """The time (naive UTC) of ``second`` seconds since :data:`EPOCH_UTC`."""
    return EPOCH_UTC + dt.timedelta(seconds=second)


class PayloadError(FleetbrakeError, ValueError):
    """A message that is not one of the format; the message names its topic and the reason."""


@dataclass(frozen=True)
class Batch:
    """The samples of one message, in the order they came."""

    wagon_id: str
    seconds: list[int]
    """Sample times, whole seconds since :data:`EPOCH_UTC`."""
    rows: list[Row]


def wagon_of_topic(topic: str, level: int) -> str:
    """The wagon id at topic level ``level``; :class:`PayloadError` if it is not one."""
    levels = topic.split("/")
    if level >= len(levels):
        raise PayloadError(f"{topic}: no topic level {level} to hold the wagon id")
    wagon_id = levels[level]
    if not WAGON_ID_PATTERN.fullmatch(wagon_id):
        raise PayloadError(
            f"{topic}: topic level {level} {wagon_id!r} is not a wagon id "
            f"({WAGON_ID_PATTERN.pattern})"
        )
    return wagon_id


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _seconds(value: object, where: str) -> int:
    if not isinstance(value, str) or not _TIME_PATTERN.fullmatch(value):
        raise PayloadError(f"{where}: time_utc {value!r} is not YYYY-MM-DDTHH:MM:SSZ")
    try:
        time_utc = dt.datetime.fromisoformat(value[:-1])
    except ValueError:
        raise PayloadError(f"{where}: time_utc {value!r} is not a valid time") from None
    return (time_utc - EPOCH_UTC) // dt.timedelta(seconds=1)


def _number(value: object, name: str, where: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise PayloadError(f"{where}: {name} is {value!r}, not a number or null")
    try:
        number = float(value)
    except OverflowError:
        raise PayloadError(f"{where}: {name} = {value} is too large for a number") from None
    if not math.isfinite(number):
        raise PayloadError(f"{where}: {name} = {value} is not a finite number")
    return number


def parse_message(
    topic: str, payload: bytes | bytearray, wagon_level: int, *, max_bytes: int
) -> Batch:
    """The samples of one message on ``topic``; :class:`PayloadError` naming the topic (and
    the sample) when the message is not one of the format (see the module's doc)."""
    wagon_id = wagon_of_topic(topic, wagon_level)
    if len(payload) > max_bytes:
        raise PayloadError(f"{topic}: payload of {len(payload)} bytes, more than {max_bytes}")
    try:
        document = json.loads(bytes(payload).decode("utf-8"), parse_constant=_reject_constant)
    except UnicodeDecodeError:
        raise PayloadError(f"{topic}: payload is not UTF-8 text") from None
    except (ValueError, RecursionError) as error:
        raise PayloadError(f"{topic}: payload is not JSON ({error})") from None
    if isinstance(document, dict):
        samples: list[Any] = [document]
    elif isinstance(document, list) and document:
        samples = document
    else:
        what = "an empty array" if document == [] else f"a JSON {type(document).__name__}"
        raise PayloadError(
            f"{topic}: payload is {what}, not a sample (an object) or a batch of samples "
            "(a non-empty array of objects)"
        )
    seconds: list[int] = []
    rows: list[Row] = []
    for i, sample in enumerate(samples):
        where = f"{topic}: sample {i}" if len(samples) > 1 else topic
        if not isinstance(sample, dict):
            raise PayloadError(f"{where}: a sample is an object, not {type(sample).__name__}")
        missing = [name for name in ("time_utc", *_REQUIRED_FLOATS) if name not in sample]
        if missing:
            raise PayloadError(f"{where}: missing required column {', '.join(missing)}")
        if "wagon_id" in sample and sample["wagon_id"] != wagon_id:
            raise PayloadError(
                f"{where}: wagon_id {sample['wagon_id']!r} is not the topic's wagon {wagon_id}"
            )
        second = _seconds(sample["time_utc"], where)
        where = f"{where} ({sample['time_utc']})"
        seconds.append(second)
        rows.append(tuple(_number(sample.get(name), name, where) for name in FLOAT_COLUMNS))
    return Batch(wagon_id, seconds, rows)
