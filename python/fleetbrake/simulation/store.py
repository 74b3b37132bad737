"""What the simulation stage stores per span and revision, and how the next stages read it.

Tables (``warehouse/sql/schema_pipeline.sql``): ``predictions`` (the event windows, behind
``v_predictions``), ``timeline`` (the block at every logged second) with ``timeline_segments``
(where and how it was re-anchored), and ``simulated_spans`` (what each span was simulated
from; :mod:`fleetbrake.ingest.spans`). A span's rows of one revision are replaced
together, in one transaction (:func:`replace_spans`).

::

    from fleetbrake.simulation.store import stored_timeline

    stored = stored_timeline("SGG-0001", "declared", data_key, segments, values)
    for span in stored.spans:
        span.start_utc, span.end_utc, span.segments, span.values
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

import numpy as np
import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information
import pyarrow.compute as pc  # type: ignore[import-untyped]

from fleetbrake.engine.writer import WriteBehind
from fleetbrake.simulation.series import strictly_increasing
from fleetbrake.warehouse.connection import Warehouse, reader, sql

if TYPE_CHECKING:
    from fleetbrake.ingest.spans import LedgerSpan, SpanKey

__all__ = [
    "Mapper",
    "StoredTimeline",
    "TimelineSpan",
    "WagonRows",
    "WagonWrite",
    "WriteBehind",
    "arrow_frame",
    "chunk_pipeline",
    "chunk_table",
    "forget_spans",
    "ledger_spans",
    "replace_spans",
    "sample_parts",
    "simulated_spans",
    "span_table",
    "stored_timeline",
    "table_rows",
    "unit_chunks",
    "utc_now",
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
U = TypeVar("U")


def chunk_pipeline(
    wh: Warehouse,
    units: Sequence[U],
    *,
    unit_rows: Callable[[U], int],
    read: Callable[[Warehouse, list[U]], C],
    compute: Callable[[C], list[R]],
    write: Callable[[list[R]], None],
    result_rows: Callable[[R], int],
    chunk_rows: int,
    batch_rows: int,
    engine: Mapper | None = None,
) -> Iterator[R]:
    """The pipeline of a stage that computes whole units (spans) and stores their rows (the
    simulation, the estimate): ``units`` in chunks of about ``chunk_rows`` samples
    (:func:`unit_chunks`, ``unit_rows`` each), each chunk ``read`` on a second connection
    (:func:`reader`: the parent's reads, one query per table), ``compute``d by ``engine.map``
    (default: the builtin ``map``, in this process; an engine's workers otherwise: a pure,
    picklable function of the chunk returning one result per unit, in order), and the results
    ``write``n in batches of whole units of at most ``batch_rows`` rows (``result_rows``
    each; one batch may exceed it with its first unit), one batch per call, on the writer's
    thread (:class:`WriteBehind`), while the next chunks are read and computed. Yields each
    result as it comes back, in the order of ``units``; the last batch is committed
    before the generator ends."""
    pending: list[R] = []
    held = 0
    with reader(wh) as source, WriteBehind(write) as writer:
        chunks = (read(source, part) for part in unit_chunks(units, unit_rows, chunk_rows))
        done = map(compute, chunks) if engine is None else engine.map(compute, chunks)
        for results in done:
            for result in results:
                rows = result_rows(result)
                if pending and held + rows > batch_rows:
                    writer.submit(pending)  # whole units per transaction, on its thread
                    pending, held = [], 0
                pending.append(result)
                held += rows
                yield result
        writer.submit(pending)
        writer.wait()


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
    """Everything one span's simulation with one revision stores (polars frames with the
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
    """A wagon's timeline (or one span's) as one revision's simulation stored it."""

    wagon_id: str
    revision: str
    data_key: str
    """The data as they were simulated (``simulated_spans.data_key``)."""
    spans: list[TimelineSpan] = field(default_factory=list)


def ledger_spans(wh: Warehouse, query: str, revision: str) -> dict[SpanKey, LedgerSpan]:
    """A stage's ledger of ``revision`` (``query``: ``q_*_spans.sql`` returning wagon, span
    start and end, data key, model key and when written, first), by span."""
    from fleetbrake.ingest.spans import LedgerSpan

    rows = wh.con.execute(sql(query), {"revision": revision}).fetchall()
    out = {}
    for r in rows:
        row = LedgerSpan(str(r[0]), r[1], r[2], str(r[3]), str(r[4]), r[5])
        out[row.key] = row
    return out


def simulated_spans(wh: Warehouse, revision: str) -> dict[SpanKey, LedgerSpan]:
    """The spans simulated with ``revision``, and from what."""
    return ledger_spans(wh, "q_simulation_simulated_spans", revision)


def unit_chunks(
    units: Sequence[U], rows_of: Callable[[U], int], max_rows: int
) -> Iterator[list[U]]:
    """``units`` in order, cut into chunks of about ``max_rows`` samples (``rows_of``: each
    unit's count), at least one unit each: the stages read a chunk's partitions with one
    query per table instead of one per unit and table."""
    chunk: list[U] = []
    held = 0
    for unit in units:
        n = rows_of(unit)
        if chunk and held + n > max_rows:
            yield chunk
            chunk, held = [], 0
        chunk.append(unit)
        held += n
    if chunk:
        yield chunk


def chunk_name(labels: Sequence[str]) -> str:
    """How an engine names a chunk of spans in an error: ``span S`` or ``spans S, T``."""
    return f"span {labels[0]}" if len(labels) == 1 else "spans " + ", ".join(labels)


def chunk_table(wh: Warehouse, name: str, wagon_ids: Sequence[str], **params: str) -> pa.Table:
    """The rows of ``wagon_ids`` that the chunk query ``name`` (``q_*_chunk_*.sql``, with a
    ``wagon_id`` column, or ``wagon_ix``: :func:`wagon_parts`) reads, as Arrow, in stored
    order (:func:`wagon_part` cuts it)."""
    values: dict[str, object] = {"wagon_ids": list(wagon_ids), **params}
    return wh.con.sql(sql(name), params=values).to_arrow_table()


def span_table(
    wh: Warehouse, name: str, ranges: Sequence[tuple[str, dt.datetime, dt.datetime]], **params: str
) -> pa.Table:
    """The rows of the spans ``ranges`` (wagon, first and last sample) that the chunk query
    ``name`` (``q_*_chunk_span_*.sql``, with ``part_ix``, the span's 1-based position in
    ``ranges``: :func:`wagon_parts`) reads, their time ranges only, as Arrow, in stored order."""
    from fleetbrake.ingest.spans import span_windows

    values: dict[str, object] = {**span_windows(ranges), **params}
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
    index: str = "wagon_ix",
) -> dict[str, pa.Table]:
    """:func:`wagon_part` of each of ``wagon_ids`` (an empty table for a wagon without
    rows). The stored order holds each wagon's rows in a few runs (its files were written
    together), so the table is cut at the runs of ``wagon_id`` (one pass, no comparison of
    every row with every wagon) and each wagon's runs are joined and sorted. A table read
    with ``index`` (``part_ix``: a span's 1-based position in ``positions_of``, the list the
    query was given, ``q_simulation_chunk_samples.sql`` and the other chunk queries of
    spans; ``wagon_ix``: a wagon's) is cut at the runs of the positions, and loses ``index``
    instead (``wagon_ids`` then names the parts: spans' labels). The parent reads and ships the
    4-byte position instead of the name (per 100 wagon-days 794 MB of Arrow shipped instead
    of 899, the flags' reads 1.21 processor-s instead of 1.36:
    ``docs/decisions/0007-reading-and-writing-in-chunks.md``), and the worker never makes a
    name per row (cutting by positions takes half the processor time of cutting by names)."""
    key = "wagon_id" if positions_of is None else index
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


