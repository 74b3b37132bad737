"""Every SQL block of ``docs/analyst-queries.md`` runs on a warehouse made from a generated
fleet and gives a sensible answer, so that the documented queries can never rot.

The fixture: 2 wagons x 2 days with anomalies (the second wagon carries them), through
``run_fleet`` (ingestion, events, simulation with the declared model, flags). Each query
must run, name every column, and give values in physical ranges; the known ones are also
checked against the same answer computed here from the views with polars.
"""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import duckdb
import polars as pl
import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "analyst-queries.md"

KNOWN = {
    "Hottest contact temperatures of the week",
    "Wagons with open flags",
    "Error by wagon and model revision",
    "Events per day and wagon",
    "Effect history",
    "Quarantined files",
    "Measured and predicted around the worst-predicted braking",
}
"""Sections that must stay on the page (each has its own checks below)."""

MAY_BE_EMPTY = {"Wagons with open flags", "Quarantined files"}
"""Answers that depend on the data (checked against polars instead)."""

SEVERITIES = {"info", "warning", "alarm"}
FLAG_KINDS = {"dragging_brake", "weak_brake", "sensor_fault", "overheating"}


def doc_queries(path: Path = DOC) -> dict[str, str]:
    """``{section title: SQL}``: each fenced ``sql`` block with the ``##`` heading above it
    (one block per section)."""
    queries: dict[str, str] = {}
    title = None
    for match in re.finditer(
        r"^## (?P<title>.+?)\s*$|^```sql\n(?P<sql>.*?)^```", path.read_text(), re.M | re.S
    ):
        if match["title"]:
            title = match["title"]
        else:
            assert title is not None, "an SQL block before any ## heading"
            assert title not in queries, f"section {title!r} has two SQL blocks"
            queries[title] = match["sql"]
    return queries


def run_query(db: Path, sql: str) -> pl.DataFrame:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.sql(sql).pl()
    finally:
        con.close()


def views(db: Path, *names: str) -> list[pl.DataFrame]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return [con.sql(f"SELECT * FROM {name}").pl() for name in names]
    finally:
        con.close()


# --------------------------------------------------------------------------------------------
# The warehouse


@pytest.fixture(scope="session")
def fleet_db(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_refinement: float,
    rom_cache_dir: Path,
) -> Iterator[Path]:
    """2 wagons x 2 days with anomalies, through ``run_fleet``."""
    from fleetbrake.app.run import run_fleet
    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    out = tmp_path_factory.mktemp("analyst")
    with pytest.MonkeyPatch.context() as mp:
        # every step (the flags' watch simulation too) uses the session's reduced model
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        config = SynthConfig(wagons=2, days=2, seed=3, anomalies=True)
        generate_fleet(out / "fleet", config, rom=reduced_model_for)
        run_fleet(
            out / "fleet",
            out / "fleet.duckdb",
            simulation=SimulationConfig(refinement=rom_refinement),
            progress=False,
        )
    yield out / "fleet.duckdb"


@pytest.fixture(scope="session")
def answers(fleet_db: Path) -> dict[str, pl.DataFrame]:
    return {title: run_query(fleet_db, sql) for title, sql in doc_queries().items()}


# --------------------------------------------------------------------------------------------
# The page


def test_page_has_the_queries() -> None:
    queries = doc_queries()
    missing = KNOWN - set(queries)
    assert not missing, f"sections gone from {DOC.name}: {sorted(missing)}"
    for title, sql in queries.items():
        assert sql.strip().endswith(";"), f"{title}: end the query with ';'"


# --------------------------------------------------------------------------------------------
# Every query: runs, names its columns, physical values


def check_generic(title: str, frame: pl.DataFrame) -> None:
    if title not in MAY_BE_EMPTY:
        assert frame.height > 0, f"{title}: no rows"
    for name in frame.columns:
        assert re.fullmatch(r"[a-z][a-z0-9_]*", name), f"{title}: column {name!r} is unnamed"
    assert len(set(frame.columns)) == len(frame.columns), f"{title}: duplicate columns"
    for name in frame.columns:
        values = frame[name].drop_nulls()
        if values.len() == 0 or not values.dtype.is_numeric():
            continue
        low, high = float(values.min()), float(values.max())
        if name.endswith("_c"):  # a temperature of the block, its sensor or the contact
            assert -40.0 <= low and high <= 1000.0, f"{title}: {name} in [{low}, {high}]"
        elif name.startswith("rmse") and name.endswith("_k"):
            assert 0.0 <= low and high < 100.0, f"{title}: {name} in [{low}, {high}]"
        elif name.endswith("_bar"):
            assert 0.0 <= low and high <= 6.0, f"{title}: {name} in [{low}, {high}]"
        elif name.endswith("_kmh"):
            assert 0.0 <= low and high <= 160.0, f"{title}: {name} in [{low}, {high}]"
        elif name in ("events", "seconds", "files", "open_flags", "duration_s", "braking_min"):
            assert low >= 0, f"{title}: {name} negative"


@pytest.mark.parametrize("title", sorted(KNOWN))
def test_query_runs_and_is_sensible(title: str, answers: dict[str, pl.DataFrame]) -> None:
    check_generic(title, answers[title])


def test_every_block_runs(answers: dict[str, pl.DataFrame]) -> None:
    """Blocks added to the page later are held to the generic checks at least."""
    for title, frame in answers.items():
        check_generic(title, frame)


# --------------------------------------------------------------------------------------------
# The known ones, against polars on the views


