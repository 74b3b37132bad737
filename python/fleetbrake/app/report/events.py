"""The report's event sections: per wagon its brakings, sensor readings and contact
temperatures, and the hottest brakings of the fleet with the virtual sensor's peaks."""

from __future__ import annotations

from pathlib import Path

import polars as pl

from fleetbrake.app.report.data import ReportData
from fleetbrake.app.report.markdown import Section, bounded, fmt, table, upper
from fleetbrake.app.report.plots import plot_contact_temperatures

__all__ = ["events_section", "hottest_section"]


def events_section(data: ReportData) -> Section:
    """Per wagon: events, days, braking minutes, pressure, hottest readings and flags."""
    return Section(["## Events per wagon", "", *_events_table(data)])


def hottest_section(data: ReportData, picture: Path) -> Section:
    """The peak contact temperature of every braking (written to ``picture``) and the
    hottest brakings' table."""
    lines = ["## Hottest contact temperatures", ""]
    pictures = []
    if data.event_stats.height:
        png = plot_contact_temperatures(data.event_stats, data.current_revision, picture)
        pictures.append(png)
        lines += [f"![peak contact temperatures]({png.name})", ""]
    lines += _hottest_table(data)
    return Section(lines, pictures)


def _events_table(data: ReportData) -> list[str]:
    if data.events.height == 0:
        return ["No events.", ""]
    peaks = data.event_stats.filter(pl.col("model_revision") == (data.current_revision or ""))
    joined = data.events.join(
        peaks.select("event_id", "contact_max_c", "measured_max_c"), on="event_id", how="left"
    )
    summary = (
        joined.group_by("wagon_id")
        .agg(
            pl.len().alias("events"),
            pl.col("start_utc").dt.date().n_unique().alias("days"),
            (pl.col("duration_s").sum() / 60.0).alias("braking_min"),
            pl.col("p_mean_bar").mean().alias("p_mean_bar"),
            pl.col("measured_max_c").max().alias("measured_max_c"),
            pl.col("contact_max_c").max().alias("contact_max_c"),
        )
        .sort("wagon_id")
    )
    flagged = data.flags.group_by("wagon_id").len()
    nflags = dict(zip(flagged["wagon_id"], flagged["len"], strict=True))
    estimated = {
        r["wagon_id"]: upper(r["est_max_peak_c"], r["est_max_peak_hi_c"])
        for r in data.current_rows(data.estimate_wagon_peaks).iter_rows(named=True)
    }
    rows = [
        (
            r["wagon_id"],
            r["events"],
            r["days"],
            fmt(r["braking_min"], 0),
            fmt(r["p_mean_bar"], 2),
            fmt(r["measured_max_c"]),
            fmt(r["contact_max_c"]),
            estimated.get(r["wagon_id"], "-"),
            nflags.get(r["wagon_id"], 0),
        )
        for r in summary.iter_rows(named=True)
    ]
    return table(
        [
            "wagon",
            "events",
            "days",
            "braking (min)",
            "mean pressure (bar)",
            "hottest sensor reading (°C)",
            "hottest contact, predicted (°C)",
            "hottest contact, estimated (°C, 95 % upper)",
            "flags",
        ],
        rows,
    )


def _hottest_table(data: ReportData, top: int = 10) -> list[str]:
    peaks = data.event_stats.filter(pl.col("model_revision") == (data.current_revision or ""))
    if peaks.height == 0:
        return []
    joined = (
        peaks.join(
            data.events.select(
                "event_id", "start_utc", "duration_s", "v_start_kmh", "v_end_kmh", "p_mean_bar"
            ),
            on="event_id",
            how="left",
        )
        .drop_nulls("contact_max_c")
        .sort("contact_max_c", descending=True)
        .head(top)
    )
    estimated = data.current_rows(data.estimate_event_peaks)
    if estimated.height:
        joined = joined.join(
            estimated.drop("wagon_id", "model_revision"), on="event_id", how="left"
        )
    else:
        joined = joined.with_columns(
            pl.lit(None, dtype=pl.Float64).alias(c)
            for c in (
                "est_mean_peak_c",
                "est_mean_peak_lo_c",
                "est_mean_peak_hi_c",
                "est_max_peak_c",
                "est_max_peak_hi_c",
            )
        )
    rows = [
        (
            r["event_id"],
            r["wagon_id"],
            fmt(r["start_utc"]),
            fmt(r["duration_s"], 0),
            f"{fmt(r['v_start_kmh'], 0)} → {fmt(r['v_end_kmh'], 0)}",
            fmt(r["p_mean_bar"], 2),
            fmt(r["contact_max_c"]),
            fmt(r["contact_mean_max_c"]),
            upper(r["est_max_peak_c"], r["est_max_peak_hi_c"]),
            bounded(r["est_mean_peak_c"], r["est_mean_peak_lo_c"], r["est_mean_peak_hi_c"]),
            fmt(r["measured_max_c"]),
        )
        for r in joined.iter_rows(named=True)
    ]
    intro = (
        f"The {len(rows)} hottest brakings by predicted contact maximum "
        f"(revision `{data.current_revision}`), with the virtual sensor's peaks over the same "
        "seconds (95 % bounds in brackets):"
    )
    return [
        intro,
        "",
        *table(
            [
                "event",
                "wagon",
                "activation (UTC)",
                "duration (s)",
                "speed (km/h)",
                "mean pressure (bar)",
                "contact max (°C)",
                "contact mean (°C)",
                "contact max, estimated (°C, 95 % upper)",
                "contact mean, estimated (°C, 95 % band)",
                "sensor reading max (°C)",
            ],
            rows,
        ),
    ]
