"""The report's section on the virtual sensor: the flagged wagons' contact estimates around
their most severe flags, and per wagon the hottest estimated contact temperatures with their
bounds and the extremes of the unexplained heat power."""

from __future__ import annotations

from pathlib import Path

from fleetbrake.app.report.data import ReportData
from fleetbrake.app.report.markdown import Section, bounded, fmt, table, upper
from fleetbrake.app.report.plots import plot_contact_estimates

__all__ = ["estimates_section"]


def estimates_section(data: ReportData, picture: Path) -> Section:
    """The virtual sensor: the flagged wagons' plot (written to ``picture``), and per wagon
    its peak contact temperatures with their bounds and the extremes of the unexplained
    power."""
    lines = ["## Contact temperature: the virtual sensor", ""]
    if not data.has_estimates:
        return Section(
            [
                *lines,
                "The database has no contact estimates (no `v_contact_estimates`, or one "
                "without `resolution_s`: it was written by an older `run`).",
                "",
            ]
        )
    peaks = data.current_rows(data.estimate_wagon_peaks)
    if peaks.height == 0:
        return Section(
            [*lines, f"No contact estimates of revision `{data.current_revision}` yet.", ""]
        )
    lines += [
        "The virtual sensor estimates the wheel-block contact (friction-face) temperature "
        "through every logged second from the model and the thermistor together, with its "
        "95 % band (stored per second around brakings, flags and unexplained heat, per minute "
        "elsewhere), "
        "and the heat power on the friction face that the declared inputs do not explain "
        "(a dragging brake heats with the cylinder released; a weak brake heats less than "
        f"declared). Revision `{data.current_revision}`, filtered (live) estimate.",
        "",
    ]
    pictures = []
    if data.estimate_series:
        png = plot_contact_estimates(data.estimate_series, data.estimate_windows, picture)
        pictures.append(png)
        flagged = data.flags["wagon_id"].n_unique() if data.flags.height else 0
        which = (
            f" (the {len(data.estimate_windows)} of {flagged} flagged wagons with the most "
            "severe flags)"
            if flagged > len(data.estimate_windows)
            else ""
        )
        lines += [
            f"Around the most severe flag of each flagged wagon{which}: the estimate and its "
            "band against the open-loop prediction (dashed) and the sensor's readings "
            "(dots); below, the unexplained power and its band.",
            "",
            f"![contact estimates]({png.name})",
            "",
        ]
    flagged_counts = (
        dict(data.flags.group_by("wagon_id").len().iter_rows()) if data.flags.height else {}
    )
    rows = [
        (
            r["wagon_id"],
            bounded(r["est_mean_peak_c"], r["est_mean_peak_lo_c"], r["est_mean_peak_hi_c"]),
            fmt(r["est_mean_peak_utc"]),
            upper(r["est_max_peak_c"], r["est_max_peak_hi_c"]),
            bounded(r["power_max_w"], r["power_max_lo_w"], r["power_max_hi_w"], 0),
            bounded(r["power_min_w"], r["power_min_lo_w"], r["power_min_hi_w"], 0),
            flagged_counts.get(r["wagon_id"], 0),
        )
        for r in peaks.sort("wagon_id").iter_rows(named=True)
    ]
    lines += [
        "Per wagon, the hottest second of the estimate (95 % bounds in brackets) and the "
        "extremes of the unexplained power:",
        "",
        *table(
            [
                "wagon",
                "hottest contact mean (°C)",
                "at (UTC)",
                "hottest contact max (°C)",
                "highest unexplained power (W)",
                "lowest unexplained power (W)",
                "flags",
            ],
            rows,
        ),
    ]
    return Section(lines, pictures)
