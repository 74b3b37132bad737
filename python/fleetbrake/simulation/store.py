"""What the simulation stage stores per wagon and revision, and how the next stages read it.

Tables (``warehouse/sql/schema_pipeline.sql``): ``predictions`` (the event windows, behind
``v_predictions``), ``timeline`` (the block at every logged second) with ``timeline_segments``
(where and how it was re-anchored), and ``simulated_wagons`` (what each wagon was simulated
from). A wagon's rows of one revision are replaced together, in one transaction.

::

    from fleetbrake.simulation.store import load_timeline

    stored = load_timeline(wh, "SGG-0001", "declared")   # None if never simulated
    for span in stored.spans:
        span.start_utc, span.end_utc, span.segments, span.values
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

import numpy as np
import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information
import pyarrow.compute as pc  # type: ignore[import-untyped]

from fleetbrake.engine.writer import WriteBehind
from fleetbrake.simulation.series import strictly_increasing
from fleetbrake.warehouse.connection import Warehouse, reader, sql

__all__ = [
    "Mapper",
    "SimulatedWagon",
    "StoredTimeline",
    "TimelineSpan",
    "WagonRows",
    "WagonWrite",
    "WriteBehind",
    "arrow_frame",
    "chunk_pipeline",
    "chunk_table",
    "data_keys",
    "forget_wagon",
    "load_timeline",
    "replace_wagon",
    "replace_wagons",
    "sample_parts",
    "sample_rows",
    "simulated_wagons",
    "stored_timeline",
    "stored_wagon_ids",
    "table_rows",
    "utc_now",
    "wagon_chunks",
    "wagon_events",
    "wagon_part",
    "wagon_parts",
    "wagon_samples",
]


def utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(tzinfo=None)


class Mapper(Protocol):
    """What runs a stage's partitions: an object with ``map(fn, items)`` yielding
    ``fn(item)`` in the order of ``items`` (a :class:`fleetbrake.engine.Engine`)."""

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any], /) -> Iterator[Any]: ...


C = TypeVar("C")
R = TypeVar("R")


def chunk_pipeline(
    wh: Warehouse,
    wagon_ids: Sequence[str],
    *,
    read: Callable[[Warehouse, list[str]], C],
    compute: Callable[[C], list[R]],
    write: Callable[[list[R]], None],
    result_rows: Callable[[R], int],
    chunk_rows: int,
    batch_rows: int,
    engine: Mapper | None = None,
) -> Iterator[R]:
    """The pipeline of a stage that computes whole wagons and stores their rows (the
    simulation, the estimate): ``wagon_ids`` in chunks of about ``chunk_rows`` samples
    (:func:`wagon_chunks`), each chunk ``read`` on a second connection (:func:`reader`: the
    parent's reads, one query per table), ``compute``d by ``engine.map`` (default: the
    builtin ``map``, in this process; an engine's workers otherwise: a pure, picklable
    function of the chunk returning one result per wagon, in order), and the results
    ``write``n in batches of whole wagons of at most ``batch_rows`` rows (``result_rows``
    each; one batch may exceed it with its first wagon), one batch per call, on the writer's
    thread (:class:`WriteBehind`), while the next chunks are read and computed. Yields each
    result as it comes back, in the order of ``wagon_ids``; the last batch is committed
    before the generator ends."""
    counts = sample_rows(wh)
    pending: list[R] = []
    held = 0
    with reader(wh) as source, WriteBehind(write) as writer:
        chunks = (read(source, ids) for ids in wagon_chunks(wagon_ids, counts, chunk_rows))
        done = map(compute, chunks) if engine is None else engine.map(compute, chunks)
        for results in done:
            for result in results:
                rows = result_rows(result)
                if pending and held + rows > batch_rows:
                    writer.submit(pending)  # whole wagons per transaction, on its thread
                    pending, held = [], 0
                pending.append(result)
                held += rows
                yield result
        writer.submit(pending)
        writer.wait()


@dataclass(frozen=True)
class SimulatedWagon:
    """A row of ``simulated_wagons``."""

    wagon_id: str
    data_key: str
    model_key: str
    events: int
    simulated_utc: dt.datetime


def arrow_frame(table: pa.Table) -> pl.DataFrame:
    """An Arrow table of a partition as a polars frame (what a worker computes on)."""
    frame = pl.from_arrow(table)
    assert isinstance(frame, pl.DataFrame)
    return frame


def table_rows(table: pl.DataFrame | pa.Table) -> int:
    """Rows of a polars frame or an Arrow table."""
    return int(table.height if isinstance(table, pl.DataFrame) else table.num_rows)


@dataclass
class WagonRows:
    """Everything one wagon's simulation with one revision stores (polars frames with the
    columns of the tables, or Arrow tables as a worker handed them back: DuckDB inserts
    those as they are, a fifth cheaper than polars frames)."""

    predictions: pl.DataFrame | pa.Table
    timeline: pl.DataFrame | pa.Table
    segments: pl.DataFrame | pa.Table
    events: int = 0


@dataclass(frozen=True)
class TimelineSpan:
    """One span of a stored timeline: first and last sample, its segments (``start_utc``,
    ``stop_utc``, ``kind``, ``event_id``, ``anchor``, ``shift_k``, ``reference_c``) and its
    values (``time_utc``, ``predicted_sensor_c``, ``predicted_contact_mean_c``,
    ``predicted_contact_max_c``)."""

    start_utc: dt.datetime
    end_utc: dt.datetime
    segments: pl.DataFrame
    values: pl.DataFrame


@dataclass
class StoredTimeline:
    """A wagon's timeline as one revision's simulation stored it."""

    wagon_id: str
    revision: str
    data_key: str
    """The wagon's data as it was simulated (compare :func:`data_keys`)."""
    spans: list[TimelineSpan] = field(default_factory=list)


