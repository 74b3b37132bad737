"""What the commands print: lines for people, and the one-line JSON summaries of ``run`` and
``close-loop`` (``--json``: the last line of stdout, for schedulers).

``run``'s summary::

    {"command": "run", "revision": "declared",
     "files": {"seen": 12, "ingested": 10, "quarantined": 2}, "rows": 61785,
     "events": 35, "events_simulated": 35, "prediction_rows": 24500,
     "flags": {"sensor_fault": 2, "weak_brake": 1}, "wagons_judged": 3,
     "stage_s": {"ingest": 0.8, ...}}

``flags`` counts the fleet's flags after a whole run (a second run judges no wagon,
``wagons_judged`` 0, and still counts them), a unit of ``watch``'s own wagons' flags.

``close-loop``'s summary::

    {"command": "close-loop", "new_revision": "r1-convection_speed", "effect": "convection_speed",
     "parameters": {"gain": 2.1, "exponent": 0.8},
     "fit": {"events": 30, "rmse_before_k": 4.1, "rmse_after_k": 0.6},
     "holdout": {"events": 12, "rmse_before_k": 4.3, "rmse_after_k": 0.7},
     "adequate": true, "noise_k": 0.3, "report": "cl.json"}
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

if TYPE_CHECKING:
    from fleetbrake.app.run import RunReport
    from fleetbrake.flags import Flag

__all__ = ["close_loop_summary", "echo_json", "print_close_loop", "print_run", "run_summary"]


def echo_json(summary: Mapping[str, Any]) -> None:
    """``summary`` as one line of JSON on stdout."""
    typer.echo(json.dumps(summary, default=str))


def _flags(report: RunReport) -> list[Flag]:
    """The flags a run reports: after a whole run the fleet's (judged now or standing), after
    a unit of ``watch`` the flags of the wagons it judged."""
    if report.fleet_flags is not None:
        return list(report.fleet_flags)
    return list(report.flags.flags) if report.flags is not None else []


def _judged(report: RunReport) -> int:
    return len(report.flags.wagons) if report.flags is not None else 0


def run_summary(report: RunReport) -> dict[str, Any]:
    """The summary of ``fleetbrake run`` (see the module)."""
    ingest, sim = report.ingest, report.simulation
    by_kind = Counter(flag.kind for flag in _flags(report))
    return {
        "command": "run",
        "revision": report.revision,
        "files": {
            "seen": ingest.files_seen,
            "ingested": len(ingest.ingested),
            "quarantined": len(ingest.quarantined),
        },
        "rows": ingest.rows,
        "rows_rejected": ingest.rows_rejected,
        "events": ingest.events.total if ingest.events is not None else None,
        "events_simulated": sim.events_simulated,
        "prediction_rows": sim.prediction_rows,
        "flags": dict(sorted(by_kind.items())),
        "wagons_judged": _judged(report),
        "stage_s": {stage: round(seconds, 3) for stage, seconds in report.stage_s.items()},
    }


def print_run(report: RunReport) -> None:
    """What ``fleetbrake run`` did, for people (after the ingestion's own report)."""
    sim = report.simulation
    typer.echo(
        f"simulated {sim.events_simulated} events with revision {report.revision} "
        f"({sim.prediction_rows:,} prediction rows)"
    )
    for reason in sim.skipped:
        typer.echo(f"  not simulated: {reason}")
    flags = _flags(report)
    by_kind = Counter(flag.kind for flag in flags)
    counts = ", ".join(f"{n} {kind}" for kind, n in sorted(by_kind.items())) or "none"
    typer.echo(f"flags: {counts} ({_judged(report)} wagons judged by this run)")
    for flag in flags:
        typer.echo(f"  [{flag.severity}] {flag.kind} {flag.wagon_id}: {flag.evidence}")


def close_loop_summary(report: Mapping[str, Any], json_out: Path) -> dict[str, Any]:
    """The summary of ``fleetbrake close-loop`` (see the module): the report's headline, and
    where the report is."""
    summary: dict[str, Any] = {
        "command": "close-loop",
        "new_revision": report.get("new_revision"),
        "effect": report.get("effect"),
        "parameters": report.get("parameters") or {},
    }
    for part in ("fit", "holdout"):
        figures = report.get(part) or {}
        summary[part] = {
            key: figures.get(key) for key in ("events", "rmse_before_k", "rmse_after_k")
        }
    for key in ("adequate", "noise_k"):
        if key in report:
            summary[key] = report[key]
    summary["report"] = str(json_out)
    return summary


def print_close_loop(report: Mapping[str, Any], json_out: Path) -> None:
    """What ``fleetbrake close-loop`` found, for people."""
    if report.get("new_revision"):
        holdout = report.get("holdout") or {}
        typer.echo(
            f"added {report['effect']} {report['parameters']} as {report['new_revision']}: "
            f"holdout RMSE {holdout.get('rmse_before_k')} -> {holdout.get('rmse_after_k')} K"
        )
    else:
        typer.echo("no significant effect is missing: nothing added")
    typer.echo(f"report: {json_out} and {json_out.with_suffix('.md')}")