def sample_parts(
    table: pa.Table, names: Sequence[str], index: str = "wagon_ix"
) -> dict[str, pa.Table]:
    """Each part's samples of a chunk read by ``q_simulation_chunk_samples.sql`` for the
    wagons ``names`` (with ``wagon_ix``), or by ``q_simulation_chunk_span_samples.sql`` for
    the spans of the labels ``names`` (``index="part_ix"``), in the order of the per-wagon
    and per-span queries (time, then file) and without ``file_id``: :func:`wagon_parts` as
    every stage that reads samples by chunks cuts them."""
    return wagon_parts(
        table, names, ["time_utc", "file_id"], ["file_id"], positions_of=names, index=index
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
    """One span's rows of a revision and the keys it was simulated from, to be stored whole
    (:func:`replace_spans`)."""

    wagon_id: str
    rows: WagonRows
    data_key: str
    model_key: str
    span_start_utc: dt.datetime
    span_end_utc: dt.datetime

    @property
    def row_count(self) -> int:
        rows = self.rows
        return table_rows(rows.predictions) + table_rows(rows.timeline) + table_rows(rows.segments)


_STAGE_TABLES = ("predictions", "timeline", "timeline_segments", "simulated_spans")
"""The simulation's tables, each with its range delete ``q_simulation_delete_span_<table>``."""


def replace_spans(wh: Warehouse, revision: str, spans: Sequence[WagonWrite]) -> None:
    """Replace the rows of ``revision`` of every span of ``spans`` in every table of the
    stage, all in one transaction (each span whole-old or whole-new whatever happens), one
    bulk delete (by the spans' time ranges) and one bulk insert per table, recording the keys
    each was simulated from (``simulated_spans``)."""
    if not spans:
        return
    if len({(w.wagon_id, w.span_start_utc) for w in spans}) != len(spans):
        raise ValueError("replace_spans: a span given twice")
    batches = (
        ("prediction_batch", "predictions", "q_simulation_insert_predictions"),
        ("timeline_batch", "timeline", "q_simulation_insert_timeline"),
        ("segment_batch", "segments", "q_simulation_insert_timeline_segments"),
    )
    now = utc_now()
    ledger = pa.table(
        {
            "wagon_id": pa.array([w.wagon_id for w in spans], pa.string()),
            "model_revision": pa.array([revision] * len(spans), pa.string()),
            "span_start_utc": pa.array([w.span_start_utc for w in spans], pa.timestamp("us")),
            "span_end_utc": pa.array([w.span_end_utc for w in spans], pa.timestamp("us")),
            "data_key": pa.array([w.data_key for w in spans], pa.string()),
            "model_key": pa.array([w.model_key for w in spans], pa.string()),
            "events": pa.array([w.rows.events for w in spans], pa.int64()),
            "simulated_utc": pa.array([now] * len(spans), pa.timestamp("us")),
        }
    )
    ranges = [(w.wagon_id, w.span_start_utc, w.span_end_utc) for w in spans]
    with wh.transaction() as con:
        _delete_ranges(con, revision, ranges)
        for name, attribute, statement in batches:
            frames = [frame for w in spans if table_rows(frame := getattr(w.rows, attribute))]
            if not frames:
                continue
            con.register(name, _concat(frames))
            try:
                con.execute(sql(statement))
            finally:
                con.unregister(name)
        con.register("simulated_batch", ledger)
        try:
            con.execute(sql("q_simulation_insert_simulated_spans"))
        finally:
            con.unregister("simulated_batch")


def _delete_ranges(
    con: Any, revision: str, ranges: Sequence[tuple[str, dt.datetime, dt.datetime]]
) -> None:
    from fleetbrake.ingest.spans import envelope, span_windows

    params = {**span_windows(ranges), "revision": revision}
    for table in _STAGE_TABLES:
        timed = table in ("predictions", "timeline")
        values = {**params, **envelope(ranges)} if timed else params
        con.execute(sql(f"q_simulation_delete_span_{table}"), values)


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


def forget_spans(
    wh: Warehouse, revision: str, ranges: Sequence[tuple[str, dt.datetime, dt.datetime]]
) -> None:
    """Remove every row the stage stored for ``revision`` in the spans' time ranges (spans
    that no longer exist: merged, cut again or gone), in one transaction."""
    if not ranges:
        return
    with wh.transaction() as con:
        _delete_ranges(con, revision, ranges)


def stored_timeline(
    wagon_id: str, revision: str, data_key: str, segments: pl.DataFrame, values: pl.DataFrame
) -> StoredTimeline:
    """A wagon's stored timeline from its rows of ``timeline_segments`` (with
    ``span_start_utc``, ``span_end_utc``) and ``timeline`` as read by
    ``q_flags_span_segments.sql`` and ``q_flags_span_timeline.sql``, cut by span (no
    database: the flags' workers call it)."""
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
    (as ``q_flags_span_segments.sql`` orders them), else a polars ``group_by``."""
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
