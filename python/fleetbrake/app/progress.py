"""Progress shown to people while a long step runs: a spinner with the elapsed time, and the
bar over the wagons of a fleet being generated. Both draw nothing when ``show`` is false
(the command line turns them off when stdout is not a terminal, and with ``--quiet``), and
both are transient: once the step is done, the terminal holds only what the command printed.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
)

__all__ = ["generation_bar", "spinner"]


@contextlib.contextmanager
def spinner(text: str, show: bool, console: Console | None = None) -> Iterator[None]:
    """A spinner with ``text`` and the elapsed time while the block runs (on ``console``, so
    that bars drawn inside on the same console nest), or nothing."""
    if not show:
        yield
        return
    with Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as bar:
        bar.add_task(text, total=None)
        yield


@contextlib.contextmanager
def generation_bar(
    total: int, show: bool, console: Console | None = None
) -> Iterator[Callable[[str], None]]:
    """A bar over the ``total`` wagons of a fleet being generated; yields the ``progress``
    callback of :func:`fleetbrake.synth.generator.generate_fleet` (it advances on each
    ``simulating WAGON`` message and shows the wagon). Without ``show``, a callback that
    does nothing."""
    if not show:
        yield lambda _message: None
        return
    with Progress(
        TextColumn("generating the fleet"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[now]}"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task("generate", total=total, now="")
        seen = 0

        def step(message: str) -> None:
            nonlocal seen
            if message.startswith("simulating"):
                if seen:
                    bar.advance(task)
                seen += 1
                bar.update(task, now=message.removeprefix("simulating").strip())

        yield step
        bar.update(task, completed=total, now="")
