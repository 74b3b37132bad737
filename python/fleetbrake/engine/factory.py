"""An engine by name, as ``--engine`` and ``--workers`` ask for it."""

from __future__ import annotations

from fleetbrake.engine.base import Engine, EngineConfigError, default_workers
from fleetbrake.engine.inline import InlineEngine
from fleetbrake.engine.local import LocalEngine

__all__ = ["ENGINES", "make_engine"]

ENGINES = ("local", "ray")
"""Names ``--engine`` accepts (``ray``: refused until issue 15 builds it)."""


def make_engine(
    name: str = "local", workers: int | None = None, *, preload: tuple[str, ...] = ()
) -> Engine:
    """``local``: a :class:`LocalEngine` of ``workers`` processes (default: the cores;
    ``preload``: modules its workers import as they start), or an :class:`InlineEngine` for
    ``workers=1``. :class:`EngineConfigError` (exit 2) for ``ray``
    (not yet available), another name, or ``workers < 1``."""
    if name == "ray":
        raise EngineConfigError(
            "--engine ray: the Ray engine is not available yet (issue 15); use --engine local"
        )
    if name != "local":
        raise EngineConfigError(f"--engine must be one of {', '.join(ENGINES)}, got {name!r}")
    if workers is not None and workers < 1:
        raise EngineConfigError(f"--workers must be >= 1, got {workers}")
    if (workers if workers is not None else default_workers()) == 1:
        return InlineEngine()
    return LocalEngine(workers, preload=preload)