def test_hottest_contact(fleet_db: Path, answers: dict[str, pl.DataFrame]) -> None:
    got = answers["Hottest contact temperatures of the week"]
    predictions, events = views(fleet_db, "v_predictions", "v_events")
    # one row per wagon with events (the data spans less than a week)
    assert sorted(got["wagon_id"].to_list()) == sorted(set(events["wagon_id"].to_list()))
    assert got["contact_max_c"].to_list() == sorted(got["contact_max_c"].to_list(), reverse=True)
    peaks = predictions.group_by("wagon_id", "event_id").agg(
        pl.col("predicted_contact_max_c").max()
    )
    for row in got.iter_rows(named=True):
        mine = peaks.filter(pl.col("wagon_id") == row["wagon_id"])
        assert row["contact_max_c"] == pytest.approx(
            mine["predicted_contact_max_c"].max(), abs=0.05
        )
        assert row["event_id"] in mine["event_id"].to_list()
        # the contact is hotter than the thermistor seated inside the block
        assert row["contact_max_c"] >= row["sensor_max_c"] - 5.0
        assert row["contact_max_c"] > 20.0


def test_open_flags(fleet_db: Path, answers: dict[str, pl.DataFrame]) -> None:
    got = answers["Wagons with open flags"]
    flags, events, predictions = views(fleet_db, "v_flags", "v_events", "v_predictions")
    end = max(events["end_utc"].max(), predictions["time_utc"].max())
    open_flags = flags.filter(pl.col("end_utc") >= end - dt.timedelta(days=1))
    assert flags.height > 0, "the anomalies of the fixture raised no flag"
    assert got["open_flags"].sum() == open_flags.height
    assert set(got["severity"].to_list()) <= SEVERITIES
    for kinds in got["kinds"].to_list():
        assert set(kinds.split(", ")) <= FLAG_KINDS
    rank = {"alarm": 0, "warning": 1, "info": 2}
    order = [rank[s] for s in got["severity"].to_list()]
    assert order == sorted(order), "alarms first"
    for row in got.iter_rows(named=True):
        assert row["since_utc"] <= row["last_seen_utc"]
        assert row["latest_evidence"], "every flag carries evidence"


def test_error_by_wagon(fleet_db: Path, answers: dict[str, pl.DataFrame]) -> None:
    got = answers["Error by wagon and model revision"]
    (predictions,) = views(fleet_db, "v_predictions")
    assert set(got["model_revision"].to_list()) == set(predictions["model_revision"].to_list())
    valid = predictions.drop_nulls("measured_sensor_c")
    for row in got.iter_rows(named=True):
        mine = valid.filter(
            (pl.col("wagon_id") == row["wagon_id"])
            & (pl.col("model_revision") == row["model_revision"])
        )
        r = mine["measured_sensor_c"] - mine["predicted_sensor_c"]
        assert row["seconds"] == mine.height
        assert row["rmse_k"] == pytest.approx(float((r**2).mean() ** 0.5), abs=1e-3)
        assert abs(row["bias_k"]) <= row["rmse_k"] + 1e-3
        assert row["rmse_k"] > 0.0  # the thermistor is noisy: never a perfect fit


def test_events_per_day(fleet_db: Path, answers: dict[str, pl.DataFrame]) -> None:
    got = answers["Events per day and wagon"]
    (events,) = views(fleet_db, "v_events")
    assert got["events"].sum() == events.height
    assert got.select("wagon_id", "day").is_unique().all()
    assert set(got["day"].to_list()) <= {dt.date(2024, 3, 4), dt.date(2024, 3, 5)}
    for row in got.iter_rows(named=True):
        assert 0 < row["events"] < 200  # a day of a freight wagon
        assert row["braking_min"] <= 24 * 60


def test_effect_history(answers: dict[str, pl.DataFrame]) -> None:
    check_effect_history(answers["Effect history"])


def check_effect_history(got: pl.DataFrame) -> None:
    """The declared model first, then each revision the closed loop added on its parent."""
    first = got.row(0, named=True)
    assert first["model_revision"] == "declared"
    assert first["parent_revision"] is None
    assert first["effect"] == "(declared model)"
    assert first["effects_json"] == "[]"
    names = got["model_revision"].to_list()
    for row in list(got.iter_rows(named=True))[1:]:  # revisions the closed loop added
        assert row["parent_revision"] in names[: names.index(row["model_revision"])]
        assert row["effect"] != "(declared model)"
        assert row["effects_json"].startswith("[{")


def test_quarantined_files(fleet_db: Path, answers: dict[str, pl.DataFrame]) -> None:
    got = answers["Quarantined files"]
    (files,) = views(fleet_db, "v_files")
    quarantined = files.filter(pl.col("status") == "quarantined")
    assert quarantined.height > 0, "the generator always writes a few bad files"
    assert got["files"].sum() == quarantined.height
    for reason in got["first_reason"].to_list():
        assert reason and not reason.startswith("logs/"), reason


def test_worst_event_series(fleet_db: Path, answers: dict[str, pl.DataFrame]) -> None:
    got = answers["Measured and predicted around the worst-predicted braking"]
    assert got["event_id"].n_unique() == 1
    assert got["t_s"][0] == 0 and got["t_s"].is_sorted()
    assert got.height >= 60  # at least a braking and some of its cooling
    (events,) = views(fleet_db, "v_events")
    event = events.filter(pl.col("event_id") == got["event_id"][0])
    assert event.height == 1
    assert got["time_utc"][0] == event["start_utc"][0]
