"""An engine by name, as ``--engine`` and ``--workers`` ask for it."""

from __future__ import annotations

from fleetbrake.engine.base import Engine, EngineConfigError, default_workers
from fleetbrake.engine.inline import InlineEngine
from fleetbrake.engine.local import LocalEngine

__all__ = ["ENGINES", "make_engine"]

ENGINES = ("local", "ray")
"""Names ``--engine`` accepts (``ray``: with the ``ray`` extra installed)."""


def make_engine(
    name: str = "local",
    workers: int | None = None,
    *,
    preload: tuple[str, ...] = (),
    address: str | None = None,
) -> Engine:
    """``local``: a :class:`LocalEngine` of ``workers`` processes (default: the cores;
    ``preload``: modules its workers import as they start), or an :class:`InlineEngine` for
    ``workers=1``. ``ray``: a :class:`~fleetbrake.engine.ray.RayEngine` on the cluster at
    ``address`` (None: a local one of ``workers`` CPUs). :class:`EngineConfigError` (exit 2)
    for another name, ``workers < 1``, ``address`` without ``ray``, or ``ray`` when Ray is
    not installed (one line: ``pip install "fleetbrake[ray]"``)."""
    if name not in ENGINES:
        raise EngineConfigError(f"--engine must be one of {', '.join(ENGINES)}, got {name!r}")
    if workers is not None and workers < 1:
        raise EngineConfigError(f"--workers must be >= 1, got {workers}")
    if name == "ray":
        from fleetbrake.engine.ray import RayEngine  # imports Ray: only when asked for

        return RayEngine(address, workers)
    if address is not None:
        raise EngineConfigError("--address needs --engine ray")
    if (workers if workers is not None else default_workers()) == 1:
        return InlineEngine()
    return LocalEngine(workers, preload=preload)
