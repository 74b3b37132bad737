"""Ingestion by partition: through the local engine's worker processes the tables are the
same as inline, a second run adds nothing, a late file changes only its wagon."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from fleetbrake.engine import InlineEngine, LocalEngine
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import run_ingest
from fleetbrake.synth import corrupt
from fleetgen import T0_UTC, simple_session, snapshot, write_registry, write_session

WALL_CLOCK = ("ingested_utc", "detected_utc", "applied_utc")
WAGONS = ["SGG-0001", "SGG-0002", "SGG-0003"]
CONFIG = IngestConfig(partition_files=3, batch_rows=1_500)
"""Several partitions per wagon, most committed on their own (a partition holds more rows)."""


@pytest.fixture(scope="module")
def local() -> Iterator[LocalEngine]:
    with LocalEngine(2) as engine:
        yield engine


def _fleet(root: Path) -> Path:
    """Three wagons with 7, 4 and 1 files (duplicates, out of order rows), a file of a wagon
    not in the registry, a junk file and a misplaced one."""
    write_registry(root, WAGONS)
    rng = np.random.default_rng(3)
    for w, (wagon, files) in enumerate(zip(WAGONS, (7, 4, 1), strict=True)):
        for k in range(files):
            start = T0_UTC + dt.timedelta(days=1, hours=3 * k + w)
            frame = corrupt.swap_neighbours(
                corrupt.duplicate_rows(simple_session(start, rows=600, seed=10 * w + k), rng, 0.01),
                rng,
                0.01,
            )
            write_session(root, wagon, frame, start, gzip=bool(k % 2))
    write_session(root, "SGG-0404", simple_session(T0_UTC, rows=300), T0_UTC)
    (root / "logs" / "SGG-0001" / "SGG-0001_20240302T230000Z.csv.gz").write_bytes(b"junk")
    (root / "logs" / "SGG-0002" / "SGG-0001_20240303T000000Z.csv").write_bytes(b"x")
    return root


def _wagon_rows(tables: dict[str, list[tuple]], db: Path, wagon: str) -> dict[str, list[tuple]]:
    """Every table's rows minus those of ``wagon`` (tables with a wagon_id column)."""
    import duckdb

    con = duckdb.connect(str(db), read_only=True)
    try:
        out = {}
        for table, rows in tables.items():
            columns = [
                r[0]
                for r in con.execute(
                    "SELECT column_name FROM information_schema.columns WHERE table_name = $t "
                    "ORDER BY ordinal_position",
                    {"t": table},
                ).fetchall()
            ]
            if "wagon_id" in columns:
                at = columns.index("wagon_id")
                out[table] = [row for row in rows if row[at] != wagon]
        return out
    finally:
        con.close()


def test_local_engine_gives_the_tables_of_inline_ingestion(
    tmp_path: Path, local: LocalEngine
) -> None:
    fleet = _fleet(tmp_path / "fleet")
    inline_db, local_db = tmp_path / "inline.duckdb", tmp_path / "local.duckdb"
    inline = run_ingest(fleet, inline_db, config=CONFIG, progress=False, engine=InlineEngine())
    through = run_ingest(fleet, local_db, config=CONFIG, progress=False, engine=local)
    assert len(inline.ingested) == 12 and len(inline.quarantined) == 3
    assert through.results == inline.results  # same files, same order, same outcomes
    tables = snapshot(local_db, ignore=WALL_CLOCK)
    assert tables["events"] and len(tables["files"]) == 15
    assert tables == snapshot(inline_db, ignore=WALL_CLOCK)  # file ids included


def test_second_run_through_the_local_engine_adds_nothing(
    tmp_path: Path, local: LocalEngine
) -> None:
    fleet = _fleet(tmp_path / "fleet")
    db = tmp_path / "fleet.duckdb"
    run_ingest(fleet, db, config=CONFIG, progress=False, engine=local)
    before = snapshot(db)
    again = run_ingest(fleet, db, config=CONFIG, progress=False, engine=local)
    assert again.results == [] and again.files_unchanged == 15
    assert again.events is not None and again.events.added == again.events.removed == 0
    assert snapshot(db) == before


def test_a_late_file_changes_only_its_wagon(tmp_path: Path, local: LocalEngine) -> None:
    fleet = _fleet(tmp_path / "fleet")
    db = tmp_path / "fleet.duckdb"
    run_ingest(fleet, db, config=CONFIG, progress=False, engine=local)
    before = snapshot(db)
    late = write_session(fleet, "SGG-0002", simple_session(T0_UTC, rows=400, seed=77), T0_UTC)
    report = run_ingest(fleet, db, config=CONFIG, progress=False, engine=local)
    assert [(r.path, r.status) for r in report.results] == [
        (late.relative_to(fleet).as_posix(), "ingested")
    ]
    after = snapshot(db)
    assert after != before
    assert _wagon_rows(after, db, "SGG-0002") == _wagon_rows(before, db, "SGG-0002")
    assert len(after["samples"]) == len(before["samples"]) + 400


def test_a_partition_is_committed_whole_in_one_transaction(
    tmp_path: Path, local: LocalEngine, monkeypatch: pytest.MonkeyPatch
) -> None:
    import fleetbrake.ingest.ledger as ledger

    batches: list[list[str]] = []
    insert = ledger._insert

    def recording(con: object, name: str, frame: pl.DataFrame, statement: str) -> None:
        if name == "file_batch":
            batches.append(frame["path"].to_list())
        insert(con, name, frame, statement)  # type: ignore[arg-type]

    monkeypatch.setattr(ledger, "_insert", recording)
    fleet = _fleet(tmp_path / "fleet")
    config = IngestConfig(partition_files=3, batch_rows=1)
    run_ingest(fleet, tmp_path / "fleet.duckdb", config=config, progress=False, engine=local)
    expected: list[list[str]] = []
    for directory in sorted((fleet / "logs").iterdir()):
        paths = sorted(p.relative_to(fleet).as_posix() for p in directory.iterdir())
        expected += [paths[i : i + 3] for i in range(0, len(paths), 3)]
    assert batches == expected  # a wagon's 7 files: 3 + 3 + 1, each in its own transaction
