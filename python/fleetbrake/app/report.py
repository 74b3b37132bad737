"""The fleet report: Markdown with PNG plots, read from a warehouse's views only.

::

    from fleetbrake.app.report import write_report

    result = write_report("demo-out/fleet.duckdb", "demo-out", close_loop=report_dict)
    result.path      # demo-out/report.md
    result.pictures  # the PNGs beside it, each referenced from the Markdown

Everything comes from the public views (``v_files``, ``v_events``, ``v_predictions``,
``v_flags``, ``v_model_revisions``, ``v_contact_estimates``; ``shared/spec/interface.md``),
opened read-only, so the
report shows what an analyst querying the database would see. Optional extras: the
close-loop report (the dict ``run_close_loop`` returns) and, for a synthetic fleet, its truth
(the effect and anomalies the generator put in, to compare with what was found).

One function per picture, each taking its data and a path and returning the path
(matplotlib's Agg backend: no display needed):

* :func:`plot_event_predictions`: measured against predicted sensor temperature, for a few
  representative events per wagon (hottest, worst predicted, typical), every revision;
* :func:`plot_flag_timeline`: the flags on a timeline, one row per wagon, coloured by kind
  (and, with a truth, the injected anomalies beneath them);
* :func:`plot_close_loop_error`: the closed loop's RMSE before and after, fit and holdout;
* :func:`plot_contact_temperatures`: the peak predicted contact temperature of every event;
* :func:`plot_contact_estimates`: per flagged wagon, around its most severe flag, the virtual
  sensor's contact estimate with its 95 % band against the open-loop prediction and the
  reading, and the unexplained heat power with its band.

The tables give the peak contact temperature with its bounds: the virtual sensor's
(``v_contact_estimates``) beside the open-loop prediction's, per wagon and per braking.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import polars as pl

from fleetbrake.errors import DatabaseLockedError, FleetbrakeError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from fleetbrake.synth.generator import FleetTruth

__all__ = [
    "FLAG_COLORS",
    "ReportData",
    "ReportInputError",
    "ReportResult",
    "load_report_data",
    "plot_close_loop_error",
    "plot_contact_estimates",
    "plot_contact_temperatures",
    "plot_event_predictions",
    "plot_flag_timeline",
    "write_report",
]


class ReportInputError(FleetbrakeError):
    """The database (or a close-loop report given with it) cannot be read; names the file."""


class ReportLockedError(ReportInputError, DatabaseLockedError):
    """Another process is writing the database: DuckDB lets no other process open it."""


FLAG_COLORS: dict[str, str] = {
    "dragging_brake": "#d62728",
    "weak_brake": "#1f77b4",
    "sensor_fault": "#9467bd",
    "overheating": "#ff7f0e",
}
"""One colour per flag kind (``v_flags.kind``), the same in every picture."""

_SEVERITY_RANK = {"alarm": 0, "warning": 1, "info": 2}
ESTIMATE_WAGONS = 8
"""At most this many flagged wagons get a contact-estimate plot (the most severe flags first)."""
ESTIMATE_PAD = dt.timedelta(minutes=30)
"""A contact-estimate plot shows its flag with at least this much before and after."""
ESTIMATE_SPAN = dt.timedelta(hours=24)
"""... and at most this much in all."""
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


@dataclass
class ReportData:
    """What the report shows, read once from the views."""

    db_path: Path
    files: pl.DataFrame
    events: pl.DataFrame
    flags: pl.DataFrame
    revisions: pl.DataFrame
    event_stats: pl.DataFrame
    """Per event and revision: peaks of measured and predicted sensor, of the predicted
    contact mean and maximum, and the RMSE measured - predicted (K)."""
    current_revision: str | None
    samples_span: tuple[dt.datetime, dt.datetime] | None
    series: pl.DataFrame = field(default_factory=pl.DataFrame)
    """``v_predictions`` rows of the representative events (every revision)."""
    representative: dict[str, list[tuple[str, str]]] = field(default_factory=dict)
    """Per wagon: (event_id, why it was chosen)."""
    has_estimates: bool = False
    """The database has ``v_contact_estimates`` (a database of an older ``run`` has not)."""
    estimate_event_peaks: pl.DataFrame = field(default_factory=pl.DataFrame)
    """Per event and revision: the virtual sensor's peak contact mean with its bounds, and
    peak contact maximum with its upper bound, over the event's window."""
    estimate_wagon_peaks: pl.DataFrame = field(default_factory=pl.DataFrame)
    """Per wagon and revision: the same over every estimated second, and the extremes of the
    unexplained power with their bounds."""
    estimate_windows: dict[str, tuple[dt.datetime, dt.datetime, dict[str, Any]]] = field(
        default_factory=dict
    )
    """Per flagged wagon (at most :data:`ESTIMATE_WAGONS`): the window of its plot and the
    flag it is around."""
    estimate_series: dict[str, pl.DataFrame] = field(default_factory=dict)
    """Per wagon of ``estimate_windows``: the current revision's estimates in the window,
    with the open-loop predicted contact mean and the measured sensor temperature."""

    @property
    def wagons(self) -> list[str]:
        ids = set(self.events["wagon_id"].to_list()) | set(
            self.files.filter(pl.col("status") == "ingested")["wagon_id"].drop_nulls().to_list()
        )
        return sorted(ids)

    @property
    def revision_names(self) -> list[str]:
        return self.revisions["model_revision"].to_list()


