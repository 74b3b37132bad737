"""The demo's outcome for people: what was made, found and written, and how long it took;
and the short texts the steps print as they go."""

from __future__ import annotations

import datetime as dt
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import rich
from rich.console import Console
from rich.markup import escape

from fleetbrake.app.demo.result import DemoResult

if TYPE_CHECKING:
    from fleetbrake.flags import FlagReport

__all__ = ["flag_counts", "loop_line", "plural", "print_summary", "seconds_text", "summary"]


def seconds_text(value: float) -> str:
    """``42 s``, or ``3 min 07 s`` from 90 s on."""
    if value < 90:
        return f"{value:.0f} s"
    return f"{int(value // 60)} min {value % 60:02.0f} s"


def plural(count: int, noun: str) -> str:
    """``1 wagon``, ``4 wagons``."""
    return f"{count} {noun}{'' if count == 1 else 's'}"


def _k(value: Any) -> str:
    return "-" if value is None else f"{value:.2f} K"


def flag_counts(flag_report: FlagReport | None) -> str:
    """The flags raised, in all and per kind."""
    if flag_report is None:
        return "not raised"
    counts = Counter(f.kind for f in flag_report.flags)
    if not counts:
        return "none"
    return (
        f"{sum(counts.values())} (" + ", ".join(f"{k} {n}" for k, n in sorted(counts.items())) + ")"
    )


def loop_line(loop: dict[str, Any]) -> str:
    """What the closed loop added (or that it added nothing), and the holdout's RMSE."""
    if not loop.get("new_revision"):
        return "no significant effect is missing: nothing added"
    params = ", ".join(f"{k} {v:.3g}" for k, v in loop.get("parameters", {}).items())
    hold = loop.get("holdout", {})
    return (
        f"added {loop['effect']} ({params}) as {loop['new_revision']}; holdout RMSE "
        f"{_k(hold.get('rmse_before_k'))} -> {_k(hold.get('rmse_after_k'))}"
    )


def _found_anomalies(db_path: Path, truth: Any) -> tuple[int, list[str]]:
    """How many injected anomalies a flag of the same kind overlaps (15 min slack), and the
    missed ones described."""
    import duckdb

    from fleetbrake.warehouse.connection import sql

    con = duckdb.connect(str(db_path), read_only=True)
    try:
        flags = con.sql(sql("q_demo_flag_spans")).fetchall()
    finally:
        con.close()
    slack = dt.timedelta(minutes=15)
    found, missed = 0, []
    for a in truth.anomalies:
        if any(
            w == a.wagon_id and k == a.kind and s <= a.end_utc + slack and e >= a.start_utc - slack
            for w, k, s, e in flags
        ):
            found += 1
        else:
            kind = a.kind + (f" ({a.subtype})" if a.subtype else "")
            missed.append(f"{a.wagon_id} {kind} {a.start_utc:%m-%d %H:%M}")
    return found, missed


def summary(result: DemoResult) -> str:
    """The demo's outcome for people: what was made, found and written, and how long it took."""
    truth, run, loop, config = result.truth, result.run, result.close_loop, result.config
    ingest = run.ingest
    by_wagon = Counter(r.wagon_id or "?" for r in ingest.quarantined)
    ok = {w.wagon_id for w in truth.wagons if w.registry == "ok"}
    registered = len(ok)
    made = sum(1 for e in truth.events if e.recorded and e.wagon_id in ok)
    lines = [
        "fleetbrake demo",
        "",
        f"fleet       {plural(config.wagons, 'wagon')} x {config.days} days from {config.start} "
        f"(seed {config.seed}); {len(truth.wagons)} wagons wrote logs ({registered} registered "
        f"and valid, the others have no or a bad registry entry); {len(truth.files)} log files",
        f"hidden      undeclared effect {truth.effects}; {len(truth.anomalies)} anomalies injected"
        if config.anomalies
        else f"hidden      undeclared effect {truth.effects}; no anomalies",
        f"model       reduced model at refinement {result.refinement:g}"
        + (" (the default mesh)" if result.refinement == 1.0 else " (coarser than the default)")
        + f", {'built' if result.rom_built else 'loaded from the cache'} in "
        f"{seconds_text(result.rom_seconds)}",
        f"ingested    {len(ingest.ingested)} files ({ingest.rows:,} rows); quarantined "
        f"{len(ingest.quarantined)}"
        + (
            " (" + ", ".join(f"{w}: {n}" for w, n in sorted(by_wagon.items())) + ")"
            if by_wagon
            else ""
        ),
        f"events      {run.simulation.events_simulated} simulated of "
        f"{ingest.events.total if ingest.events else '?'} detected "
        f"(the generator made {made} brakings in the logs of the registered wagons)",
        f"flags       declared model: {flag_counts(run.flags)}",
    ]
    if result.rerun is not None:
        lines.append(
            f"            after the closed loop ({loop['new_revision']}): "
            f"{flag_counts(result.rerun.flags)}"
        )
    if truth.anomalies:
        flagged, missed = _found_anomalies(result.db_path, truth)
        lines.append(
            f"            injected anomalies flagged: {flagged} of {len(truth.anomalies)}"
            + (f"; missed: {'; '.join(missed)}" if missed else "")
        )
    if result.close_loop_error is not None:
        lines.append(f"closed loop could not run: {result.close_loop_error}")
    fit, hold = loop.get("fit", {}), loop.get("holdout", {})
    lines += [
        f"closed loop fit {fit.get('events', 0)} events before {config.holdout_from}, "
        f"holdout {hold.get('events', 0)} events on it",
        f"            RMSE fit {_k(fit.get('rmse_before_k'))} -> {_k(fit.get('rmse_after_k'))}, "
        f"holdout {_k(hold.get('rmse_before_k'))} -> {_k(hold.get('rmse_after_k'))}",
    ]
    if loop.get("new_revision"):
        params = ", ".join(f"{k} = {v:.3g}" for k, v in loop.get("parameters", {}).items())
        lines.append(f"            found {loop['effect']} ({params}) -> {loop['new_revision']}")
    else:
        lines.append("            found nothing significant to add")
    true_params = "; ".join(
        f"{e.name} (" + ", ".join(f"{k} = {v:.3g}" for k, v in e.parameters.items()) + ")"
        for e in truth.effects
    )
    found = set((loop.get("effect") or "").split("+")) - {""}
    extra = sorted(found - set(truth.effects.names))
    if result.effect_matched:
        verdict = "MATCHED"
    elif found & set(truth.effects.names):
        verdict = f"PARTLY matched (the true effect, with {' + '.join(extra)} on top)"
    else:
        verdict = "NOT matched"
    lines.append(f"            truth {true_params}: {verdict}")
    lines += ["", "written"]
    for what, path in result.artefacts():
        lines.append(f"  {path}  ({what})")
    for png in result.pictures:
        lines.append(f"  {png}")
    if result.event_id:
        lines.append(f"  (the event recording: {result.event_reason})")
    steps = ", ".join(
        f"{name.replace('_', ' ')} {seconds_text(t)}"
        for name, t in result.timings.items()
        if name != "total"
    )
    total = result.timings.get("total", sum(result.timings.values()))
    lines += ["", f"took {seconds_text(total)} ({steps})"]
    lines.append(f"read {result.report} first; open a recording with `rerun FILE.rrd`")
    return "\n".join(lines)


def print_summary(result: DemoResult, console: Console | None = None) -> None:
    """Print :attr:`DemoResult.summary` as it is (no markup, no highlighting)."""
    (console or rich.get_console()).print(escape(result.summary), highlight=False, soft_wrap=True)
