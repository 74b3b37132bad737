"""The flags' partitions read by chunks (fleetbrake.flags.partition): a chunk's tables, read with
each span's position instead of its wagon's name (``q_flags_chunk_*.sql``) and cut in the
worker, give each span the tables its own queries read, the estimates included; and the braking
statistics (``event_stats``) are the same whether the predictions come sorted (the stage's
reads: the sort is skipped) or not.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import polars as pl
import pytest

from fleetbrake.flags import judge, partition
from fleetbrake.flags.config import FlagConfig
from fleetbrake.flags.stats import _by_event_and_time, event_stats
from fleetbrake.simulation.store import arrow_frame
from fleetbrake.warehouse.connection import Warehouse

pytestmark = pytest.mark.usefixtures("rom_cache_dir")


@pytest.fixture(scope="module")
def estimated_fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., object],
    rom_cache_dir: Path,
) -> Path:
    """A generated fleet of three wagons (and its warehouse) run through the simulation and
    the estimation stages: timelines, predictions and estimates stored."""
    from conftest import TEST_REFINEMENT
    from fleetbrake.app.run import run_fleet
    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    root = tmp_path_factory.mktemp("flag-chunks")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        config = SynthConfig(wagons=3, days=1, seed=12, refinement=TEST_REFINEMENT)
        generate_fleet(root / "fleet", config, rom=reduced_model_for)
        run_fleet(
            root / "fleet",
            root / "fleet.duckdb",
            simulation=SimulationConfig(refinement=TEST_REFINEMENT),
            workers=1,
            progress=False,
        )
    return root


def _heads(wh: Warehouse, fleet_dir: Path, revision_name: str) -> list[partition.FlagHead]:
    from fleetbrake.ingest.files import load_fleet_registry
    from fleetbrake.ingest.spans import stored_spans
    from fleetbrake.simulation.store import simulated_spans

    registry = load_fleet_registry(fleet_dir)
    done = simulated_spans(wh, revision_name)
    estimated = judge.current_estimates(wh, revision_name)
    return [
        partition.FlagHead(
            s,
            7.0,
            None,
            done[s.key].data_key if s.key in done and s.wagon_id in registry.wagons else None,
            registry.wagons.get(s.wagon_id),
            s.key in estimated,
        )
        for s in stored_spans(wh)
    ]


def test_a_chunks_tables_cut_in_the_worker_are_each_wagons_own(estimated_fleet: Path) -> None:
    """Every table of every span's task cut from a chunk (read with the span's position,
    ``part_ix``, the estimates with the wagon's, ``wagon_ix``, and named again in the worker)
    equals the one its own per-span queries read (``flag_task``), the estimates included; a
    chunk read in another order of its spans cuts the same tasks."""
    from fleetbrake.simulation.predictions import revision
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(estimated_fleet / "fleet.duckdb", read_only=True) as wh:
        rev = revision(wh, "declared")
        heads = _heads(wh, estimated_fleet / "fleet", rev.name)
        assert len(heads) >= 2 and all(h.estimated for h in heads if h.data_key is not None)
        config = FlagConfig()
        chunk = partition.flag_chunk(wh, heads, rev.name, config, rev)
        backwards = partition.flag_chunk(wh, heads[::-1], rev.name, config, rev)
        alone = {
            h.span.key: partition.flag_task(
                wh,
                h.span,
                rev.name,
                config,
                ambient_c=h.ambient_c,
                note=None,
                data_key=h.data_key,
                wagon=h.wagon,
                rev=rev,
                estimated=h.estimated,
            )
            for h in heads
        }
    assert "part_ix" in chunk.timeline.column_names  # not the names: the test's premise
    tables = ("samples", "events", "segments", "timeline", "predictions", "estimates")
    for tasks in (partition.chunk_tasks(chunk), partition.chunk_tasks(backwards)[::-1]):
        assert [t.span for t in tasks] == [h.span for h in heads]
        for task in tasks:
            theirs = alone[task.span.key]
            for name in tables:
                mine, own = getattr(task, name), getattr(theirs, name)
                assert (mine is None) == (own is None), (task.wagon_id, name)
                assert mine is None or mine.equals(own), (task.wagon_id, name)
            assert task.estimates is not None and task.estimates.num_rows > 0


def test_braking_statistics_do_not_depend_on_the_predictions_order(
    estimated_fleet: Path,
) -> None:
    """``event_stats`` of a wagon's predictions as the stage hands them (sorted by event and
    time: its sort skipped) equals that of the same rows shuffled (sorted again)."""
    from fleetbrake.warehouse.connection import open_warehouse

    with open_warehouse(estimated_fleet / "fleet.duckdb", read_only=True) as wh:
        heads = [h for h in _heads(wh, estimated_fleet / "fleet", "declared") if h.data_key]
        chunk = partition.flag_chunk(wh, heads, "declared", FlagConfig(), None)
    judged = 0
    for task in partition.chunk_tasks(chunk):
        assert task.predictions is not None
        predictions, events = arrow_frame(task.predictions), arrow_frame(task.events)
        if predictions.height < 2:
            continue
        shuffled = predictions.sample(fraction=1.0, shuffle=True, seed=3)
        assert _by_event_and_time(predictions) and not _by_event_and_time(shuffled)
        assert repr(event_stats(predictions, events)) == repr(event_stats(shuffled, events))
        ties = pl.concat([predictions.head(1), predictions])  # a repeated row: still sorted
        assert _by_event_and_time(ties)
        judged += 1
    assert judged >= 2
