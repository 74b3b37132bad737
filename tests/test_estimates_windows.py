"""The storage of the contact estimates (interface v3): per second inside the estimate windows
(events, flags, significant unexplained power, each widened by 60 s and rounded to whole
minutes), per minute elsewhere, with the minute's means, extremes and root mean squares."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from fleetbrake.warehouse.connection import Warehouse, open_warehouse
from fleetbrake.warehouse.estimate_windows import compact_estimates

WAGON = "WW-0001"
OTHER = "WW-0002"  # not compacted
T0 = dt.datetime(2024, 3, 1, 10, 0, 17)  # not on a minute
N_S = 3 * 3600
EVENT = (dt.datetime(2024, 3, 1, 10, 30, 10), dt.datetime(2024, 3, 1, 10, 40, 5))
FLAG = (dt.datetime(2024, 3, 1, 11, 20, 30), dt.datetime(2024, 3, 1, 11, 21, 0))
POWER = (dt.datetime(2024, 3, 1, 12, 5, 0), dt.datetime(2024, 3, 1, 12, 5, 20))
COLUMNS = [
    "contact_mean_c",
    "contact_mean_lo_c",
    "contact_mean_hi_c",
    "contact_max_c",
    "contact_max_hi_c",
    "smoothed_contact_mean_c",
    "smoothed_contact_mean_lo_c",
    "smoothed_contact_mean_hi_c",
    "unexplained_power_w",
    "unexplained_power_lo_w",
    "unexplained_power_hi_w",
    "innovation_k",
    "innovation_sd_k",
    "smoothed_contact_max_c",
    "smoothed_contact_max_hi_c",
    "smoothed_unexplained_power_w",
    "smoothed_unexplained_power_lo_w",
    "smoothed_unexplained_power_hi_w",
]


def _estimates(wagon_id: str, revision: str, seed: int) -> pl.DataFrame:
    """A row per second of :data:`N_S` from :data:`T0`: random values, the power's band
    excluding zero during :data:`POWER` only, readings missing one second in seven."""
    rng = np.random.default_rng(seed)
    times = [T0 + dt.timedelta(seconds=k) for k in range(N_S)]
    mean = 40.0 + np.cumsum(rng.normal(0.0, 0.1, N_S))
    power = rng.normal(0.0, 20.0, N_S)
    significant = np.array([POWER[0] <= t <= POWER[1] for t in times])
    power = np.where(significant, 800.0, power)
    innovation = rng.normal(0.0, 0.3, N_S)
    return pl.DataFrame(
        {
            "wagon_id": wagon_id,
            "time_utc": times,
            "model_revision": revision,
            "contact_mean_c": mean,
            "contact_mean_lo_c": mean - rng.uniform(1, 3, N_S),
            "contact_mean_hi_c": mean + rng.uniform(1, 3, N_S),
            "contact_max_c": mean + rng.uniform(5, 9, N_S),
            "contact_max_hi_c": mean + rng.uniform(10, 12, N_S),
            "smoothed_contact_mean_c": mean + 0.5,
            "smoothed_contact_mean_lo_c": mean - rng.uniform(0.5, 1, N_S),
            "smoothed_contact_mean_hi_c": mean + rng.uniform(0.5, 1, N_S),
            "unexplained_power_w": power,
            "unexplained_power_lo_w": power - 100.0,
            "unexplained_power_hi_w": power + 100.0,
            "innovation_k": pl.Series(
                np.where(np.arange(N_S) % 7 == 3, np.nan, innovation)
            ).fill_nan(None),
            "innovation_sd_k": rng.uniform(0.1, 0.2, N_S),
            "smoothed_contact_max_c": mean + rng.uniform(5, 9, N_S),
            "smoothed_contact_max_hi_c": mean + rng.uniform(10, 12, N_S),
            "smoothed_unexplained_power_w": power * 0.9,
            "smoothed_unexplained_power_lo_w": power * 0.9 - 80.0,
            "smoothed_unexplained_power_hi_w": power * 0.9 + 80.0,
            "resolution_s": 1,
        },
        schema_overrides={"time_utc": pl.Datetime("us"), "resolution_s": pl.Int32()},
    )


def fill_warehouse(wh: Warehouse, estimates: pl.DataFrame) -> None:
    """``estimates`` stored, with an event of :data:`WAGON` predicted over :data:`EVENT`
    (revision declared) and a flag over :data:`FLAG`."""
    event_s = int((EVENT[1] - EVENT[0]).total_seconds()) + 1
    predictions = pl.DataFrame(
        {
            "event_id": f"{WAGON}-E1",
            "wagon_id": WAGON,
            "time_utc": [EVENT[0] + dt.timedelta(seconds=k) for k in range(event_s)],
            "model_revision": "declared",
            "phase": "heating",
            "measured_sensor_c": 30.0,
            "predicted_sensor_c": 31.0,
            "predicted_contact_mean_c": 50.0,
            "predicted_contact_max_c": 60.0,
            "speed_kmh": 50.0,
            "brake_pressure_bar": 2.0,
            "ambient_c": 10.0,
            "flux_w_m2": 1.0e4,
        },
        schema_overrides={"time_utc": pl.Datetime("us")},
    )
    with wh.transaction() as con:
        con.register("new_estimates", estimates.to_arrow())
        con.execute("INSERT INTO contact_estimates BY NAME SELECT * FROM new_estimates")
        con.register("new_predictions", predictions.to_arrow())
        con.execute("INSERT INTO predictions BY NAME SELECT * FROM new_predictions")
        con.execute(
            "INSERT INTO flags VALUES ('F1', $w, NULL, 'sensor_fault', 'warning', $a, $b, "
            "'a test flag', $a)",
            {"w": WAGON, "a": FLAG[0], "b": FLAG[1]},
        )


def _minute(t: dt.datetime) -> dt.datetime:
    return t.replace(second=0, microsecond=0)


def kept_minutes() -> set[dt.datetime]:
    """The minutes of the estimate windows of :data:`WAGON`, computed here: each window
    widened by 60 s, every minute it touches."""
    kept = set()
    for a, b in (EVENT, FLAG, POWER):
        m = _minute(a - dt.timedelta(seconds=60))
        while m <= b + dt.timedelta(seconds=60):
            kept.add(m)
            m += dt.timedelta(minutes=1)
    return kept


@pytest.fixture
def warehouse(tmp_path: Path) -> Iterator[Warehouse]:
    with open_warehouse(tmp_path / "fleet.duckdb") as wh:
        _fill(wh)
        yield wh


def _fill(wh: Warehouse) -> None:
    fill_warehouse(
        wh,
        pl.concat(
            [
                _estimates(WAGON, "declared", 1),
                _estimates(WAGON, "r1-other", 2),
                _estimates(OTHER, "declared", 3),
            ]
        ),
    )


def _rows(wh: Warehouse, wagon_id: str, revision: str) -> pl.DataFrame:
    return wh.con.sql(
        "SELECT * FROM contact_estimates WHERE wagon_id = $w AND model_revision = $r "
        "ORDER BY time_utc, resolution_s",
        params={"w": wagon_id, "r": revision},
    ).pl()


def test_minutes_outside_the_windows_hold_their_seconds_aggregates(warehouse: Warehouse) -> None:
    wh = warehouse
    before = _rows(wh, WAGON, "declared")
    done = compact_estimates(wh.con, [(WAGON, T0, T0 + dt.timedelta(seconds=N_S - 1))], "declared")
    after = _rows(wh, WAGON, "declared")

    kept = kept_minutes()
    by_minute = before.with_columns(minute=pl.col("time_utc").dt.truncate("1m"))
    minutes = by_minute["minute"].unique().sort().to_list()
    compacted = [m for m in minutes if m not in kept]
    seconds_kept = by_minute.filter(pl.col("minute").is_in(sorted(kept)))
    assert done.minutes == len(compacted)
    assert done.seconds_removed == before.height - seconds_kept.height
    assert after.height == seconds_kept.height + len(compacted)
    # per second inside the windows, unchanged
    per_second = after.filter(pl.col("resolution_s") == 1)
    assert per_second.drop("resolution_s").equals(seconds_kept.drop("minute", "resolution_s"))
    # one row per other minute, at its start (the first, partial minute included)
    per_minute = after.filter(pl.col("resolution_s") == 60)
    assert per_minute["time_utc"].to_list() == compacted
    assert _minute(T0) in compacted
    expected = (
        by_minute.filter(pl.col("minute").is_in(compacted))
        .group_by("minute")
        .agg(
            *(pl.col(c).mean() for c in COLUMNS if c.endswith(("mean_c", "power_w"))),
            *(pl.col(c).max() for c in COLUMNS if "_hi_" in c or c.endswith("max_c")),
            *(pl.col(c).min() for c in COLUMNS if "_lo_" in c),
            *((pl.col(c) ** 2).mean().sqrt().alias(c) for c in ("innovation_k", "innovation_sd_k")),
        )
        .sort("minute")
    )
    assert sorted(expected.columns) == sorted(["minute", *COLUMNS])
    for column in COLUMNS:
        np.testing.assert_allclose(
            per_minute[column].to_numpy(), expected[column].to_numpy(), rtol=1e-12, err_msg=column
        )
    # the other revision and the other wagon are left as they were
    assert _rows(wh, WAGON, "r1-other")["resolution_s"].unique().to_list() == [1]
    assert _rows(wh, OTHER, "declared").height == N_S


def test_compacting_again_changes_nothing(warehouse: Warehouse) -> None:
    wh = warehouse
    whole = [(WAGON, None, None)]
    first = compact_estimates(wh.con, whole, "declared")
    assert first.minutes > 0
    once = _rows(wh, WAGON, "declared")
    again = compact_estimates(wh.con, whole, "declared")
    assert (again.minutes, again.seconds_removed) == (0, 0)
    assert _rows(wh, WAGON, "declared").equals(once)


def test_only_the_ranges_given_are_compacted(warehouse: Warehouse) -> None:
    """A range ending inside a minute takes the whole minute; the rows after stay per second;
    compacting the rest afterwards gives what compacting the whole gives."""
    wh = warehouse
    cut = dt.datetime(2024, 3, 1, 11, 0, 30)
    compact_estimates(wh.con, [(WAGON, None, cut)], "declared")
    rows = _rows(wh, WAGON, "declared")
    per_minute = rows.filter(pl.col("resolution_s") == 60)["time_utc"]
    assert per_minute.max() == _minute(cut)
    assert rows.filter(pl.col("time_utc") > _minute(cut))["resolution_s"].unique().to_list() == [1]
    compact_estimates(wh.con, [(WAGON, cut + dt.timedelta(seconds=1), None)], "declared")
    split = _rows(wh, WAGON, "declared")
    compact_estimates(wh.con, [(OTHER, None, None)], "declared")
    assert _rows(wh, OTHER, "declared").height < N_S
    assert set(split.filter(pl.col("resolution_s") == 1)["time_utc"].dt.truncate("1m")) == (
        kept_minutes()
    )


def test_view_shows_the_resolution(warehouse: Warehouse) -> None:
    wh = warehouse
    compact_estimates(wh.con, [(WAGON, None, None)], "declared")
    counts = dict(
        wh.con.sql(
            "SELECT resolution_s, count(*) FROM v_contact_estimates "
            "WHERE wagon_id = $w AND model_revision = 'declared' GROUP BY 1",
            params={"w": WAGON},
        ).fetchall()
    )
    assert set(counts) == {1, 60}
    columns = [r[0] for r in wh.con.sql("DESCRIBE v_contact_estimates").fetchall()]
    assert columns[:5] == [
        "wagon_id",
        "time_utc",
        "model_revision",
        "resolution_s",
        "contact_mean_c",
    ]


def test_the_reports_lines_run_through_minute_rows_and_break_at_gaps() -> None:
    """The report's plot of a wagon's estimates draws one line through seconds and the minute
    rows beside them, and breaks it where the data has a gap."""
    from fleetbrake.app.report.plots import _with_breaks

    seconds = [T0 + dt.timedelta(seconds=k) for k in range(120)]
    minutes = [_minute(seconds[-1]) + dt.timedelta(minutes=k) for k in range(1, 5)]
    later = [minutes[-1] + dt.timedelta(hours=2, seconds=k) for k in range(10)]
    frame = pl.DataFrame(
        {
            "time_utc": seconds + minutes + later,
            "resolution_s": [1] * 120 + [60] * 4 + [1] * 10,
            "contact_mean_c": 1.0,
        }
    )
    broken = _with_breaks(frame)
    gaps = broken.filter(pl.col("contact_mean_c").is_null())["time_utc"].to_list()
    assert gaps == [minutes[-1] + dt.timedelta(seconds=1)]
    assert (
        _with_breaks(frame.drop("resolution_s")).filter(pl.col("contact_mean_c").is_null()).height
        == 5
    )  # per-second rows only: every minute step is a gap