def data_keys(wh: Warehouse) -> dict[str, str]:
    """Each wagon with samples: a key of its data (files, samples, events) as they are now."""
    rows = wh.con.execute(sql("q_simulation_wagon_data")).fetchall()
    return {str(wagon_id): str(key) for wagon_id, key in rows}


def simulated_wagons(wh: Warehouse, revision: str) -> dict[str, SimulatedWagon]:
    """The wagons simulated with ``revision``, and from what."""
    rows = wh.con.execute(sql("q_simulation_simulated_wagons"), {"revision": revision}).fetchall()
    return {str(r[0]): SimulatedWagon(str(r[0]), r[1], r[2], int(r[3]), r[4]) for r in rows}


def sample_rows(wh: Warehouse) -> dict[str, int]:
    """Each wagon with samples: how many it has (what the stages' chunks are sized by)."""
    rows = wh.con.execute(sql("q_simulation_wagon_sample_rows")).fetchall()
    return {str(wagon_id): int(n) for wagon_id, n in rows}


def wagon_chunks(
    wagon_ids: Sequence[str], rows: Mapping[str, int], max_rows: int
) -> Iterator[list[str]]:
    """``wagon_ids`` in order, cut into chunks of about ``max_rows`` samples (``rows``: each
    wagon's count, :func:`sample_rows`), at least one wagon each: the stages read a chunk's
    partitions with one query per table instead of one per wagon and table."""
    chunk: list[str] = []
    held = 0
    for wagon_id in wagon_ids:
        n = rows.get(wagon_id, 0)
        if chunk and held + n > max_rows:
            yield chunk
            chunk, held = [], 0
        chunk.append(wagon_id)
        held += n
    if chunk:
        yield chunk


def chunk_name(wagon_ids: Sequence[str]) -> str:
    """How an engine names a chunk of whole wagons in an error: ``wagon W`` or ``wagons W, V``."""
    return f"wagon {wagon_ids[0]}" if len(wagon_ids) == 1 else "wagons " + ", ".join(wagon_ids)


def chunk_table(wh: Warehouse, name: str, wagon_ids: Sequence[str], **params: str) -> pa.Table:
    """The rows of ``wagon_ids`` that the chunk query ``name`` (``q_*_chunk_*.sql``, with a
    ``wagon_id`` column, or ``wagon_ix``: :func:`wagon_parts`) reads, as Arrow, in stored order (:func:`wagon_part` cuts it)."""
    values: dict[str, object] = {"wagon_ids": list(wagon_ids), **params}
    return wh.con.sql(sql(name), params=values).to_arrow_table()


