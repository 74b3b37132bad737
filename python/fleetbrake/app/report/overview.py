"""The report's head and plain listings: the title and the data's span, the overview
table, the quarantined files and what the run wrote."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import polars as pl

from fleetbrake.app.report.data import ReportData
from fleetbrake.app.report.markdown import Section, table

__all__ = ["heading", "overview_section", "quarantined_section", "written_section"]


def heading(data: ReportData, title: str, notes: Sequence[str]) -> Section:
    """The title, the database and the events' span, and the ``notes`` under them."""
    lines = [f"# {title}", ""]
    lines += [f"Database `{data.db_path}`" + _span_text(data) + ".", ""]
    for note in notes:
        lines += [note, ""]
    return Section(lines)


def overview_section(data: ReportData) -> Section:
    """Counts of wagons, files, events, flags and revisions."""
    ingested = data.files.filter(pl.col("status") == "ingested")
    quarantined = data.files.filter(pl.col("status") == "quarantined")
    lines = ["## Overview", ""]
    overview = [
        ("wagons with data", len(data.wagons)),
        ("log files ingested", f"{ingested.height} ({int(ingested['rows'].sum() or 0):,} rows)"),
        ("log files quarantined", quarantined.height),
        ("braking events", data.events.height),
        ("flags", _flag_counts_text(data.flags)),
        ("model revisions", ", ".join(f"`{r}`" for r in data.revision_names) or "-"),
    ]
    lines += table(["", ""], overview)
    return Section(lines)


def quarantined_section(data: ReportData) -> Section:
    """Every quarantined file with its reason (nothing when none is)."""
    quarantined = data.files.filter(pl.col("status") == "quarantined")
    if not quarantined.height:
        return Section([])
    lines = ["## Quarantined files", ""]
    lines += table(
        ["file", "reason"],
        [
            (f["path"], (f["reason"] or "-").removeprefix(f"{f['path']}: "))
            for f in quarantined.iter_rows(named=True)
        ],
    )
    return Section(lines)


def written_section(artefacts: Sequence[tuple[str, str | Path]]) -> Section:
    """The (what, path) pairs the caller wrote beside the report (nothing when none)."""
    if not artefacts:
        return Section([])
    lines = ["## Written", ""]
    lines += [f"- {what}: `{path}`" for what, path in artefacts] + [""]
    return Section(lines)


def _span_text(data: ReportData) -> str:
    if data.samples_span is None:
        return ""
    a, b = data.samples_span
    return f", events from {a:%Y-%m-%d %H:%M} to {b:%Y-%m-%d %H:%M} UTC"


def _flag_counts_text(flags: pl.DataFrame) -> str:
    if flags.height == 0:
        return "none"
    counts = flags.group_by("kind").len().sort("kind")
    return f"{flags.height}: " + ", ".join(
        f"{k} {n}" for k, n in zip(counts["kind"], counts["len"], strict=True)
    )
