"""Why a file is quarantined, and which of those reasons are judged again at every run.

A quarantined file is recorded in the ledger (``files.status = 'quarantined'``, ``rows = 0``)
with a :class:`Quarantine`'s ``code`` (the kind of problem: ``name``, ``size``, ``registry``,
``unreadable``, ``empty``, ``gzip``, ``binary``, ``header``, ``error``, and ``rows`` for a file
whose data rows were read and every one rejected) and its ``reason`` (a sentence naming the
file; for ``rows``, each rejected line and why). The codes of :data:`RETRIED_CODES` depend on something outside the
file's bytes, so such a file is read and judged again at every run.
"""

from __future__ import annotations

from fleetbrake.fleet.registry import Registry, RegistryError

__all__ = ["RETRIED_CODES", "Quarantine", "path_wagon", "registry_problem"]


class Quarantine(Exception):
    """A file that cannot be ingested: ``code`` says what kind of problem, the message which."""

    def __init__(self, code: str, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason

    def __reduce__(self) -> tuple[object, ...]:  # crosses from a worker process intact
        return (Quarantine, (self.code, self.reason))


RETRIED_CODES = frozenset({"registry", "unreadable", "error"})
"""Quarantine reasons judged again at every run, as their cause may have gone away: the
registry fixed, the file made readable, the reader fixed."""


def path_wagon(relpath: str) -> str | None:
    """The wagon directory of a path ``logs/<wagon>/<file>``, None for any other shape."""
    parts = relpath.split("/")
    return parts[1] if len(parts) == 3 else None


def registry_problem(registry: Registry, wagon_id: str) -> str | None:
    """Why ``wagon_id``'s files cannot be ingested with this registry, None if they can."""
    if wagon_id in registry.wagons:
        return None
    try:
        registry.wagon(wagon_id)
        return f"wagon {wagon_id} is not in the registry"
    except RegistryError as error:  # UnknownWagonError: its message says why
        return str(error)