def wagon_part(
    table: pa.Table, wagon_id: str, order_by: Sequence[str], drop: Sequence[str] = ()
) -> pa.Table:
    """One wagon's rows of a chunk's table (:func:`chunk_table`), sorted by ``order_by`` (a
    stable sort: rows equal in it stay in stored order), without ``wagon_id`` and ``drop``:
    the table the per-wagon query (the chunk query's namesake) reads, no database needed.
    (:func:`wagon_parts` cuts every wagon's at once, for a fraction of the cost.)"""
    return wagon_parts(table, [wagon_id], order_by, drop)[wagon_id]


def wagon_parts(
    table: pa.Table,
    wagon_ids: Sequence[str],
    order_by: Sequence[str],
    drop: Sequence[str] = (),
    *,
    positions_of: Sequence[str] | None = None,
) -> dict[str, pa.Table]:
    """:func:`wagon_part` of each of ``wagon_ids`` (an empty table for a wagon without
    rows). The stored order holds each wagon's rows in a few runs (its files were written
    together), so the table is cut at the runs of ``wagon_id`` (one pass, no comparison of
    every row with every wagon) and each wagon's runs are joined and sorted. A table read
    with ``wagon_ix`` (its wagon's 1-based position in ``positions_of``, the list the query
    was given: ``q_simulation_chunk_samples.sql``, the flags' large chunk queries) is cut at
    the runs of the positions, and loses ``wagon_ix`` instead. The parent reads and ships the
    4-byte position instead of the name (per 100 wagon-days 794 MB of Arrow shipped instead
    of 899, the flags' reads 1.21 processor-s instead of 1.36:
    ``docs/decisions/0007-reading-and-writing-in-chunks.md``), and the worker never makes a
    name per row (cutting by positions takes half the processor time of cutting by names)."""
    key = "wagon_id" if positions_of is None else "wagon_ix"
    column = table.column(key)
    runs: dict[str, list[pa.Table]] = {w: [] for w in wagon_ids}
    if table.num_rows:
        encoded = pc.run_end_encode(column.combine_chunks())
        ends = encoded.run_ends.to_pylist()
        values = encoded.values.to_pylist()
        if positions_of is not None:
            values = [positions_of[ix - 1] for ix in values]
        start = 0
        for value, end in zip(values, ends, strict=True):
            if value in runs:
                runs[value].append(table.slice(start, end - start))
            start = end
    keys = [(name, "ascending") for name in order_by]
    parts = {}
    for wagon_id, pieces in runs.items():
        part = pa.concat_tables(pieces) if pieces else table.slice(0, 0)
        if part.num_rows > 1 and not _increasing(part.column(order_by[0])):
            order = pc.sort_indices(part.select(list(order_by)), sort_keys=keys)
            if not _in_order(order):  # most wagons' rows are stored in order: no copy
                part = part.take(order)
        parts[wagon_id] = part.drop_columns([key, *drop])
    return parts


def sample_parts(table: pa.Table, wagon_ids: Sequence[str]) -> dict[str, pa.Table]:
    """Each wagon's samples of a chunk read by ``q_simulation_chunk_samples.sql`` for
    ``wagon_ids`` (with ``wagon_ix``), in the order of the per-wagon query
    (time, then file) and without ``file_id``: :func:`wagon_parts` as every stage that reads
    samples by chunks cuts them."""
    return wagon_parts(
        table, wagon_ids, ["time_utc", "file_id"], ["file_id"], positions_of=wagon_ids
    )


def _increasing(column: pa.ChunkedArray) -> bool:
    """True when ``column`` (a time or an integer, no nulls) strictly increases: sorting on it
    first changes nothing, whatever the keys after it (most wagons' rows, stored in order),
    and the sort is not computed. False when unsure (another type, nulls)."""
    kind = column.type
    if not (pa.types.is_timestamp(kind) or pa.types.is_integer(kind)):
        return False
    series = pl.from_arrow(column)
    assert isinstance(series, pl.Series)  # a column converts to a series
    return strictly_increasing(series)


