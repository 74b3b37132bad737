"""How the long-running commands (``watch``, ``bridge mqtt``) stop: SIGTERM or SIGINT sets an
event that the service checks between units, so the unit in progress finishes and commits and
the command exits 0 (a supervisor's ``systemctl stop`` is an ordinary end)."""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from types import FrameType

__all__ = ["stop_on_signals"]


@contextlib.contextmanager
def stop_on_signals(stop: threading.Event, logger: logging.Logger | None = None) -> Iterator[None]:
    """Set ``stop`` on SIGTERM and SIGINT while in the block (main thread only; elsewhere the
    block runs unchanged), saying so on ``logger``; the previous handlers are put back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        if logger is not None:
            logger.info("%s: finishing the unit in progress", signal.Signals(signum).name)
        stop.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
