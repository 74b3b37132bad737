"""One tree of expected failures, each carrying the exit code the command line gives it.

Every failure a user can cause or meet (a bad registry, a bad flag configuration, a database
held by another writer, an unknown revision or wagon, a bad command-line value) is a
subclass of :class:`FleetbrakeError` whose message names the file, row, wagon or key. The
command line maps the base class once (``fleetbrake.cli``): message on stderr, no traceback,
``exit_code`` as the process's exit status (contract: ``shared/spec/interface.md``):

* 1 (:data:`EXIT_FAILED`): the command could not do its job;
* 2 (:data:`EXIT_USAGE`): bad usage or configuration;
* 75 (:data:`EXIT_LOCKED`): the database is held by another writer (EX_TEMPFAIL).

Anything else that escapes is a bug, and shows its traceback.
"""

from __future__ import annotations

__all__ = [
    "EXIT_FAILED",
    "EXIT_LOCKED",
    "EXIT_USAGE",
    "ConfigError",
    "DatabaseLockedError",
    "FleetbrakeError",
    "UnknownKeyError",
]

EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_LOCKED = 75


class FleetbrakeError(Exception):
    """An expected failure; the message names what is wrong and where."""

    exit_code: int = EXIT_FAILED


class ConfigError(FleetbrakeError, ValueError):
    """A configuration file or command-line value is not usable (exit 2)."""

    exit_code = EXIT_USAGE


class UnknownKeyError(FleetbrakeError, KeyError):
    """A wagon, event, revision or other key asked for does not exist (exit 1)."""

    def __str__(self) -> str:  # KeyError quotes its message; this one reads as a sentence
        return str(self.args[0]) if self.args else ""


class DatabaseLockedError(FleetbrakeError):
    """Another process is writing the database (exit 75: try again later, or ``--wait``)."""

    exit_code = EXIT_LOCKED
