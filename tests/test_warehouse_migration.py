"""A warehouse of schema version 2 opened for writing becomes version 3: every row of its
files, events, predictions and flags kept, its contact estimates given ``resolution_s``,
compacted as :func:`compact_estimates` compacts them (per second inside the estimate windows,
per minute elsewhere) and kept for `declared` and the current revision only; an interrupted
migration is completed by the next open."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import duckdb
import polars as pl
import pytest

from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.files import run_ingest
from fleetbrake.warehouse import migration
from fleetbrake.warehouse.connection import SCHEMA_VERSION, open_warehouse
from fleetbrake.warehouse.estimate_windows import compact_estimates
from fleetgen import T0_UTC, simple_session, write_registry, write_session
from test_estimates_windows import OTHER, WAGON, _estimates, fill_warehouse

VIEWS = {
    "v_files": "SELECT * EXCLUDE (ingested_utc) FROM v_files",
    "v_events": "SELECT * FROM v_events",
    "v_predictions": "SELECT * FROM v_predictions",
    "v_flags": "SELECT * FROM v_flags",
}
ESTIMATES = "SELECT * FROM contact_estimates ORDER BY model_revision, wagon_id, time_utc"
KEPT = ("declared", "r2-current")


def _revisions(con: duckdb.DuckDBPyConnection) -> None:
    for name, parent, current in (
        ("declared", None, False),
        ("r1-older", "declared", False),
        ("r2-current", "r1-older", True),
    ):
        con.execute(
            "INSERT INTO model_revisions VALUES ($n, $p, NULL, '{}', NULL, NULL, 'rom', $c, "
            "now(), NULL)",
            {"n": name, "p": parent, "c": current},
        )


@pytest.fixture
def version_2(tmp_path: Path) -> dict[str, Path]:
    """A warehouse as schema version 2 left it (an ingested file, its events, predictions, a
    flag, contact estimates per second of three revisions of two wagons), and the same
    estimates compacted by version 3 (``reference``)."""
    fleet = tmp_path / "fleet"
    write_registry(fleet, ["SGG-0001"])
    write_session(fleet, "SGG-0001", simple_session(rows=900), T0_UTC)
    db = tmp_path / "v2" / "fleet.duckdb"
    run_ingest(fleet, db, config=IngestConfig(), progress=False)
    estimates = pl.concat(
        [
            _estimates(w, r, seed)
            for seed, (w, r) in enumerate(
                (w, r) for w in (WAGON, OTHER) for r in ("declared", "r1-older", "r2-current")
            )
        ]
    )
    with open_warehouse(db) as wh:
        fill_warehouse(wh, estimates)
        _revisions(wh.con)
    reference = tmp_path / "reference.duckdb"
    shutil.copy(db, reference)
    with open_warehouse(reference) as wh:
        wh.con.execute("DELETE FROM contact_estimates WHERE model_revision = 'r1-older'")
        for revision in KEPT:
            compact_estimates(wh.con, [(WAGON, None, None), (OTHER, None, None)], revision)
    con = duckdb.connect(str(db))
    try:  # the schema of version 2: no resolution_s
        con.execute("DROP VIEW v_contact_estimates")
        con.execute("ALTER TABLE contact_estimates DROP COLUMN resolution_s")
        con.execute("CREATE VIEW v_contact_estimates AS SELECT * FROM contact_estimates")
        con.execute("DELETE FROM schema_version")
        con.execute("INSERT INTO schema_version VALUES (2, now())")
    finally:
        con.close()
    return {"db": db, "reference": reference}


def _read(db: Path) -> dict[str, list[tuple[object, ...]]]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        out = {name: sorted(con.execute(q).fetchall(), key=repr) for name, q in VIEWS.items()}
        if "resolution_s" in [r[0] for r in con.execute("DESCRIBE contact_estimates").fetchall()]:
            out["estimates"] = con.execute(ESTIMATES).fetchall()
        out["version"] = con.execute("SELECT max(version) FROM schema_version").fetchall()
        return out
    finally:
        con.close()


def test_a_version_2_warehouse_is_migrated_its_rows_kept(
    version_2: dict[str, Path], caplog: pytest.LogCaptureFixture
) -> None:
    before = _read(version_2["db"])
    assert before["version"] == [(2,)] and len(before["v_predictions"]) > 0
    assert len(before["v_events"]) > 0 and len(before["v_files"]) == 1
    with caplog.at_level(logging.INFO, logger="fleetbrake.warehouse.migration"):
        with open_warehouse(version_2["db"]):
            pass
    after = _read(version_2["db"])
    reference = _read(version_2["reference"])
    for name in VIEWS:
        assert after[name] == before[name], name
    assert after["version"] == [(SCHEMA_VERSION,)] == [(3,)]
    assert after["estimates"] == reference["estimates"]
    con = duckdb.connect(str(version_2["db"]), read_only=True)
    try:
        counts = dict(
            con.execute(
                "SELECT model_revision || ':' || resolution_s, count(*) FROM v_contact_estimates "
                "GROUP BY 1"
            ).fetchall()
        )
        nullable, default = con.execute(
            "SELECT is_nullable, column_default FROM information_schema.columns "
            "WHERE table_name = 'contact_estimates' AND column_name = 'resolution_s'"
        ).fetchone()
    finally:
        con.close()
    assert set(counts) == {f"{r}:{s}" for r in KEPT for s in (1, 60)}
    assert (nullable, default) == ("NO", None)
    progress = [r.getMessage() for r in caplog.records if "wagon revisions compacted" in r.message]
    assert progress and progress[-1].split(": ")[2].startswith("4 of 4 wagon revisions")


def test_an_interrupted_migration_is_completed_by_the_next_open(
    version_2: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = []
    compact = migration.compact_estimates

    def stopping(*args: object, **kwargs: object) -> object:
        if calls:
            raise KeyboardInterrupt  # the process stopped after one step
        calls.append(args)
        return compact(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(migration, "compact_estimates", stopping)
    monkeypatch.setattr(migration, "WAGONS_PER_STEP", 1)
    with pytest.raises(KeyboardInterrupt):
        open_warehouse(version_2["db"])
    assert _read(version_2["db"])["version"] == [(2,)]
    monkeypatch.undo()
    with open_warehouse(version_2["db"]):
        pass
    after, reference = _read(version_2["db"]), _read(version_2["reference"])
    assert after["version"] == [(3,)]
    assert after["estimates"] == reference["estimates"]


def test_a_version_2_warehouse_read_only_is_recorded_and_reported_without_its_estimates(
    version_2: dict[str, Path], tmp_path: Path
) -> None:
    """`record` and `report` only read: a version 2 warehouse is not migrated by them, and
    they say its estimates are of an older fleetbrake instead of failing on them."""
    from fleetbrake.app.report import write_report
    from fleetbrake.viz.record import record

    summary = record(version_2["db"], "SGG-0001", tmp_path / "wagon.rrd")
    assert any("schema version 2" in note for note in summary.notes), summary.notes
    text = write_report(version_2["db"], tmp_path / "report").path.read_text(encoding="utf-8")
    assert "without `resolution_s`" in text
    assert _read(version_2["db"])["version"] == [(2,)]
