"""``fleetbrake demo``: the whole of fleetbrake on a synthetic fleet, in a few minutes.

::

    from fleetbrake.app.demo import DemoConfig, run_demo

    result = run_demo("demo-out", DemoConfig(wagons=4, days=2))
    print(result.summary)

One module per part: :mod:`~fleetbrake.app.demo.config` (:class:`DemoConfig` and the errors),
:mod:`~fleetbrake.app.demo.outdir` (the output directory, never mixed nor wiped unless a
demo's), :mod:`~fleetbrake.app.demo.steps` (the seven steps and :func:`run_demo`, which calls
them in order), :mod:`~fleetbrake.app.demo.result` (what a demo wrote and found) and
:mod:`~fleetbrake.app.demo.summary` (its outcome for people).
"""

from fleetbrake.app.demo.config import (
    DEMO_EFFECT,
    DemoConfig,
    DemoConfigError,
    DemoError,
    DemoExistsError,
)
from fleetbrake.app.demo.outdir import MARKER, prepare_out_dir
from fleetbrake.app.demo.result import DemoResult
from fleetbrake.app.demo.steps import pick_event, run_demo
from fleetbrake.app.demo.summary import print_summary, summary

__all__ = [
    "DEMO_EFFECT",
    "MARKER",
    "DemoConfig",
    "DemoConfigError",
    "DemoError",
    "DemoExistsError",
    "DemoResult",
    "pick_event",
    "prepare_out_dir",
    "print_summary",
    "run_demo",
    "summary",
]
