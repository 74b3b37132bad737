"""The report's pictures: one function per picture, each taking its data and a path and
returning the path (matplotlib's Agg backend: no display needed).

* :func:`plot_event_predictions`: measured against predicted sensor temperature, for a few
  representative events per wagon (hottest, worst predicted, typical), every revision;
* :func:`plot_flag_timeline`: the flags on a timeline, one row per wagon, coloured by kind
  (and, with a truth, the injected anomalies beneath them);
* :func:`plot_close_loop_error`: the closed loop's RMSE before and after, fit and holdout;
* :func:`plot_contact_temperatures`: the peak predicted contact temperature of every event;
* :func:`plot_contact_estimates`: per flagged wagon, around its most severe flag, the virtual
  sensor's contact estimate with its 95 % band against the open-loop prediction and the
  reading, and the unexplained heat power with its band.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import polars as pl

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "FLAG_COLORS",
    "plot_close_loop_error",
    "plot_contact_estimates",
    "plot_contact_temperatures",
    "plot_event_predictions",
    "plot_flag_timeline",
]

FLAG_COLORS: dict[str, str] = {
    "dragging_brake": "#d62728",
    "weak_brake": "#1f77b4",
    "sensor_fault": "#9467bd",
    "overheating": "#ff7f0e",
}
"""One colour per flag kind (``v_flags.kind``), the same in every picture."""

_REVISION_STYLES = ("--", "-", ":", "-.")
_REVISION_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#8c564b")


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _dates() -> Any:
    """``matplotlib.dates`` (its ``date2num`` and ``DateFormatter`` are not annotated)."""
    import matplotlib.dates

    return matplotlib.dates


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    _pyplot().close(fig)
    return path


# --------------------------------------------------------------------------------------------
# Data


def plot_event_predictions(
    series: pl.DataFrame,
    representative: Mapping[str, Sequence[tuple[str, str]]],
    revisions: Sequence[str],
    path: str | Path,
) -> Path:
    """Measured against predicted sensor temperature of the representative events: a row per
    wagon, a column per event, one line per model revision, time since activation."""
    plt = _pyplot()
    wagons = [w for w in representative if representative[w]]
    cols = max((len(v) for v in representative.values()), default=1)
    rows = max(len(wagons), 1)
    fig, axes = plt.subplots(
        rows, cols, figsize=(4.2 * cols, 2.6 * rows), squeeze=False, sharey="row"
    )
    for ax in axes.flat:
        ax.set_visible(False)
    for r, wagon_id in enumerate(wagons):
        for c, (event_id, why) in enumerate(representative[wagon_id]):
            ax = axes[r, c]
            ax.set_visible(True)
            part = series.filter(pl.col("event_id") == event_id)
            if part.height == 0:
                continue
            t0 = part["time_utc"].min()
            measured = part.filter(pl.col("model_revision") == revisions[0] if revisions else True)
            minutes = (measured["time_utc"] - t0).dt.total_seconds() / 60.0
            ax.plot(
                minutes.to_numpy(),
                measured["measured_sensor_c"].to_numpy(),
                ".",
                ms=1.5,
                color="black",
                label="measured",
                zorder=3,
            )
            for i, rev in enumerate(revisions):
                mine = part.filter(pl.col("model_revision") == rev)
                if mine.height == 0:
                    continue
                ax.plot(
                    ((mine["time_utc"] - t0).dt.total_seconds() / 60.0).to_numpy(),
                    mine["predicted_sensor_c"].to_numpy(),
                    _REVISION_STYLES[i % len(_REVISION_STYLES)],
                    color=_REVISION_COLORS[i % len(_REVISION_COLORS)],
                    lw=1.3,
                    label=f"predicted, {rev}",
                )
            ax.set_title(f"{event_id} ({why})", fontsize=8)
            ax.tick_params(labelsize=7)
            if c == 0:
                ax.set_ylabel(f"{wagon_id}\nsensor (°C)", fontsize=8)
            if r == len(wagons) - 1:
                ax.set_xlabel("minutes since activation", fontsize=8)
    handles: list[Any] = []
    labels: list[str] = []
    for ax in axes.flat:
        if ax.get_visible():
            h, lab = ax.get_legend_handles_labels()
            if len(lab) > len(labels):
                handles, labels = h, lab
    if labels:
        fig.legend(handles, labels, loc="upper center", ncol=len(labels), fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.97 if rows > 1 else 0.9))
    return _save(fig, path)


def plot_flag_timeline(
    flags: pl.DataFrame,
    events: pl.DataFrame,
    wagons: Sequence[str],
    path: str | Path,
    *,
    truth_anomalies: Sequence[Mapping[str, Any]] = (),
) -> Path:
    """The flags on a timeline: a row per wagon, a bar per flag coloured by kind (alarms
    with a black edge), the events as grey ticks; ``truth_anomalies`` (dicts with
    ``wagon_id``, ``kind``, ``start_utc``, ``end_utc``), if given, as hollow bars beneath."""
    mdates = _dates()
    from matplotlib.patches import Patch

    plt = _pyplot()
    wagons = list(wagons) or sorted(set(flags["wagon_id"].to_list()))
    fig, ax = plt.subplots(figsize=(11, 0.7 * max(len(wagons), 1) + 1.6))
    times = [t for t in events["start_utc"].to_list() if t is not None]
    times += [t for t in flags["start_utc"].to_list() + flags["end_utc"].to_list() if t]
    if times:
        span = (max(times) - min(times)).total_seconds() or 3600.0
    else:
        span = 3600.0
    min_width = dt.timedelta(seconds=span / 250.0)  # a short flag stays visible
    row = {w: i for i, w in enumerate(wagons)}
    for wagon_id, start in zip(events["wagon_id"], events["start_utc"], strict=True):
        if wagon_id in row and start is not None:
            y = row[wagon_id]
            ax.vlines(mdates.date2num(start), y - 0.35, y - 0.15, color="0.6", lw=0.5)
    for f in flags.iter_rows(named=True):
        if f["wagon_id"] not in row:
            continue
        start, end = f["start_utc"], f["end_utc"]
        width = max(end - start, min_width)
        ax.broken_barh(
            [(mdates.date2num(start), width / dt.timedelta(days=1))],
            (row[f["wagon_id"]] - 0.1, 0.4),
            facecolors=FLAG_COLORS.get(f["kind"], "0.3"),
            edgecolors="black" if f["severity"] == "alarm" else "none",
            linewidth=1.2,
        )
    for a in truth_anomalies:
        if a["wagon_id"] not in row:
            continue
        width = max(a["end_utc"] - a["start_utc"], min_width)
        ax.broken_barh(
            [(mdates.date2num(a["start_utc"]), width / dt.timedelta(days=1))],
            (row[a["wagon_id"]] + 0.32, 0.18),
            facecolors="none",
            edgecolors=FLAG_COLORS.get(a["kind"], "0.3"),
            linewidth=1.0,
            hatch="////",
        )
    ax.set_yticks(range(len(wagons)), wagons)
    ax.set_ylim(len(wagons) - 0.4, -0.6)
    ax.xaxis_date()
    ax.xaxis.set_major_formatter(mdates.DateFormatter("%m-%d %H:%M"))
    ax.set_xlabel("UTC")
    legend = [Patch(facecolor=c, label=k) for k, c in FLAG_COLORS.items()]
    legend.append(Patch(facecolor="white", edgecolor="black", label="alarm (edge)"))
    if truth_anomalies:
        legend.append(
            Patch(facecolor="none", edgecolor="0.3", hatch="////", label="injected (truth)")
        )
    ax.legend(handles=legend, loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=6, fontsize=8)
    ax.set_title("Flags per wagon (ticks: braking events)", fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)


def plot_close_loop_error(close_loop: Mapping[str, Any], path: str | Path) -> Path:
    """RMSE measured - predicted before and after the closed loop, on the fit and the
    holdout events (the close-loop report's ``fit`` and ``holdout``)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    groups = ("fit", "holdout")
    before = [_num(close_loop.get(g, {}).get("rmse_before_k")) for g in groups]
    after = [_num(close_loop.get(g, {}).get("rmse_after_k")) for g in groups]
    x = range(len(groups))
    base = close_loop.get("baseline_revision") or "before"
    new = close_loop.get("new_revision") or "after (unchanged)"
    bars_b = ax.bar([i - 0.18 for i in x], before, 0.36, label=base, color=_REVISION_COLORS[0])
    bars_a = ax.bar([i + 0.18 for i in x], after, 0.36, label=new, color=_REVISION_COLORS[1])
    for bars in (bars_b, bars_a):
        for bar in bars:
            h = bar.get_height()
            if math.isfinite(h):
                ax.annotate(
                    f"{h:.2f}",
                    (bar.get_x() + bar.get_width() / 2, h),
                    ha="center",
                    va="bottom",
                    fontsize=8,
                )
    labels = [f"{g}\n({close_loop.get(g, {}).get('events', 0)} events)" for g in groups]
    ax.set_xticks(list(x), labels)
    ax.set_ylabel("RMSE measured - predicted (K)")
    ax.set_title(f"Closed loop: {close_loop.get('effect') or 'nothing added'}", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def plot_contact_temperatures(
    event_stats: pl.DataFrame, revision: str | None, path: str | Path
) -> Path:
    """The peak predicted wheel-block contact temperature (friction-face maximum) of every
    event of ``revision``, over time, one colour per wagon."""
    mdates = _dates()

    plt = _pyplot()
    frame = event_stats.filter(pl.col("model_revision") == (revision or "")).drop_nulls(
        "contact_max_c"
    )
    fig, ax = plt.subplots(figsize=(11, 3.6))
    for wagon_id in sorted(set(frame["wagon_id"].to_list())):
        mine = frame.filter(pl.col("wagon_id") == wagon_id)
        ax.plot(
            mdates.date2num(mine["first_utc"].to_list()),
            mine["contact_max_c"].to_numpy(),
            "o",
            ms=3,
            label=wagon_id,
        )
    ax.xaxis_date()
    ax.xaxis.set_major_formatter(mdates.DateFormatter("%m-%d %H:%M"))
    ax.set_ylabel("peak contact temperature (°C)")
    ax.set_xlabel("activation (UTC)")
    ax.set_title(f"Predicted contact maximum per braking (revision {revision})", fontsize=10)
    if frame.height:
        ax.legend(fontsize=8, ncol=6)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)


def _with_breaks(frame: pl.DataFrame, gap_s: float = 10.0) -> pl.DataFrame:
    """``frame`` (by ``time_utc``) with a row of nulls a second after each gap longer than
    ``gap_s`` beyond the rows' step (``resolution_s`` where the frame has it: a minute row
    follows the row before it by a minute), so that a line is not drawn across a data gap."""
    step_s = pl.lit(1) if "resolution_s" not in frame.columns else pl.col("resolution_s")
    step_s = pl.max_horizontal(step_s, step_s.shift(-1).fill_null(step_s))
    after_gap = pl.col("time_utc").diff().shift(-1).dt.total_seconds() > step_s - 1 + gap_s
    breaks = frame.filter(after_gap).select(pl.col("time_utc") + dt.timedelta(seconds=1))
    if breaks.height == 0:
        return frame
    return pl.concat([frame, breaks], how="diagonal").sort("time_utc")


def plot_contact_estimates(
    series: Mapping[str, pl.DataFrame],
    windows: Mapping[str, tuple[dt.datetime, dt.datetime, Mapping[str, Any]]],
    path: str | Path,
) -> Path:
    """Per wagon of ``series`` (the rows of ``q_report_estimate_series``), two plots over its
    window: the virtual sensor's filtered contact mean with its 95 % band against the
    open-loop predicted contact mean and the measured sensor temperature; below, the
    unexplained heat power with its band. The flag the window is around is shaded in both."""
    mdates = _dates()
    plt = _pyplot()
    wagons = [w for w in windows if w in series and series[w].height]
    rows = max(len(wagons), 1)
    fig, axes = plt.subplots(
        2 * rows,
        1,
        figsize=(11, 3.9 * rows),
        squeeze=False,
        gridspec_kw={"height_ratios": [2.2, 1.2] * rows},
    )
    for k, wagon_id in enumerate(wagons):
        frame = _with_breaks(series[wagon_id])
        start, end, flag = windows[wagon_id]
        times = mdates.date2num(frame["time_utc"].to_list())
        top, bottom = axes[2 * k, 0], axes[2 * k + 1, 0]
        top.fill_between(
            times,
            frame["contact_mean_lo_c"].to_numpy(),
            frame["contact_mean_hi_c"].to_numpy(),
            color="#17becf",
            alpha=0.3,
            lw=0,
            label="estimate, 95 % band",
        )
        top.plot(
            times, frame["contact_mean_c"].to_numpy(), color="#17becf", lw=1.2, label="estimate"
        )
        top.plot(
            times,
            frame["predicted_contact_mean_c"].to_numpy(),
            "--",
            color="#d62728",
            lw=1.0,
            label="open-loop prediction",
        )
        top.plot(
            times,
            frame["measured_sensor_c"].to_numpy(),
            ".",
            ms=1.2,
            color="black",
            label="sensor reading",
        )
        top.set_ylabel("contact mean (°C)", fontsize=8)
        top.set_title(
            f"{wagon_id}: {flag['kind']} [{flag['severity']}] "
            f"{flag['start_utc']:%m-%d %H:%M} to {flag['end_utc']:%m-%d %H:%M} UTC",
            fontsize=9,
        )
        bottom.fill_between(
            times,
            frame["unexplained_power_lo_w"].to_numpy(),
            frame["unexplained_power_hi_w"].to_numpy(),
            color="#bcbd22",
            alpha=0.3,
            lw=0,
            label="95 % band",
        )
        bottom.plot(
            times,
            frame["unexplained_power_w"].to_numpy(),
            color="#8c8c00",
            lw=1.0,
            label="unexplained power",
        )
        bottom.axhline(0.0, color="0.5", lw=0.6)
        bottom.set_ylabel("power (W)", fontsize=8)
        for ax in (top, bottom):
            ax.axvspan(
                mdates.date2num(flag["start_utc"]),
                mdates.date2num(flag["end_utc"]),
                color=FLAG_COLORS.get(flag["kind"], "0.5"),
                alpha=0.12,
                lw=0,
            )
            ax.set_xlim(mdates.date2num(start), mdates.date2num(end))
            ax.xaxis_date()
            ax.xaxis.set_major_formatter(mdates.DateFormatter("%m-%d %H:%M"))
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
        if k == 0:
            top.legend(fontsize=7, ncol=4, loc="upper left")
            bottom.legend(fontsize=7, ncol=2, loc="upper left")
    if not wagons:
        axes[0, 0].set_visible(False)
        axes[1, 0].set_visible(False)
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------------------------
# Markdown


def _num(value: Any) -> float:
    return float("nan") if value is None else float(value)
