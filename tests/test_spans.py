"""Spans as the unit of work: a wagon's log cut at gaps longer than 6 h; a second run computes
no span; a late file inside a span recomputes that span alone (the other spans' rows and
ledger rows untouched); a file bridging two spans merges them (their old results removed, one
span stored); a new day's file computes the new day's span alone."""

from __future__ import annotations

import datetime as dt
import itertools
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import duckdb
import pytest

from fleetbrake.app.run import run_fleet
from fleetbrake.engine import InlineEngine
from fleetbrake.simulation.config import SimulationConfig

WAGON = "SGG-0001"

LATE = "SGG-0001_20240304T051551Z.csv"
"""Inside the first span (05:15-07:24, between files ending 02:03 and starting 07:24)."""
BRIDGE = ("SGG-0001_20240305T044050Z.csv.gz", "SGG-0001_20240305T065948Z.csv")
"""04:40-09:08 on the 5th: less than 6 h after the second span (ending 23:02 on the 4th)
and before the third (starting 13:19): the two become one."""
NEW_DAY = (
    "SGG-0001_20240306T081043Z.csv",
    "SGG-0001_20240306T093916Z.csv",
    "SGG-0001_20240306T151900Z.csv",
)
"""08:10-18:12 on the 6th, 11.5 h after the third span: a span of its own."""
LEFT_OUT = (
    "SGG-0001_20240304T152432Z.csv.gz",
    "SGG-0001_20240304T175723Z.csv.gz",
    "SGG-0001_20240306T015756Z.csv",
)
"""Never landing: they make the gaps of more than 6 h."""

RESULT_TABLES = {
    "predictions": "time_utc",
    "timeline": "time_utc",
    "contact_estimates": "time_utc",
    "flags": "start_utc",
}
LEDGERS = ("simulated_spans", "estimated_spans", "flagged_spans")


@pytest.fixture(scope="module")
def source(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_cache_dir: Path,
) -> Iterator[Path]:
    """One wagon x 3 days with the anomalies (the other wagons' logs removed)."""
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    root = tmp_path_factory.mktemp("spans") / "fleet"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        generate_fleet(root, SynthConfig(wagons=2, days=3, seed=4), rom=reduced_model_for)
    for folder in (root / "logs").iterdir():
        if folder.name != WAGON:
            shutil.rmtree(folder)
    yield root


def _run(fleet: Path, db: Path, refinement: float, cache: Path) -> Any:
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(cache))
        return run_fleet(
            fleet,
            db,
            simulation=SimulationConfig(refinement=refinement),
            progress=False,
            engine=InlineEngine(),
        )


def _query(db: Path, text: str, params: dict[str, object] | None = None) -> list[tuple[Any, ...]]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.execute(text, params or {}).fetchall()
    finally:
        con.close()


def _spans(db: Path) -> list[tuple[dt.datetime, dt.datetime]]:
    return [
        (a, b)
        for a, b in _query(
            db,
            "SELECT span_start_utc, span_end_utc FROM spans WHERE wagon_id = $w ORDER BY 1",
            {"w": WAGON},
        )
    ]


def _rows_in(db: Path, span: tuple[dt.datetime, dt.datetime]) -> dict[str, list[tuple[Any, ...]]]:
    """Every row of the result tables in the span's time range, and its ledger rows (with
    when they were written)."""
    out = {}
    for table, column in RESULT_TABLES.items():
        out[table] = _query(
            db,
            f"SELECT * FROM {table} WHERE wagon_id = $w AND {column} BETWEEN $a AND $b "
            "ORDER BY ALL",
            {"w": WAGON, "a": span[0], "b": span[1]},
        )
    for table in LEDGERS:
        out[table] = _query(
            db,
            f"SELECT * FROM {table} WHERE wagon_id = $w AND span_start_utc = $a ORDER BY ALL",
            {"w": WAGON, "a": span[0]},
        )
    return out


def _keys(spans: list[tuple[str, dt.datetime, dt.datetime]]) -> list[dt.datetime]:
    assert {w for w, _, _ in spans} <= {WAGON}
    return sorted(a for _, a, _ in spans)


