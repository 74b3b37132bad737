"""What the report shows, read once from a warehouse's public views (opened read-only), and
the choices made on it: the representative events per wagon, the flagged wagons' windows of
the virtual sensor's plot."""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import polars as pl

from fleetbrake.errors import DatabaseLockedError, FleetbrakeError

__all__ = [
    "ESTIMATE_PAD",
    "ESTIMATE_SPAN",
    "ESTIMATE_WAGONS",
    "SEVERITY_RANK",
    "ReportData",
    "ReportInputError",
    "ReportLockedError",
    "flag_windows",
    "load_report_data",
]


class ReportInputError(FleetbrakeError):
    """The database (or a close-loop report given with it) cannot be read; names the file."""


class ReportLockedError(ReportInputError, DatabaseLockedError):
    """Another process is writing the database: DuckDB lets no other process open it."""


SEVERITY_RANK = {"alarm": 0, "warning": 1, "info": 2}
ESTIMATE_WAGONS = 8
"""At most this many flagged wagons get a contact-estimate plot (the most severe flags first)."""
ESTIMATE_PAD = dt.timedelta(minutes=30)
"""A contact-estimate plot shows its flag with at least this much before and after."""
ESTIMATE_SPAN = dt.timedelta(hours=24)
"""... and at most this much in all."""
"""Flag severities, the most severe first."""


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
    """The database has ``v_contact_estimates`` of interface v3 (a database of an older
    ``run`` has none, or one without ``resolution_s`` until a ``run`` migrates it)."""
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

    def current_rows(self, frame: pl.DataFrame) -> pl.DataFrame:
        """The rows of ``frame`` of the current revision (none without one)."""
        if frame.height == 0:
            return frame
        return frame.filter(pl.col("model_revision") == (self.current_revision or ""))


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
        if (
            "v_contact_estimates" in set(_query(con, "q_report_relations")["view_name"])
            and (_query(con, "q_estimates_view_current")["current"][0])
        ):
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
        pl.col("severity").replace_strict(SEVERITY_RANK, default=9).alias("_rank"),
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