def _in_order(indices: pa.Array) -> bool:
    """True when ``indices`` (a permutation) is 0, 1, 2, ...: taking them changes nothing."""
    values = indices.to_numpy()
    return bool(values[0] == 0 and (values[1:] - values[:-1] == 1).all())


def wagon_samples(wh: Warehouse, wagon_id: str) -> pl.DataFrame:
    """All samples of a wagon, by time (``q_simulation_wagon_samples.sql``)."""
    return wh.con.sql(sql("q_simulation_wagon_samples"), params={"wagon_id": wagon_id}).pl()


def wagon_events(wh: Warehouse, wagon_id: str) -> pl.DataFrame:
    """The braking events of a wagon, by activation (``q_simulation_wagon_events.sql``)."""
    return wh.con.sql(sql("q_simulation_wagon_events"), params={"wagon_id": wagon_id}).pl()


@dataclass(frozen=True)
class WagonWrite:
    """One wagon's rows of a revision and the keys it was simulated from, to be stored
    whole (:func:`replace_wagons`)."""

    wagon_id: str
    rows: WagonRows
    data_key: str
    model_key: str

    @property
    def row_count(self) -> int:
        rows = self.rows
        return table_rows(rows.predictions) + table_rows(rows.timeline) + table_rows(rows.segments)


def replace_wagon(
    wh: Warehouse,
    wagon_id: str,
    revision: str,
    rows: WagonRows,
    *,
    data_key: str,
    model_key: str,
) -> None:
    """Replace the wagon's rows of ``revision`` in every table of the stage, in one
    transaction, recording the keys it was simulated from."""
    replace_wagons(wh, revision, [WagonWrite(wagon_id, rows, data_key, model_key)])


def stored_wagon_ids(wh: Warehouse, revision: str) -> set[str]:
    """The wagons holding rows of ``revision`` in any table of the stage: the ones
    :func:`replace_wagons` must delete before it inserts."""
    rows = wh.con.execute(sql("q_simulation_stored_wagon_ids"), {"revision": revision}).fetchall()
    return {str(r[0]) for r in rows}


def replace_wagons(
    wh: Warehouse, revision: str, wagons: Sequence[WagonWrite], *, delete: bool = True
) -> None:
    """Replace the rows of ``revision`` of every wagon of ``wagons`` in every table of the
    stage, all in one transaction (each wagon whole-old or whole-new whatever happens), one
    bulk delete and one bulk insert per table, recording the keys each was simulated from.

    ``delete=False``: none of the wagons holds rows of ``revision`` (:func:`stored_wagon_ids`),
    so the deletes, each a scan of its whole table (which grows with the fleet), are skipped."""
    if not wagons:
        return
    if len({w.wagon_id for w in wagons}) != len(wagons):
        raise ValueError("replace_wagons: a wagon given twice")
    batches = (
        ("prediction_batch", "predictions", "q_simulation_insert_predictions"),
        ("timeline_batch", "timeline", "q_simulation_insert_timeline"),
        ("segment_batch", "segments", "q_simulation_insert_timeline_segments"),
    )
    key = {"wagon_ids": [w.wagon_id for w in wagons], "revision": revision}
    now = utc_now()
    with wh.transaction() as con:
        for table in ("predictions", "timeline", "timeline_segments", "simulated_wagons"):
            if delete:
                con.execute(sql(f"q_simulation_delete_{table}_wagons"), key)
        for name, attribute, statement in batches:
            frames = [frame for w in wagons if table_rows(frame := getattr(w.rows, attribute))]
            if not frames:
                continue
            con.register(name, _concat(frames))
            try:
                con.execute(sql(statement))
            finally:
                con.unregister(name)
        for w in wagons:
            con.execute(
                sql("q_simulation_insert_simulated_wagon"),
                {
                    "wagon_id": w.wagon_id,
                    "revision": revision,
                    "data_key": w.data_key,
                    "model_key": w.model_key,
                    "events": w.rows.events,
                    "simulated_utc": now,
                },
            )


