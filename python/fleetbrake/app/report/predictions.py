"""The report's section on the model's error: measured against predicted sensor temperature
for the representative events, and the RMSE per wagon and revision."""

from __future__ import annotations

from pathlib import Path

import polars as pl

from fleetbrake.app.report.data import ReportData
from fleetbrake.app.report.markdown import Section, fmt, table
from fleetbrake.app.report.plots import plot_event_predictions

__all__ = ["predictions_section"]


def predictions_section(data: ReportData, picture: Path) -> Section:
    """The representative events' plot (written to ``picture``) and the error per wagon."""
    lines = ["## Measured against predicted sensor temperature", ""]
    if not data.representative:
        return Section([*lines, "No predictions in the database.", ""])
    png = plot_event_predictions(data.series, data.representative, data.revision_names, picture)
    lines += [
        "Representative events of each wagon: the hottest, the one the first revision "
        "predicted worst, and a typical one; black dots are the thermistor's readings.",
        "",
        f"![measured against predicted]({png.name})",
        "",
    ]
    lines += _error_by_wagon_table(data)
    return Section(lines, [png])


def _error_by_wagon_table(data: ReportData) -> list[str]:
    stats = data.event_stats.filter(pl.col("valid_s") > 0)
    if stats.height == 0:
        return []
    # RMSE over every valid second: weight each event's mean square by its valid seconds
    by = (
        stats.with_columns((pl.col("rmse_k") ** 2 * pl.col("valid_s")).alias("_sq"))
        .group_by("wagon_id", "model_revision")
        .agg((pl.col("_sq").sum() / pl.col("valid_s").sum()).sqrt().alias("rmse_k"))
    )
    revisions = [r for r in data.revision_names if r in set(by["model_revision"].to_list())]
    rows = []
    for wagon_id in sorted(set(by["wagon_id"].to_list())):
        mine = by.filter(pl.col("wagon_id") == wagon_id)
        lookup = dict(zip(mine["model_revision"], mine["rmse_k"], strict=True))
        rows.append((wagon_id, *(fmt(lookup.get(r), 3) for r in revisions)))
    header = ["wagon", *(f"`{r}`" for r in revisions)]
    return [
        "RMSE measured - predicted sensor temperature per wagon (K):",
        "",
        *table(header, rows),
    ]
