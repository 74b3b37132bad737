"""Logging of the command line: standard :mod:`logging` to stderr, as text or one JSON object
per line (``--log-format``), at the level ``--quiet`` / ``--verbose`` ask for.

The library only logs (``logging.getLogger(__name__)``); the command line is the one place
that decides where the records go. :func:`configure_logging` installs one handler on the root
logger for the duration of a command and returns the function that puts everything back, so
that a command invoked in-process (tests, ``typer.testing.CliRunner``) leaves the process's
logging as it found it. Python warnings (e.g. numpy's) become records of the ``py.warnings``
logger, so that they too come out in the chosen format.
"""

from __future__ import annotations

import datetime as dt
import enum
import json
import logging
import sys
import warnings
from collections.abc import Callable
from typing import TextIO

__all__ = ["LogFormat", "configure_logging", "level_for"]


class LogFormat(enum.StrEnum):
    """How log records are written to stderr."""

    TEXT = "text"
    """``2024-03-05T12:00:00Z WARNING fleetbrake.ingest.files: message``."""
    JSON = "json"
    """One object per line: ``time`` (UTC, ISO 8601), ``level``, ``logger``, ``message``
    (and ``exception`` when the record carries one, and any ``extra`` the caller gave)."""


DEFAULT_LEVEL = logging.WARNING
"""Without ``--quiet`` or ``--verbose``: warnings and errors."""

_RECORD_FIELDS = frozenset(vars(logging.makeLogRecord({}))) | {"message", "asctime"}
"""Attributes every record has: what is left on a record beyond them came as ``extra``."""


def level_for(*, quiet: bool, verbose: int) -> int:
    """The level of the ``fleetbrake`` loggers: ``--quiet`` errors only, each ``--verbose``
    one step more (``-v`` info, ``-vv`` debug)."""
    if quiet:
        return logging.ERROR
    return max(logging.DEBUG, DEFAULT_LEVEL - 10 * verbose)


def _utc(record: logging.LogRecord) -> str:
    when = dt.datetime.fromtimestamp(record.created, dt.UTC)
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"


class TextFormatter(logging.Formatter):
    """``time level logger: message`` (time in UTC), with the traceback if any."""

    def format(self, record: logging.LogRecord) -> str:
        line = f"{_utc(record)} {record.levelname} {record.name}: {record.getMessage()}"
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, object] = {
            "time": _utc(record),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key, value in vars(record).items():
            if key not in _RECORD_FIELDS and not key.startswith("_"):
                entry[key] = value
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


class _StderrHandler(logging.StreamHandler):
    """A stream handler writing to whatever ``sys.stderr`` is at the time of the record (a
    test runner swaps it), never to a stream closed since."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, _value: TextIO) -> None:
        pass


def configure_logging(fmt: LogFormat, level: int) -> Callable[[], None]:
    """Send the records of the ``fleetbrake`` loggers at ``level`` and above, and those of
    other libraries at warning and above (error with ``--quiet``), to stderr in ``fmt``;
    return the function that restores the logging configuration found."""
    root = logging.getLogger()
    ours = logging.getLogger("fleetbrake")
    before = (root.level, ours.level, warnings.showwarning)
    handler = _StderrHandler()
    handler.setFormatter(JsonFormatter() if fmt is LogFormat.JSON else TextFormatter())
    root.addHandler(handler)
    root.setLevel(max(level, DEFAULT_LEVEL))
    ours.setLevel(level)
    logging.captureWarnings(True)

    def restore() -> None:
        logging.captureWarnings(False)
        warnings.showwarning = before[2]
        root.removeHandler(handler)
        root.setLevel(before[0])
        ours.setLevel(before[1])

    return restore
