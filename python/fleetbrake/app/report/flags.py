"""The report's flags section: the timeline picture, every flag (most severe first) and,
for a synthetic fleet, what the generator injected and whether a flag found it."""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import polars as pl

from fleetbrake.app.report.data import SEVERITY_RANK, ReportData
from fleetbrake.app.report.markdown import Section, fmt, table
from fleetbrake.app.report.plots import plot_flag_timeline

if TYPE_CHECKING:
    from fleetbrake.synth.generator import FleetTruth

__all__ = ["flags_section"]


def flags_section(data: ReportData, truth: FleetTruth | None, picture: Path) -> Section:
    """The flags on a timeline (written to ``picture``, with the truth's anomalies beneath
    them), the flags' table and the truth's table."""
    anomalies = _truth_anomalies(truth)
    lines = ["## Flags", ""]
    png = plot_flag_timeline(
        data.flags, data.events, data.wagons, picture, truth_anomalies=anomalies
    )
    lines += [f"![flags per wagon]({png.name})", ""]
    if data.flags.height:
        ordered = data.flags.with_columns(
            pl.col("severity").replace_strict(SEVERITY_RANK, default=9).alias("_rank")
        ).sort("_rank", "wagon_id", "start_utc")
        lines += table(
            ["wagon", "kind", "severity", "from", "to", "event", "evidence"],
            [
                (
                    f["wagon_id"],
                    f["kind"],
                    f["severity"],
                    fmt(f["start_utc"]),
                    fmt(f["end_utc"]),
                    f["event_id"] or "-",
                    f["evidence"],
                )
                for f in ordered.iter_rows(named=True)
            ],
        )
    else:
        lines += ["No flags.", ""]
    if anomalies:
        lines += _truth_table(data.flags, anomalies)
    return Section(lines, [png])


def _truth_anomalies(truth: FleetTruth | None) -> list[dict[str, Any]]:
    if truth is None:
        return []
    return [
        {
            "wagon_id": a.wagon_id,
            "kind": a.kind,
            "subtype": a.subtype,
            "start_utc": a.start_utc,
            "end_utc": a.end_utc,
        }
        for a in truth.anomalies
    ]


def _flag_matches(
    flags: pl.DataFrame, anomaly: Mapping[str, Any], slack: dt.timedelta
) -> pl.DataFrame:
    return flags.filter(
        (pl.col("wagon_id") == anomaly["wagon_id"])
        & (pl.col("kind") == anomaly["kind"])
        & (pl.col("start_utc") <= anomaly["end_utc"] + slack)
        & (pl.col("end_utc") >= anomaly["start_utc"] - slack)
    )


def _truth_table(flags: pl.DataFrame, anomalies: Sequence[Mapping[str, Any]]) -> list[str]:
    """What the generator injected, and whether a flag of the same kind covers it."""
    slack = dt.timedelta(minutes=15)
    rows = []
    for a in anomalies:
        hits = _flag_matches(flags, a, slack)
        kind = a["kind"] + (f" ({a['subtype']})" if a.get("subtype") else "")
        rows.append(
            (
                a["wagon_id"],
                kind,
                fmt(a["start_utc"]),
                fmt(a["end_utc"]),
                ", ".join(f"{s}" for s in hits["severity"].to_list()) or "**missed**",
            )
        )
    found = sum(1 for r in rows if r[-1] != "**missed**")
    intro = (
        f"Injected by the generator (truth): {found} of {len(rows)} found by a flag of the "
        "same kind overlapping it (15 min slack)."
    )
    return [intro, "", *table(["wagon", "anomaly", "from", "to", "flagged"], rows)]