def _query(con: Any, name: str, params: Mapping[str, Any] | None = None) -> pl.DataFrame:
    """The rows of the packaged query ``name`` (``warehouse/sql/<name>.sql``)."""
    from fleetbrake.warehouse.connection import sql

    return con.sql(sql(name), params=dict(params) if params else None).pl()


def load_report_data(db_path: str | Path, per_wagon: int = 3) -> ReportData:
    """Read the views of ``db_path`` (read-only) and pick ``per_wagon`` representative
    events per wagon: the hottest (predicted contact maximum), the worst predicted by the
    declared model (largest RMSE) and a typical one (median peak contact temperature)."""
    import duckdb

    db_path = Path(db_path)
    if not db_path.is_file():
        raise ReportInputError(f"{db_path}: no such database (run `fleetbrake run` first)")
    try:
        con = duckdb.connect(str(db_path), read_only=True)
    except duckdb.IOException as error:
        if "lock" in str(error).lower():
            raise ReportLockedError(
                f"{db_path}: cannot be read now: another process is writing to it; run again "
                "when it has finished"
            ) from None
        raise ReportInputError(f"{db_path}: cannot be opened ({error})") from None
    except duckdb.Error as error:
        raise ReportInputError(f"{db_path}: cannot be opened ({error})") from None
    try:
        files = _query(con, "q_report_files")
        events = _query(con, "q_report_events")
        flags = _query(con, "q_report_flags")
        revisions = _query(con, "q_report_revisions")
        event_stats = _query(con, "q_report_event_stats")
        span = _query(con, "q_report_events_span").row(0)
        current = revisions["model_revision"][-1] if revisions.height else None
        data = ReportData(
            db_path=db_path,
            files=files,
            events=events,
            flags=flags,
            revisions=revisions,
            event_stats=event_stats,
            current_revision=current,
            samples_span=(span[0], span[1]) if span[0] is not None else None,
        )
        data.representative = _representative_events(data, per_wagon)
        ids = [e for picks in data.representative.values() for e, _ in picks]
        if ids:
            data.series = _query(con, "q_report_series", {"event_ids": ids})
        if "v_contact_estimates" in set(_query(con, "q_report_relations")["view_name"]):
            _load_estimates(con, data)
    finally:
        con.close()
    return data


def _load_estimates(con: Any, data: ReportData) -> None:
    """The virtual sensor's peaks, and the series of the flagged wagons' plots."""
    data.has_estimates = True
    data.estimate_event_peaks = _query(con, "q_report_estimate_event_peaks")
    data.estimate_wagon_peaks = _query(con, "q_report_estimate_wagon_peaks")
    if data.current_revision is None:
        return
    data.estimate_windows = flag_windows(data.flags)
    for wagon_id, (start, end, _) in data.estimate_windows.items():
        series = _query(
            con,
            "q_report_estimate_series",
            {
                "wagon_id": wagon_id,
                "model_revision": data.current_revision,
                "from_utc": start,
                "to_utc": end,
            },
        )
        if series.height:
            data.estimate_series[wagon_id] = series


