"""Benchmarks that print their figures beside a peer or a limit.

Their meters and peers (psutil, scikit-fem) are not dependencies of the product: they come
with the ``bench`` extra (``pip install "fleetbrake[bench]"``). Nothing outside this package
and the ``bench`` commands imports them; a benchmark that needs one checks for it first
(:func:`require_extra`) and says what to install.
"""

from __future__ import annotations

import importlib.util
import sys

from fleetbrake.errors import ConfigError, FleetbrakeError

__all__ = ["BenchConfigError", "BenchError", "BenchExtraMissingError", "require_extra"]


class BenchError(FleetbrakeError):
    """A benchmark could not run to its figures (exit 1); the message says which part."""


class BenchConfigError(BenchError, ConfigError):
    """A benchmark's setting is not usable (exit 2); the message names it."""


class BenchExtraMissingError(BenchConfigError):
    """A module of the ``bench`` extra is not installed (exit 2)."""


def _installed(module: str) -> bool:
    if module in sys.modules:
        return sys.modules[module] is not None
    return importlib.util.find_spec(module) is not None


def require_extra(benchmark: str, *modules: str) -> None:
    """Raise :class:`BenchExtraMissingError` naming ``benchmark`` and what to install when
    one of ``modules`` (top-level names, e.g. ``psutil``, ``skfem``) is not installed."""
    missing = [m for m in modules if not _installed(m)]
    if missing:
        raise BenchExtraMissingError(
            f"{benchmark} needs {', '.join(missing)}, which come with the bench extra: "
            'pip install "fleetbrake[bench]"'
        )
