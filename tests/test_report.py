"""``fleetbrake report``: the virtual sensor's contact estimate in the report (a plot per flagged
wagon, the peak contact temperatures with their bounds in the tables), on the small warehouse
of ``tests/test_record.py``."""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path

import duckdb
import polars as pl
import pytest

from fleetbrake.app.report import flag_windows, load_report_data, write_report
from test_record import E1, E1_END, E1_START, T0, WAGON, build_fleet_db


@pytest.fixture(scope="module")
def fleet_db(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    return build_fleet_db(tmp_path_factory.mktemp("report") / "fleet.duckdb")


def _row(markdown: str, first_cell: str, after: str) -> str:
    """The table row beginning with ``first_cell`` after the line containing ``after``."""
    text = markdown[markdown.index(after) :]
    return next(line for line in text.splitlines() if line.startswith(f"| {first_cell} |"))


def test_report_shows_the_estimate_with_its_band(
    fleet_db: dict[str, object], tmp_path: Path
) -> None:
    result = write_report(fleet_db["db"], tmp_path)  # type: ignore[arg-type]
    text = result.path.read_text(encoding="utf-8")
    assert "## Contact temperature: the virtual sensor" in text
    png = tmp_path / "report-estimates.png"
    assert png in result.pictures and png.stat().st_size > 10_000
    assert f"![contact estimates]({png.name})" in text

    estimates: pl.DataFrame = fleet_db["estimates_frame"]  # type: ignore[assignment]
    mine = estimates.filter(pl.col("wagon_id") == WAGON)
    hottest = mine.row(int(mine["contact_mean_c"].arg_max()), named=True)  # type: ignore[arg-type]
    band = (
        f"{hottest['contact_mean_c']:.1f} ({hottest['contact_mean_lo_c']:.1f} to "
        f"{hottest['contact_mean_hi_c']:.1f})"
    )
    row = _row(text, WAGON, "## Contact temperature: the virtual sensor")
    assert band in row
    assert f"{hottest['time_utc']:%Y-%m-%d %H:%M:%S}" in row
    hottest_max = mine.row(int(mine["contact_max_c"].arg_max()), named=True)  # type: ignore[arg-type]
    assert f"{hottest_max['contact_max_c']:.1f} (≤ {hottest_max['contact_max_hi_c']:.1f})" in row
    assert "500 (450 to 550)" in row and "0 (-50 to 50)" in row  # the drag, and no weak brake

    # the events table: the wagon's hottest estimated contact maximum beside the predicted one
    events_row = _row(text, WAGON, "## Events per wagon")
    assert f"(≤ {hottest_max['contact_max_hi_c']:.1f})" in events_row

    # the hottest brakings: the estimate's peak over E1's window (its predicted seconds)
    window = mine.filter(pl.col("time_utc") >= E1_START)
    window = window.filter(pl.col("time_utc") <= fleet_db["p1"]["time_utc"].max())  # type: ignore[index]
    peak = window.row(int(window["contact_mean_c"].arg_max()), named=True)  # type: ignore[arg-type]
    e1_row = _row(text, E1, "hottest brakings")
    assert f"{peak['contact_mean_c']:.1f} ({peak['contact_mean_lo_c']:.1f} to" in e1_row


def test_the_plot_is_around_the_most_severe_flag(fleet_db: dict[str, object]) -> None:
    data = load_report_data(fleet_db["db"])  # type: ignore[arg-type]
    ((wagon, (start, end, flag)),) = data.estimate_windows.items()
    assert wagon == WAGON and flag["flag_id"] == "F1"  # the alarm, not the warning
    assert start == T0 + dt.timedelta(seconds=150) - dt.timedelta(minutes=30)
    assert end == T0 + dt.timedelta(seconds=210) + dt.timedelta(minutes=30)
    series = data.estimate_series[WAGON]
    assert series["time_utc"].min() >= start and series["time_utc"].max() <= end
    # the open-loop prediction and the reading beside the estimate, where E1's rows are
    inside = series.filter(pl.col("time_utc").is_between(E1_START, E1_END))
    assert inside["predicted_contact_mean_c"].null_count() == 0
    assert series.filter(pl.col("time_utc") < E1_START)["predicted_contact_mean_c"].null_count() > 0

    long = pl.DataFrame(
        {
            "flag_id": ["A", "B"],
            "wagon_id": ["W", "W"],
            "severity": ["warning", "warning"],
            "start_utc": [T0, T0 + dt.timedelta(hours=1)],
            "end_utc": [T0 + dt.timedelta(hours=40), T0 + dt.timedelta(hours=2)],
        }
    )
    ((a, b, f),) = flag_windows(long).values()
    assert f["flag_id"] == "A" and b - a == dt.timedelta(hours=24)  # the longest, capped


def test_a_database_without_estimates_says_so(fleet_db: dict[str, object], tmp_path: Path) -> None:
    db = tmp_path / "old.duckdb"
    shutil.copy(fleet_db["db"], db)  # type: ignore[arg-type]
    con = duckdb.connect(str(db))
    con.execute("DROP VIEW v_contact_estimates")
    con.close()
    result = write_report(db, tmp_path / "out")
    text = result.path.read_text(encoding="utf-8")
    assert "has no contact estimates" in text
    assert not (tmp_path / "out" / "report-estimates.png").exists()
    assert "## Hottest contact temperatures" in text  # the rest of the report as before