def flag_windows(
    flags: pl.DataFrame, limit: int = ESTIMATE_WAGONS
) -> dict[str, tuple[dt.datetime, dt.datetime, dict[str, Any]]]:
    """Per flagged wagon, its most severe flag (then the longest, then the first) and the
    window a plot of it shows: :data:`ESTIMATE_PAD` (or half the flag's length, if longer)
    before and after, at most :data:`ESTIMATE_SPAN` in all. The ``limit`` wagons whose flags
    are the most severe, in wagon order."""
    if flags.height == 0:
        return {}
    ranked = flags.with_columns(
        pl.col("severity").replace_strict(_SEVERITY_RANK, default=9).alias("_rank"),
        (pl.col("end_utc") - pl.col("start_utc")).alias("_length"),
    ).sort(["_rank", "_length", "start_utc", "flag_id"], descending=[False, True, False, False])
    chosen = ranked.unique("wagon_id", keep="first", maintain_order=True).head(limit)
    out: dict[str, tuple[dt.datetime, dt.datetime, dict[str, Any]]] = {}
    for f in chosen.sort("wagon_id").iter_rows(named=True):
        start, end = f["start_utc"], f["end_utc"]
        pad = max(ESTIMATE_PAD, (end - start) / 2)
        begin, finish = start - pad, end + pad
        if finish - begin > ESTIMATE_SPAN:
            begin, finish = start - ESTIMATE_PAD, start - ESTIMATE_PAD + ESTIMATE_SPAN
        flag = {k: v for k, v in f.items() if not k.startswith("_")}
        out[str(f["wagon_id"])] = (begin, finish, flag)
    return out


