"""``fleetbrake run`` through the local engine's worker processes gives the tables of a run
in one process; a second run adds nothing; a late file changes only its wagon; the flags of
a run are judged only for the wagons whose flags are out of date."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from fleetbrake.app.run import run_fleet
from fleetbrake.engine import InlineEngine, LocalEngine
from fleetbrake.simulation.config import SimulationConfig
from fleetgen import snapshot

WALL_CLOCK = (
    "ingested_utc",
    "detected_utc",
    "applied_utc",
    "created_utc",
    "simulated_utc",
    "updated_utc",
    "data_key",
)
"""Columns that say when a row was written (``spans.data_key`` hashes the events'
``detected_utc``): the only ones allowed to differ between two runs."""


@pytest.fixture(scope="module")
def fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_cache_dir: Path,
) -> Iterator[Path]:
    """3 wagons x 1 day with the anomalies; the session's reduced models, in the workers
    too (they inherit ``FLEETBRAKE_CACHE_DIR``)."""
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    root = tmp_path_factory.mktemp("run-engine") / "fleet"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        generate_fleet(root, SynthConfig(wagons=3, days=1, seed=4), rom=reduced_model_for)
        yield root


def _run(
    fleet: Path,
    db: Path,
    engine: object,
    refinement: float,
    cache: Path,
    flag_config_path: Path | None = None,
) -> Any:
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(cache))
        return run_fleet(
            fleet,
            db,
            simulation=SimulationConfig(refinement=refinement),
            progress=False,
            engine=engine,  # type: ignore[arg-type]
            flag_config_path=flag_config_path,
        )


def _flag_tables(db: Path) -> dict[str, list[tuple[object, ...]]]:
    """Every column of ``flags`` and ``flagged_spans``, sorted: when each wagon was judged
    and each flag detected included."""
    import duckdb

    con = duckdb.connect(str(db), read_only=True)
    try:
        return {
            table: sorted(con.execute(f"SELECT * FROM {table}").fetchall(), key=repr)
            for table in ("flags", "flagged_spans")
        }
    finally:
        con.close()


def _flags(db: Path) -> list[tuple[object, ...]]:
    """The flags as judged (``detected_utc`` left out: when, not what)."""
    import duckdb

    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.execute(
            "SELECT flag_id, wagon_id, event_id, kind, severity, start_utc, end_utc, evidence "
            "FROM flags ORDER BY flag_id"
        ).fetchall()
    finally:
        con.close()


def test_local_engine_run_equals_inline_run_and_a_second_run_adds_nothing(
    fleet: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    inline_db, local_db = tmp_path / "inline.duckdb", tmp_path / "local.duckdb"
    _run(fleet, inline_db, InlineEngine(), rom_refinement, rom_cache_dir)
    with LocalEngine(2) as engine:
        report = _run(fleet, local_db, engine, rom_refinement, rom_cache_dir)
        assert report.simulation.events_simulated > 0  # type: ignore[attr-defined]
        tables = snapshot(local_db, ignore=WALL_CLOCK)
        assert tables == snapshot(inline_db, ignore=WALL_CLOCK)
        before = snapshot(local_db, ignore=("updated_utc",))  # the registry, stored every run
        again = _run(fleet, local_db, engine, rom_refinement, rom_cache_dir)
    assert again.ingest.results == []  # type: ignore[attr-defined]
    assert again.simulation.events_simulated == 0  # type: ignore[attr-defined]
    assert snapshot(local_db, ignore=("updated_utc",)) == before


def test_a_late_file_through_the_local_engine_changes_only_its_wagon(
    fleet: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    import shutil

    import duckdb

    copy = tmp_path / "fleet"
    shutil.copytree(fleet, copy)
    logs = sorted((copy / "logs").glob("*/*.csv*"))
    late = logs[0]  # the first file of the first wagon: held back, then landing late
    held = tmp_path / late.name
    late.rename(held)
    db = tmp_path / "fleet.duckdb"
    wagon = late.parent.name
    with LocalEngine(2) as engine:
        first = _run(copy, db, engine, rom_refinement, rom_cache_dir)
        before = snapshot(db, ignore=("updated_utc",))
        judged_before = _flag_tables(db)
        held.rename(late)
        report = _run(copy, db, engine, rom_refinement, rom_cache_dir)
        fresh_db = tmp_path / "fresh.duckdb"
        _run(copy, fresh_db, engine, rom_refinement, rom_cache_dir)
    assert [r.path for r in report.ingest.results] == [late.relative_to(copy).as_posix()]
    # the late file's wagon alone judged again; the others' flags and judgements untouched
    # (when they were judged included), and the flags those of a fresh run over all files
    assert len(first.flags.wagons) > 1 and report.flags.wagons == [wagon]
    judged_after = _flag_tables(db)
    for other in sorted(set(first.flags.wagons) - {wagon}):
        assert _flag_tables_of(judged_after, other) == _flag_tables_of(judged_before, other)
    assert _flags(db) == _flags(fresh_db) and _flags(db)
    after = snapshot(db, ignore=("updated_utc",))
    con = duckdb.connect(str(db), read_only=True)
    try:
        for table, rows in after.items():
            columns = [
                r[0]
                for r in con.execute(
                    "SELECT column_name FROM information_schema.columns WHERE table_name = $t "
                    "ORDER BY ordinal_position",
                    {"t": table},
                ).fetchall()
                if r[0] != "updated_utc"
            ]
            if "wagon_id" not in columns:
                continue
            at = columns.index("wagon_id")
            others_after = [row for row in rows if row[at] != wagon]
            others_before = [row for row in before[table] if row[at] != wagon]
            assert others_after == others_before, f"{table}: another wagon's rows changed"
    finally:
        con.close()
    assert len(after["samples"]) > len(before["samples"])


def test_a_unit_of_files_judges_its_wagons_and_the_stale_ones_only(
    fleet: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    """``run_fleet(files=...)`` (a unit of ``fleetbrake watch``) judges the flags of the
    wagons its files changed, plus any wagon whose flags are older than its timeline (a unit
    stopped before its flags), and leaves the others' flags as they were; the flags equal
    those of a whole run."""
    import shutil

    import duckdb

    copy = tmp_path / "fleet"
    shutil.copytree(fleet, copy)
    by_wagon = sorted((copy / "logs").glob("*/*.csv*"))
    late = by_wagon[0]
    held = tmp_path / late.name
    late.rename(held)
    db, whole_db = tmp_path / "fleet.duckdb", tmp_path / "whole.duckdb"
    wagon = late.parent.name

    with InlineEngine() as engine:
        _run(copy, db, engine, rom_refinement, rom_cache_dir)
        con = duckdb.connect(str(db))
        try:  # another wagon's flags judged before its timeline was written: stale
            other = con.execute(
                "SELECT min(wagon_id) FROM flagged_spans WHERE wagon_id <> $w", {"w": wagon}
            ).fetchall()[0][0]
            con.execute(
                "UPDATE flagged_spans SET updated_utc = TIMESTAMP '2000-01-01' WHERE wagon_id = $w",
                {"w": other},
            )
        finally:
            con.close()
        held.rename(late)
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
            unit = run_fleet(
                copy,
                db,
                simulation=SimulationConfig(refinement=rom_refinement),
                progress=False,
                engine=engine,
                files=[late.relative_to(copy).as_posix()],
            )
            again = run_fleet(
                copy,
                db,
                simulation=SimulationConfig(refinement=rom_refinement),
                progress=False,
                engine=engine,
                files=[],
            )
        _run(copy, whole_db, engine, rom_refinement, rom_cache_dir)
    assert unit.flags is not None and again.flags is not None
    assert unit.flags.wagons == sorted({wagon, other})
    assert again.flags.wagons == []  # nothing changed, nothing stale
    assert _flags(db) == _flags(whole_db) and _flags(db)


def test_large_arrow_tables_cross_to_the_workers_as_mapped_files_and_leave_nothing() -> None:
    """The local engine ships a large Arrow table (a partition's data, a result's rows) as an
    Arrow IPC file in its own directory, read back mapped and removed at once: the table
    arrives equal, no file is left, and the directory goes with the engine."""
    from operator import methodcaller

    import numpy as np
    import pyarrow as pa

    from fleetbrake.engine import local

    n = 200_000  # 8 bytes x 2 columns x n > SHIPPED_MIN_BYTES
    table = pa.table({"a": np.arange(n, dtype=np.float64), "b": np.arange(n) % 7})
    assert table.nbytes >= local.SHIPPED_MIN_BYTES
    small = table.slice(0, 10)
    with LocalEngine(1) as engine:
        back = list(engine.map(methodcaller("combine_chunks"), [table, small, table]))
        directory = engine._ship_dir
        assert directory is not None and Path(directory).is_dir()
        assert list(Path(directory).iterdir()) == []  # each file removed as it was read
    assert [t.equals(u) for t, u in zip(back, [table, small, table], strict=True)] == [True] * 3
    assert not Path(directory).exists()
    assert local._ship_dir is None  # pickled as usual again


def test_a_whole_run_judges_only_the_wagons_whose_flags_are_out_of_date(
    fleet: Path, tmp_path: Path, rom_refinement: float, rom_cache_dir: Path
) -> None:
    """A whole ``run`` judges the flags of the wagons whose flags are out of date, the
    others' rows stay as they are: a second run judges none and leaves ``flags`` and
    ``flagged_spans`` identical; a wagon whose flags were removed is judged again alone;
    other thresholds judge every wagon (once); a warehouse from before the spans' judgements
    were recorded has every wagon judged once."""
    import duckdb

    db = tmp_path / "fleet.duckdb"

    def run(flag_config_path: Path | None = None) -> list[str]:
        report = _run(fleet, db, engine, rom_refinement, rom_cache_dir, flag_config_path)
        return list(report.flags.wagons)

    def execute(statement: str, values: dict[str, object] | None = None) -> None:
        con = duckdb.connect(str(db))
        try:
            con.execute(statement, values or {})
        finally:
            con.close()

    with InlineEngine() as engine:
        every = run()
        assert len(every) == 3
        judged = _flag_tables(db)
        assert judged["flags"] and len(judged["flagged_spans"]) >= 3
        assert run() == []  # nothing new: nothing judged, nothing rewritten
        assert _flag_tables(db) == judged

        flagged = str(judged["flags"][0][1])
        execute("DELETE FROM flags WHERE wagon_id = $w", {"w": flagged})
        assert run() == [flagged]  # its flags removed: judged again, alone
        assert _flags(db) == [tuple(r[:8]) for r in judged["flags"]]
        for other in sorted(set(every) - {flagged}):
            assert _flag_tables_of(_flag_tables(db), other) == _flag_tables_of(judged, other)
        assert run() == []

        # a warehouse from before the spans' judgements were recorded: judged once
        execute("DELETE FROM flagged_spans")
        assert run() == every
        assert run() == []

        thresholds = tmp_path / "flags.toml"
        thresholds.write_text("contact_limit_c = 150.0\n", encoding="utf-8")
        assert run(thresholds) == every  # other thresholds: every wagon judged
        assert run(thresholds) == []
        assert run() == every  # and back
    assert _flags(db) == [tuple(r[:8]) for r in judged["flags"]]


def _flag_tables_of(
    tables: dict[str, list[tuple[object, ...]]], wagon: str
) -> dict[str, list[tuple[object, ...]]]:
    """``tables`` (:func:`_flag_tables`) cut to one wagon's rows."""
    return {
        "flags": [r for r in tables["flags"] if r[1] == wagon],
        "flagged_spans": [r for r in tables["flagged_spans"] if r[0] == wagon],
    }