@pytest.mark.slow
def test_spans_are_the_unit_of_simulation_estimate_and_flags(
    source: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    fleet = tmp_path / "fleet"
    shutil.copytree(source, fleet)
    logs = fleet / "logs" / WAGON
    held = tmp_path / "held"
    held.mkdir()
    for name in (LATE, *BRIDGE, *NEW_DAY):
        (logs / name).rename(held / name)
    for name in LEFT_OUT:
        (logs / name).unlink()
    db = tmp_path / "fleet.duckdb"

    first = _run(fleet, db, rom_refinement, rom_cache_dir)
    spans = _spans(db)
    assert len(spans) == 3  # cut at the two gaps longer than 6 h
    assert all((b[0] - a[1]).total_seconds() > 6 * 3600 for a, b in itertools.pairwise(spans))
    assert _keys(first.simulation.spans_simulated) == [a for a, _ in spans]
    assert _keys(first.estimated_spans) == [a for a, _ in spans]
    before = {span: _rows_in(db, span) for span in spans}
    assert all(before[s]["timeline"] and before[s]["contact_estimates"] for s in spans)
    assert all(len(before[s][t]) == 1 for s in spans for t in LEDGERS)

    again = _run(fleet, db, rom_refinement, rom_cache_dir)  # nothing new: no span computed
    assert again.simulation.spans_simulated == []
    assert again.estimated_spans == []
    assert again.flags.wagons == []
    assert {span: _rows_in(db, span) for span in spans} == before

    (held / LATE).rename(logs / LATE)  # a late file inside the first span
    late = _run(fleet, db, rom_refinement, rom_cache_dir)
    after = _spans(db)
    assert len(after) == 3 and after[0][0] == spans[0][0] and after[1:] == spans[1:]
    assert _keys(late.simulation.spans_simulated) == [spans[0][0]]
    assert _keys(late.estimated_spans) == [spans[0][0]]
    rows = _rows_in(db, after[0])
    assert rows["timeline"] != before[spans[0]]["timeline"]  # its rows recomputed
    for span in spans[1:]:  # the others' rows and ledger rows (written_utc too) untouched
        assert _rows_in(db, span) == before[span]

    for name in BRIDGE:  # files landing between the second and the third span
        (held / name).rename(logs / name)
    bridged = _run(fleet, db, rom_refinement, rom_cache_dir)
    merged = _spans(db)
    assert len(merged) == 2 and merged[0] == after[0]
    assert merged[1] == (spans[1][0], spans[2][1])  # one span from the second's start
    assert _keys(bridged.simulation.spans_simulated) == [spans[1][0]]
    assert _keys(bridged.estimated_spans) == [spans[1][0]]
    for table in LEDGERS:  # the third span's ledger rows gone, one row for the merged span
        starts = _query(db, f"SELECT span_start_utc, span_end_utc FROM {table} ORDER BY 1")
        assert starts == merged, table
    seconds = _query(
        db,
        "SELECT count(DISTINCT time_utc) FROM samples WHERE wagon_id = $w "
        "AND time_utc BETWEEN $a AND $b",
        {"w": WAGON, "a": merged[1][0], "b": merged[1][1]},
    )[0][0]
    for table in ("timeline", "contact_estimates"):  # every second once: old rows removed
        count, distinct = _query(
            db,
            f"SELECT count(*), count(DISTINCT time_utc) FROM {table} WHERE wagon_id = $w "
            "AND time_utc BETWEEN $a AND $b",
            {"w": WAGON, "a": merged[1][0], "b": merged[1][1]},
        )[0]
        assert count == distinct == seconds, table
    first_span = _rows_in(db, merged[0])
    assert first_span == rows  # the first span: untouched by the merge

    for name in NEW_DAY:  # a new day: its own span, computed alone
        (held / name).rename(logs / name)
    day = _run(fleet, db, rom_refinement, rom_cache_dir)
    final = _spans(db)
    assert len(final) == 3 and final[:2] == merged
    assert _keys(day.simulation.spans_simulated) == [final[2][0]]
    assert _keys(day.estimated_spans) == [final[2][0]]
    assert _rows_in(db, merged[0]) == first_span

    fresh = tmp_path / "fresh.duckdb"  # the same files in one run: the same results
    _run(fleet, fresh, rom_refinement, rom_cache_dir)
    for span in final:
        ours, theirs = _rows_in(db, span), _rows_in(fresh, span)
        for table in ("predictions", "timeline", "contact_estimates"):
            assert ours[table] == theirs[table], (span, table)


def test_a_spans_estimates_replace_an_older_closed_loop_revisions(tmp_path: Path) -> None:
    """The stage's writes by span keep what ``replace_estimates`` keeps: storing a newer
    revision's estimates of a wagon's span deletes the wagon's estimates of older closed-loop
    revisions (``declared`` and the current one stay); writing a span again replaces its rows,
    at every resolution, and its ledger row."""
    from fleetbrake.ingest.spans import Span
    from fleetbrake.model.estimator import EstimatorNoise
    from fleetbrake.simulation.estimates import EstimateResult, replace_span_estimates
    from fleetbrake.warehouse.connection import open_warehouse
    from test_estimates_retention import WAGONS, _record_revision, _rows, stored

    def results(revision: str, wagons: tuple[str, ...] = WAGONS) -> list[EstimateResult]:
        out = []
        for w in wagons:
            rows = _rows(w, revision)
            times = rows.column("time_utc").to_pylist()
            span = Span(w, times[0], times[-1], rows.num_rows, "data")
            noise = EstimatorNoise()
            out.append(EstimateResult(w, revision, "data", "model", rows, 0.0, noise, span))
        return out

    with open_warehouse(tmp_path / "fleet.duckdb") as wh:
        _record_revision(wh, "declared", None)
        replace_span_estimates(wh, "declared", results("declared"))
        _record_revision(wh, "r1-a", "declared")
        replace_span_estimates(wh, "r1-a", results("r1-a"))
        _record_revision(wh, "r2-b", "r1-a")
        replace_span_estimates(wh, "r2-b", results("r2-b", WAGONS[:1]))
        assert set(stored(wh)) == {
            (WAGONS[0], "declared"),
            (WAGONS[0], "r2-b"),
            (WAGONS[1], "declared"),
            (WAGONS[1], "r1-a"),  # not estimated with r2-b yet: kept until it is
        }
        replace_span_estimates(wh, "declared", results("declared"))  # again: replaced
        assert stored(wh)[(WAGONS[0], "declared")] == 30
        ((ledger,),) = wh.con.execute(
            "SELECT count(*) FROM estimated_spans WHERE model_revision = 'declared'"
        ).fetchall()
        assert ledger == len(WAGONS)