def _representative_events(data: ReportData, per_wagon: int) -> dict[str, list[tuple[str, str]]]:
    if data.event_stats.height == 0 or per_wagon <= 0:
        return {}
    first = data.revision_names[0] if data.revisions.height else None
    current = data.current_revision
    now = data.event_stats.filter(pl.col("model_revision") == (current or ""))
    base = data.event_stats.filter(pl.col("model_revision") == first)
    out: dict[str, list[tuple[str, str]]] = {}
    for wagon_id in sorted(set(now["wagon_id"].to_list())):
        mine = now.filter(pl.col("wagon_id") == wagon_id).drop_nulls("contact_max_c")
        if mine.height == 0:
            continue
        picks: list[tuple[str, str]] = []

        def add(event_id: str, why: str, picks: list[tuple[str, str]] = picks) -> None:
            if len(picks) < per_wagon and event_id not in {e for e, _ in picks}:
                picks.append((event_id, why))

        hottest = mine.sort("contact_max_c", descending=True)
        add(hottest["event_id"][0], "hottest")
        worst = (
            base.filter((pl.col("wagon_id") == wagon_id) & (pl.col("valid_s") > 0))
            .drop_nulls("rmse_k")
            .sort("rmse_k", descending=True)
        )
        if worst.height:
            add(worst["event_id"][0], f"largest error ({first})")
        ordered = mine.sort("contact_max_c")
        for k in (ordered.height // 2, ordered.height // 4, (3 * ordered.height) // 4):
            add(ordered["event_id"][k], "typical")
        out[wagon_id] = picks
    return out


# --------------------------------------------------------------------------------------------
# Pictures


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
    ``gap_s``, so that a line is not drawn across a data gap."""
    after_gap = pl.col("time_utc").diff().shift(-1) > dt.timedelta(seconds=gap_s)
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


@dataclass
class ReportResult:
    path: Path
    pictures: list[Path]


def _num(value: Any) -> float:
    return float("nan") if value is None else float(value)


def _fmt(value: Any, digits: int = 1, unit: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, dt.datetime):
        return value.strftime("%Y-%m-%d %H:%M:%S")
    if isinstance(value, float):
        return f"{value:.{digits}f}{unit}"
    return f"{value}{unit}"


def _cell(value: Any) -> str:
    return str(value).replace("|", "\\|").replace("\n", " ")


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    lines.append("")
    return lines


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


def effect_verdict(close_loop: Mapping[str, Any] | None, truth_effects: Sequence[str]) -> str:
    """One sentence: the effect the closed loop added against the one(s) the generator used."""
    found = (close_loop or {}).get("effect")
    found_names = set(found.split("+")) if found else set()
    truth_names = set(truth_effects)
    if not truth_names:
        return f"found {found or 'nothing'}; the data had no undeclared effect"
    said = " + ".join(sorted(truth_names))
    if found_names == truth_names:
        return f"**matched**: found {found}, the effect the generator used"
    if found_names & truth_names:
        return f"**partly matched**: found {found}, the generator used {said}"
    return f"**not matched**: found {found or 'nothing'}, the generator used {said}"


def _flag_matches(
    flags: pl.DataFrame, anomaly: Mapping[str, Any], slack: dt.timedelta
) -> pl.DataFrame:
    return flags.filter(
        (pl.col("wagon_id") == anomaly["wagon_id"])
        & (pl.col("kind") == anomaly["kind"])
        & (pl.col("start_utc") <= anomaly["end_utc"] + slack)
        & (pl.col("end_utc") >= anomaly["start_utc"] - slack)
    )


def write_report(
    db_path: str | Path,
    out_dir: str | Path,
    *,
    close_loop: Mapping[str, Any] | None = None,
    truth: FleetTruth | None = None,
    artefacts: Sequence[tuple[str, str | Path]] = (),
    name: str = "report.md",
    title: str = "fleetbrake fleet report",
    notes: Sequence[str] = (),
) -> ReportResult:
    """Write ``out_dir/name`` (Markdown) and its pictures (``out_dir/report-*.png``) from the
    views of ``db_path``. ``artefacts``: (what, path) pairs listed at the end; ``notes``:
    sentences put under the title (how the data was made, timings, ...)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = load_report_data(db_path)
    stem = Path(name).stem
    pictures: list[Path] = []
    anomalies = _truth_anomalies(truth)
    lines = [f"# {title}", ""]
    lines += [f"Database `{data.db_path}`" + _span_text(data) + ".", ""]
    for note in notes:
        lines += [note, ""]

    # ---- overview
    ingested = data.files.filter(pl.col("status") == "ingested")
    quarantined = data.files.filter(pl.col("status") == "quarantined")
    lines += ["## Overview", ""]
    overview = [
        ("wagons with data", len(data.wagons)),
        ("log files ingested", f"{ingested.height} ({int(ingested['rows'].sum() or 0):,} rows)"),
        ("log files quarantined", quarantined.height),
        ("braking events", data.events.height),
        ("flags", _flag_counts_text(data.flags)),
        ("model revisions", ", ".join(f"`{r}`" for r in data.revision_names) or "-"),
    ]
    lines += _table(["", ""], overview)

    # ---- closed loop
    if close_loop is not None:
        lines += ["## Closed loop", ""]
        if close_loop.get("new_revision"):
            params = ", ".join(f"{k} = {v:.3g}" for k, v in close_loop["parameters"].items())
            lines.append(
                f"The model lacked **{close_loop['effect']}** ({params}); it was added as "
                f"revision `{close_loop['new_revision']}` on top of "
                f"`{close_loop['baseline_revision']}`."
            )
        else:
            lines.append("No significant effect is missing: nothing was added.")
        if truth is not None:
            lines += [
                "",
                f"Against the truth (the generator's `{truth.effects}`): "
                f"{effect_verdict(close_loop, truth.effects.names)}.",
            ]
        lines += ["", f"Evidence: {close_loop.get('evidence', '-')}.", ""]
        if truth is not None and truth.effects:
            lines += _parameters_table(close_loop, truth)
        rows = []
        for key in ("fit", "holdout"):
            part = close_loop.get(key, {})
            rows.append(
                (
                    key,
                    part.get("events", 0),
                    _fmt(part.get("rmse_before_k"), 3),
                    _fmt(part.get("rmse_after_k"), 3),
                )
            )
        lines += _table(["events", "count", "RMSE before (K)", "RMSE after (K)"], rows)
        png = plot_close_loop_error(close_loop, out_dir / f"{stem}-close-loop.png")
        pictures.append(png)
        lines += [f"![closed-loop error]({png.name})", ""]

    # ---- measured vs predicted
    lines += ["## Measured against predicted sensor temperature", ""]
    if data.representative:
        png = plot_event_predictions(
            data.series,
            data.representative,
            data.revision_names,
            out_dir / f"{stem}-predictions.png",
        )
        pictures.append(png)
        lines += [
            "Representative events of each wagon: the hottest, the one the first revision "
            "predicted worst, and a typical one; black dots are the thermistor's readings.",
            "",
            f"![measured against predicted]({png.name})",
            "",
        ]
        lines += _error_by_wagon_table(data)
    else:
        lines += ["No predictions in the database.", ""]

    # ---- flags
    lines += ["## Flags", ""]
    png = plot_flag_timeline(
        data.flags,
        data.events,
        data.wagons,
        out_dir / f"{stem}-flags.png",
        truth_anomalies=anomalies,
    )
    pictures.append(png)
    lines += [f"![flags per wagon]({png.name})", ""]
    if data.flags.height:
        ordered = data.flags.with_columns(
            pl.col("severity").replace_strict(_SEVERITY_RANK, default=9).alias("_rank")
        ).sort("_rank", "wagon_id", "start_utc")
        lines += _table(
            ["wagon", "kind", "severity", "from", "to", "event", "evidence"],
            [
                (
                    f["wagon_id"],
                    f["kind"],
                    f["severity"],
                    _fmt(f["start_utc"]),
                    _fmt(f["end_utc"]),
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

    # ---- the virtual sensor
    lines += ["## Contact temperature: the virtual sensor", ""]
    lines += _estimates_section(data, out_dir / f"{stem}-estimates.png", pictures)

    # ---- events
    lines += ["## Events per wagon", ""]
    lines += _events_table(data)
    lines += ["## Hottest contact temperatures", ""]
    if data.event_stats.height:
        png = plot_contact_temperatures(
            data.event_stats, data.current_revision, out_dir / f"{stem}-contact.png"
        )
        pictures.append(png)
        lines += [f"![peak contact temperatures]({png.name})", ""]
    lines += _hottest_table(data)

    # ---- files
    if quarantined.height:
        lines += ["## Quarantined files", ""]
        lines += _table(
            ["file", "reason"],
            [
                (f["path"], (f["reason"] or "-").removeprefix(f"{f['path']}: "))
                for f in quarantined.iter_rows(named=True)
            ],
        )
    if artefacts:
        lines += ["## Written", ""]
        lines += [f"- {what}: `{path}`" for what, path in artefacts] + [""]
    path = out_dir / name
    path.write_text("\n".join(lines), encoding="utf-8")
    return ReportResult(path=path, pictures=pictures)


def _parameters_table(close_loop: Mapping[str, Any], truth: FleetTruth) -> list[str]:
    """Each true effect's parameters against the fitted ones (when the effect was found)."""
    found = {e["name"]: e.get("parameters", {}) for e in close_loop.get("effects", [])}
    rows = []
    for effect in truth.effects:
        fitted = found.get(effect.name, {})
        for key, value in effect.parameters.items():
            got = fitted.get(key)
            rows.append(
                (
                    effect.name,
                    key,
                    f"{value:.4g}",
                    "-" if got is None else f"{got:.4g}",
                    "-" if got is None or not value else f"{100 * (got - value) / value:+.1f} %",
                )
            )
    return _table(["effect", "parameter", "truth", "fitted", "difference"], rows)


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
        rows.append((wagon_id, *(_fmt(lookup.get(r), 3) for r in revisions)))
    header = ["wagon", *(f"`{r}`" for r in revisions)]
    return [
        "RMSE measured - predicted sensor temperature per wagon (K):",
        "",
        *_table(header, rows),
    ]


def _bounded(value: Any, lo: Any, hi: Any, digits: int = 1) -> str:
    """A value with its 95 % bounds: ``412.3 (398.1 to 426.5)``; ``-`` without a value."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{_fmt(value, digits)} ({_fmt(lo, digits)} to {_fmt(hi, digits)})"


def _upper(value: Any, hi: Any, digits: int = 1) -> str:
    """A value with its 95 % upper bound: ``430.2 (≤ 441.0)``."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{_fmt(value, digits)} (≤ {_fmt(hi, digits)})"


def _current(frame: pl.DataFrame, data: ReportData) -> pl.DataFrame:
    """The rows of the current revision (none without one)."""
    if frame.height == 0:
        return frame
    return frame.filter(pl.col("model_revision") == (data.current_revision or ""))


def _estimates_section(data: ReportData, png: Path, pictures: list[Path]) -> list[str]:
    """The virtual sensor: the flagged wagons' plot, and per wagon its peak contact
    temperatures with their bounds and the extremes of the unexplained power."""
    if not data.has_estimates:
        return [
            "The database has no contact estimates (no `v_contact_estimates`: it was written "
            "by an older `run`).",
            "",
        ]
    peaks = _current(data.estimate_wagon_peaks, data)
    if peaks.height == 0:
        return [f"No contact estimates of revision `{data.current_revision}` yet.", ""]
    lines = [
        "The virtual sensor estimates the wheel-block contact (friction-face) temperature at "
        "every logged second from the model and the thermistor together, with its 95 % band, "
        "and the heat power on the friction face that the declared inputs do not explain "
        "(a dragging brake heats with the cylinder released; a weak brake heats less than "
        f"declared). Revision `{data.current_revision}`, filtered (live) estimate.",
        "",
    ]
    if data.estimate_series:
        plot_contact_estimates(data.estimate_series, data.estimate_windows, png)
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
            _bounded(r["est_mean_peak_c"], r["est_mean_peak_lo_c"], r["est_mean_peak_hi_c"]),
            _fmt(r["est_mean_peak_utc"]),
            _upper(r["est_max_peak_c"], r["est_max_peak_hi_c"]),
            _bounded(r["power_max_w"], r["power_max_lo_w"], r["power_max_hi_w"], 0),
            _bounded(r["power_min_w"], r["power_min_lo_w"], r["power_min_hi_w"], 0),
            flagged_counts.get(r["wagon_id"], 0),
        )
        for r in peaks.sort("wagon_id").iter_rows(named=True)
    ]
    lines += [
        "Per wagon, the hottest second of the estimate (95 % bounds in brackets) and the "
        "extremes of the unexplained power:",
        "",
        *_table(
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
    return lines


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
        r["wagon_id"]: _upper(r["est_max_peak_c"], r["est_max_peak_hi_c"])
        for r in _current(data.estimate_wagon_peaks, data).iter_rows(named=True)
    }
    rows = [
        (
            r["wagon_id"],
            r["events"],
            r["days"],
            _fmt(r["braking_min"], 0),
            _fmt(r["p_mean_bar"], 2),
            _fmt(r["measured_max_c"]),
            _fmt(r["contact_max_c"]),
            estimated.get(r["wagon_id"], "-"),
            nflags.get(r["wagon_id"], 0),
        )
        for r in summary.iter_rows(named=True)
    ]
    return _table(
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
    estimated = _current(data.estimate_event_peaks, data)
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
            _fmt(r["start_utc"]),
            _fmt(r["duration_s"], 0),
            f"{_fmt(r['v_start_kmh'], 0)} → {_fmt(r['v_end_kmh'], 0)}",
            _fmt(r["p_mean_bar"], 2),
            _fmt(r["contact_max_c"]),
            _fmt(r["contact_mean_max_c"]),
            _upper(r["est_max_peak_c"], r["est_max_peak_hi_c"]),
            _bounded(r["est_mean_peak_c"], r["est_mean_peak_lo_c"], r["est_mean_peak_hi_c"]),
            _fmt(r["measured_max_c"]),
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
        *_table(
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
                _fmt(a["start_utc"]),
                _fmt(a["end_utc"]),
                ", ".join(f"{s}" for s in hits["severity"].to_list()) or "**missed**",
            )
        )
    found = sum(1 for r in rows if r[-1] != "**missed**")
    intro = (
        f"Injected by the generator (truth): {found} of {len(rows)} found by a flag of the "
        "same kind overlapping it (15 min slack)."
    )
    return [intro, "", *_table(["wagon", "anomaly", "from", "to", "flagged"], rows)]