def _concat(tables: list[pl.DataFrame | pa.Table]) -> pl.DataFrame | pa.Table:
    """The tables one under the other: Arrow if all are (no copy), else a polars frame."""
    if len(tables) == 1:
        return tables[0]
    if all(isinstance(t, pa.Table) for t in tables):
        return pa.concat_tables(tables)
    frames = []
    for table in tables:
        frame = table if isinstance(table, pl.DataFrame) else pl.from_arrow(table)
        assert isinstance(frame, pl.DataFrame)
        frames.append(frame)
    return pl.concat(frames, how="vertical")


def forget_wagon(wh: Warehouse, wagon_id: str, revision: str) -> None:
    """Remove every row the stage stored for the wagon and revision (its data are gone)."""
    with wh.transaction() as con:
        for table in ("predictions", "timeline", "timeline_segments", "simulated_wagons"):
            con.execute(
                sql(f"q_simulation_delete_{table}"), {"wagon_id": wagon_id, "revision": revision}
            )


def load_timeline(wh: Warehouse, wagon_id: str, revision: str) -> StoredTimeline | None:
    """The wagon's stored timeline of ``revision``, by span; None if it was never simulated
    with it."""
    done = simulated_wagons(wh, revision).get(wagon_id)
    if done is None:
        return None
    params = {"wagon_id": wagon_id, "revision": revision}
    segments = wh.con.sql(sql("q_simulation_timeline_segments"), params=params).pl()
    values = wh.con.sql(sql("q_simulation_timeline"), params=params).pl()
    return stored_timeline(wagon_id, revision, done.data_key, segments, values)


def stored_timeline(
    wagon_id: str, revision: str, data_key: str, segments: pl.DataFrame, values: pl.DataFrame
) -> StoredTimeline:
    """A wagon's stored timeline from its rows of ``timeline_segments`` (with
    ``span_start_utc``, ``span_end_utc``) and ``timeline`` as read by
    ``q_simulation_timeline_segments.sql`` and ``q_simulation_timeline.sql``, cut by span
    (what :func:`load_timeline` returns, without a database: the flags' workers call it)."""
    stored = StoredTimeline(wagon_id, revision, data_key)
    if segments.height == 0:
        return stored
    times = values["time_utc"]
    at = times.to_numpy() if strictly_increasing(times) else None
    for (start, end), part in _by_span(segments):
        assert isinstance(start, dt.datetime) and isinstance(end, dt.datetime)
        if at is not None:  # the span's rows: a slice, no polars query
            lo = int(np.searchsorted(at, np.datetime64(start, "us"), "left"))
            hi = int(np.searchsorted(at, np.datetime64(end, "us"), "right"))
            inside = values.slice(lo, hi - lo)
        else:
            inside = values.filter(pl.col("time_utc").is_between(start, end))
        stored.spans.append(TimelineSpan(start, end, part, inside))
    stored.spans.sort(key=lambda s: s.start_utc)
    return stored


def _by_span(
    segments: pl.DataFrame,
) -> list[tuple[tuple[dt.datetime, dt.datetime], pl.DataFrame]]:
    """``segments`` grouped by (``span_start_utc``, ``span_end_utc``) in the order each span
    first appears, without those two columns: slices when each span's rows are consecutive
    (as ``q_simulation_timeline_segments.sql`` orders them), else a polars ``group_by``."""
    starts = segments["span_start_utc"]
    ends = segments["span_end_utc"]
    if not (starts.has_nulls() or ends.has_nulls()):
        a, b = starts.to_numpy(), ends.to_numpy()
        cut = np.flatnonzero((a[1:] != a[:-1]) | (b[1:] != b[:-1])) + 1
        first = np.concatenate([[0], cut])
        if len(set(zip(a[first].tolist(), b[first].tolist(), strict=True))) == first.size:
            stops = np.concatenate([cut, [a.size]])
            rest = segments.drop("span_start_utc", "span_end_utc")
            return [
                ((starts[int(i)], ends[int(i)]), rest.slice(int(i), int(j - i)))
                for i, j in zip(first, stops, strict=True)
            ]
    return [
        (key, part.drop("span_start_utc", "span_end_utc"))
        for key, part in segments.group_by(["span_start_utc", "span_end_utc"], maintain_order=True)
    ]
