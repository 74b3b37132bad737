"""Braking events kept up to date in the warehouse, after each ingestion.

::

    from fleetbrake.ingest.events import update_events

    with open_warehouse(db) as wh:
        update = update_events(wh)                  # incremental, after an ingestion

How the events of a wagon's samples are found: :mod:`fleetbrake.ingest.detection`.

Incremental (:func:`update_events`): each ingested file records its time range in
``event_dirty`` (in the file's transaction). A wagon's files whose time ranges lie within
``max_gap_s`` of each other form a *chain*; since events never bridge larger gaps, a chain's
events depend only on its own samples. Every chain touching a dirty range is detected again,
and the events table is brought in line for a batch of whole wagons (about 1,000 events) in
one transaction: events that are the same are left alone (their ``detected_utc``
unchanged), changed or vanished ones are replaced or deleted, new ones inserted, and the
wagons' dirty ranges removed. A run killed half-way leaves whole wagons done and the others'
dirty ranges in place, so the next run does their work again. Samples are loaded whole
chains at a time, the touched chains of several wagons together (at most about 200,000
rows, unless one chain is longer) with one query, in stored order: a partition, cut into
its wagons' windows and sorted by time and detected by an engine's worker when
``update_events`` is given an engine (:mod:`fleetbrake.engine`), while this process, the
single writer, commits the batches.
"""

from __future__ import annotations

import bisect
import datetime as dt
import itertools
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import duckdb
import numpy as np
import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.engine.writer import WriteBehind
from fleetbrake.ingest.config import EventConfig
from fleetbrake.ingest.detection import EVENT_COLUMNS, detect_events, physical_us
from fleetbrake.ingest.spans import SpanUpdate, update_spans
from fleetbrake.warehouse.connection import Warehouse, reader, sql

__all__ = ["EventUpdate", "Mapper", "update_events"]


@dataclass
class EventUpdate:
    """What :func:`update_events` changed."""

    wagons: int = 0
    chains: int = 0
    """Chains of files detected again."""
    added: int = 0
    """Events inserted (new, or replacing a changed one)."""
    removed: int = 0
    """Events deleted (vanished, or replaced by a changed one)."""
    unchanged: int = 0
    """Events detected again with the same values, left alone."""
    total: int = 0
    """Events in the table afterwards."""
    changed_ids: list[str] = field(default_factory=list)
    """Ids of the events inserted by this update."""
    spans: SpanUpdate = field(default_factory=SpanUpdate)
    """The spans cut again after the events (:func:`~fleetbrake.ingest.spans.update_spans`:
    where files were added, removed or replaced)."""


_LOAD_ROWS = 200_000
"""Samples loaded per query at most (whole chains of one or more wagons, a partition; a
longer chain is loaded alone): about five wagon-days, the size of the other stages' chunks
(a hundred wagon-days make twenty partitions for the workers to share)."""

_COMMIT_EVENTS = 1_000
"""Events brought in line per transaction at most (whole wagons; a wagon with more is
committed alone; a wagon without any counts one): ``BEGIN``/``COMMIT`` and the insert cost
milliseconds whatever their size (3 transactions instead of 100 on 100 wagons take the
writer from 2.1-2.2 to 1.7 processor-s:
``docs/decisions/0007-reading-and-writing-in-chunks.md``)."""


@dataclass(frozen=True)
class _Chain:
    """Files of one wagon closer than ``max_gap_s`` to each other: their time span, rows."""

    from_utc: dt.datetime
    to_utc: dt.datetime
    rows: int


def _chains(files: list[tuple[dt.datetime, dt.datetime, int]], max_gap_s: float) -> list[_Chain]:
    """Files (first, last sample, rows) sorted by first, grouped where closer than ``max_gap_s``."""
    chains: list[_Chain] = []
    gap = dt.timedelta(seconds=max_gap_s)
    for first, last, rows in files:
        if chains and first - chains[-1].to_utc <= gap:
            before = chains[-1]
            chains[-1] = _Chain(before.from_utc, max(before.to_utc, last), before.rows + rows)
        else:
            chains.append(_Chain(first, last, rows))
    return chains


def _merged(
    ranges: list[tuple[dt.datetime, dt.datetime]], pad: dt.timedelta
) -> list[tuple[dt.datetime, dt.datetime]]:
    """Ranges widened by ``pad`` on both sides, sorted, overlapping ones merged."""
    merged: list[tuple[dt.datetime, dt.datetime]] = []
    for a, b in sorted((a - pad, b + pad) for a, b in ranges):
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged


def _overlaps(
    merged: list[tuple[dt.datetime, dt.datetime]], from_utc: dt.datetime, to_utc: dt.datetime
) -> bool:
    """[from_utc, to_utc] meets one of the sorted disjoint ranges ``merged``."""
    i = bisect.bisect_right(merged, (to_utc, dt.datetime.max))
    return i > 0 and merged[i - 1][1] >= from_utc


def update_events(
    wh: Warehouse, config: EventConfig | None = None, *, engine: Mapper | None = None
) -> EventUpdate:
    """Detect the events of every chain of files touched since the last update (see module).

    This process reads the wagons' touched chains (several wagons' at a time, at most about
    ``_LOAD_ROWS`` samples, one query: a partition, :func:`_detect_tasks`), ``engine.map``
    runs the detection on them (default: the builtin ``map``, here; an engine's workers
    otherwise, which cut and sort the rows: :func:`_window_parts`), and this process brings
    whole wagons' events in line, a batch of wagons (at most about ``_COMMIT_EVENTS``
    events) in one transaction, as their partitions come back. The transactions run on a
    writer thread (:class:`~fleetbrake.engine.writer.WriteBehind`), one batch at a time and
    in order, while the next wagons' samples are read on a second connection
    (:func:`reader`): the reads and the commits overlap instead of adding up."""
    config = config or EventConfig()
    con = wh.con
    update = EventUpdate()
    dirty = con.execute(sql("q_events_dirty")).fetchall()
    by_wagon: dict[str, list[tuple[dt.datetime, dt.datetime]]] = {}
    for wagon_id, from_utc, to_utc in dirty:
        by_wagon.setdefault(wagon_id, []).append((from_utc, to_utc))
    affected_by_wagon: dict[str, list[_Chain]] = {}
    holding = _holding_events(wh, sorted(by_wagon))

    def write(batch: list[_Detected]) -> None:
        _update_wagons(wh, batch, by_wagon, holding, update)

    pending: list[_Detected] = []
    held = 0
    with reader(wh) as source, WriteBehind(write) as writer:
        tasks = _detect_tasks(source, by_wagon, config, affected_by_wagon)
        results = map(_detect_task, tasks) if engine is None else engine.map(_detect_task, tasks)
        found: list[pl.DataFrame] = []
        for task_wagon, events, last in (one for chunk in results for one in chunk):
            found.append(events)
            if not last:
                continue
            new = pl.concat(found)
            found = []
            rows = max(new.height, 1)
            if pending and held + rows > _COMMIT_EVENTS:
                writer.submit(pending)  # whole wagons per transaction, on its thread
                pending, held = [], 0
            pending.append(_Detected(task_wagon, affected_by_wagon.pop(task_wagon), new))
            held += rows
        if pending:
            writer.submit(pending)
    update.spans = update_spans(wh)  # the spans cut again where files changed
    row = con.execute(sql("q_events_count")).fetchone()
    update.total = int(row[0]) if row is not None else 0
    return update


class Mapper(Protocol):
    """What runs the detection's partitions: ``map(fn, items)`` yielding ``fn(item)`` in the
    order of ``items`` (a :class:`fleetbrake.engine.Engine`)."""

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any], /) -> Iterator[Any]: ...


@dataclass(frozen=True)
class _Window:
    """A time window of one wagon's samples read in one piece: some of its touched chains
    (consecutive ones, with the chains between them) or none."""

    wagon_id: str
    chains: tuple[tuple[dt.datetime, dt.datetime], ...]
    """The touched chains' time spans, in time order (the window runs from the first's start
    to the last's end)."""
    rows: int
    """Samples of the window's files (what chunks are sized by)."""
    last: bool
    """The wagon's last window: its events can be brought in line once it is back."""


@dataclass(frozen=True)
class _DetectTask:
    """A partition of the detection: windows of one or more wagons, in wagon order, and their
    samples read together (``q_events_chunk_samples.sql``: Arrow, each row with its
    window's 1-based ``part_ix``, in stored order)."""

    windows: tuple[_Window, ...]
    samples: pa.Table | None
    """The samples of the windows with chains (``part_ix`` counts those); None: none has."""
    config: EventConfig

    def __str__(self) -> str:  # how an engine names the partition in an error
        wagons = list(dict.fromkeys(w.wagon_id for w in self.windows))
        chains = sum(len(w.chains) for w in self.windows)
        names = f"wagon {wagons[0]}" if len(wagons) == 1 else "wagons " + ", ".join(wagons)
        return f"{names} ({chains} stretches of samples)"


def _detect_task(task: _DetectTask) -> list[tuple[str, pl.DataFrame, bool]]:
    """The events of each window's chains, in the task's order (pure: runs in an engine's
    worker): the chunk cut into the windows it read (:func:`_window_parts`), each sorted as
    ``q_event_samples.sql`` sorts one, each chain's slice detected alone."""
    parts = iter(_window_parts(task.samples, sum(1 for w in task.windows if w.chains)))
    out = []
    for window in task.windows:
        found = [pl.DataFrame(schema=EVENT_COLUMNS)]
        if window.chains:
            samples = next(parts)
            times = samples["time_utc"].to_numpy()  # sorted; numpy: no Series per lookup
            for from_utc, to_utc in window.chains:
                lo = int(np.searchsorted(times, np.datetime64(from_utc, "us"), "left"))
                hi = int(np.searchsorted(times, np.datetime64(to_utc, "us"), "right"))
                chain = samples.slice(lo, hi - lo)
                found.append(detect_events(chain, window.wagon_id, task.config))
        out.append((window.wagon_id, pl.concat(found), window.last))
    return out


_SAMPLE_COLUMNS: dict[str, pl.DataType] = {
    "time_utc": pl.Datetime("us"),
    "file_id": pl.Int64(),
    "speed_kmh": pl.Float64(),
    "distance_m": pl.Float64(),
    "brake_pressure_bar": pl.Float64(),
    "block_temp_c": pl.Float64(),
    "block_temp_fault": pl.Boolean(),
}
"""The columns of ``q_event_samples.sql`` (a window's samples as the detection reads them)."""


def _window_parts(samples: pa.Table | None, windows: int) -> list[pl.DataFrame]:
    """Each of ``windows`` windows' samples of a chunk read by ``q_events_chunk_samples.sql``
    (by ``part_ix``), sorted by ``time_utc`` then ``file_id`` as ``q_event_samples.sql`` sorts
    one window (a file holds one sample per time: the order is total, so any sort gives the
    same rows), without ``part_ix``. The stored order holds each window's rows in a few runs
    (its files were written together), mostly in time order: each window is its runs'
    slices joined without a copy, sorted only when its times do not strictly increase."""
    empty = pl.DataFrame(schema=_SAMPLE_COLUMNS)
    if samples is None or samples.num_rows == 0:
        return [empty] * windows
    frame = pl.from_arrow(samples)
    assert isinstance(frame, pl.DataFrame)  # a table converts to a frame
    ix = frame["part_ix"].to_numpy()
    frame = frame.select(list(_SAMPLE_COLUMNS))
    runs: list[list[pl.DataFrame]] = [[] for _ in range(windows)]
    starts = [0, *(np.flatnonzero(ix[1:] != ix[:-1]) + 1).tolist(), ix.size]
    for a, b in itertools.pairwise(starts):
        runs[int(ix[a]) - 1].append(frame.slice(a, b - a))
    parts = []
    for pieces in runs:
        part = pl.concat(pieces, rechunk=False) if pieces else empty
        if not np.all(np.diff(physical_us(part["time_utc"])) > 0):  # or a time repeated
            part = part.sort(["time_utc", "file_id"])
        parts.append(part)
    return parts


def _detect_tasks(
    wh: Warehouse,
    by_wagon: dict[str, list[tuple[dt.datetime, dt.datetime]]],
    config: EventConfig,
    affected_by_wagon: dict[str, list[_Chain]],
) -> Iterator[_DetectTask]:
    """The dirty wagons' touched chains as windows (:func:`_load_groups`), in wagon order,
    packed into chunks of at most about ``_LOAD_ROWS`` samples (whole windows; a longer one
    alone), each chunk's samples read with one query (``q_events_chunk_samples.sql``); the
    wagons' files are read with one query (``q_events_files.sql``). Records each wagon's
    touched chains in ``affected_by_wagon``. Read lazily, between the wagons' transactions."""
    wagon_ids = sorted(by_wagon)
    files_by_wagon: dict[str, list[tuple[dt.datetime, dt.datetime, int]]] = {}
    if wagon_ids:
        rows = wh.con.execute(sql("q_events_files"), {"wagon_ids": wagon_ids}).fetchall()
        for wagon_id, first, last, n in rows:
            files_by_wagon.setdefault(wagon_id, []).append((first, last, n))
    chunk: list[_Window] = []
    held = 0
    for wagon_id in wagon_ids:
        chains = _chains(files_by_wagon.get(wagon_id, []), config.max_gap_s)
        touched = _merged(by_wagon[wagon_id], dt.timedelta(seconds=config.max_gap_s))
        affected = [c for c in chains if _overlaps(touched, c.from_utc, c.to_utc)]
        affected_by_wagon[wagon_id] = affected
        groups = _load_groups(chains, affected)
        windows = [
            _Window(
                wagon_id,
                tuple((c.from_utc, c.to_utc) for c in group),
                _span_rows(chains, group),
                last=i == len(groups) - 1,
            )
            for i, group in enumerate(groups)
        ] or [_Window(wagon_id, (), 0, last=True)]
        for window in windows:
            if chunk and held + window.rows > _LOAD_ROWS:
                yield _chunk_task(wh, chunk, config)
                chunk, held = [], 0
            chunk.append(window)
            held += window.rows
    if chunk:
        yield _chunk_task(wh, chunk, config)


def _chunk_task(wh: Warehouse, windows: list[_Window], config: EventConfig) -> _DetectTask:
    """A chunk of windows with the samples of those with chains, read with one query (their
    ``part_ix`` counts them in order; none read when no window has chains)."""
    reading = [w for w in windows if w.chains]
    samples = None
    if reading:
        params = {
            "wagon_ids": [w.wagon_id for w in reading],
            "from_utc": [w.chains[0][0] for w in reading],
            "to_utc": [w.chains[-1][1] for w in reading],
        }
        samples = wh.con.sql(sql("q_events_chunk_samples"), params=params).to_arrow_table()
    return _DetectTask(tuple(windows), samples, config)


def _span_rows(chains: list[_Chain], group: list[_Chain]) -> int:
    """Samples of the chains from ``group``'s first to its last (those between included)."""
    first, last = chains.index(group[0]), chains.index(group[-1])
    return sum(c.rows for c in chains[first : last + 1])


def _load_groups(chains: list[_Chain], affected: list[_Chain]) -> list[list[_Chain]]:
    """The ``affected`` chains in groups read by one query: consecutive ones spanning at
    most ``_LOAD_ROWS`` samples (the chains between them included), or one longer chain."""
    position = {chain: i for i, chain in enumerate(chains)}
    rows_before = list(itertools.accumulate((c.rows for c in chains), initial=0))
    groups: list[list[_Chain]] = []
    group: list[_Chain] = []
    for chain in [*affected, None]:
        if group and (
            chain is None
            or rows_before[position[chain] + 1] - rows_before[position[group[0]]] > _LOAD_ROWS
        ):
            groups.append(group)
            group = []
        if chain is not None:
            group.append(chain)
    return groups


@dataclass(frozen=True)
class _Detected:
    """A wagon's touched chains and their events, detected again: what its transaction
    brings in line."""

    wagon_id: str
    affected: list[_Chain]
    events: pl.DataFrame


def _update_wagons(
    wh: Warehouse,
    batch: list[_Detected],
    dirty: dict[str, list[tuple[dt.datetime, dt.datetime]]],
    holding: set[str],
    update: EventUpdate,
) -> None:
    """Whole wagons, one transaction: each wagon's touched chains' events (detected again)
    brought in line with the stored ones (:func:`_line_up`), then one delete, one insert and
    the wagons' dirty ranges (``dirty``) removed. A wagon not in ``holding`` holds no events
    (:func:`_holding_events`): none are read to compare. ``update`` counts them once
    committed."""
    con = wh.con
    with wh.transaction():
        lined = [
            _line_up(wh, wagon, dirty[wagon.wagon_id], wagon.wagon_id in holding) for wagon in batch
        ]
        gone = [i for wagon_gone, _, _ in lined for i in wagon_gone]
        fresh = [frame for _, frame, _ in lined if frame.height]
        if gone:
            con.execute(sql("q_events_delete"), {"ids": gone})
        if fresh:
            _insert_events(con, pl.concat(fresh))
        con.execute(sql("q_events_clear_dirty"), {"wagon_ids": [w.wagon_id for w in batch]})
    for wagon, (wagon_gone, frame, unchanged) in zip(batch, lined, strict=True):
        update.wagons += 1
        update.chains += len(wagon.affected)
        update.added += frame.height
        update.removed += len(wagon_gone)
        update.unchanged += unchanged
        update.changed_ids.extend(sorted(frame["event_id"].to_list()))


def _line_up(
    wh: Warehouse, wagon: _Detected, dirty: list[tuple[dt.datetime, dt.datetime]], stored: bool
) -> tuple[list[str], pl.DataFrame, int]:
    """A wagon's stored events to delete (changed or vanished), its new events to insert
    (new or changed), how many are unchanged. ``stored=False``: it holds none to read."""
    windows = _merged([(c.from_utc, c.to_utc) for c in wagon.affected] + dirty, dt.timedelta(0))
    new = wagon.events
    old = _events_in(wh, wagon.wagon_id, windows) if stored else _NO_EVENTS
    new_rows = {row["event_id"]: row for row in new.iter_rows(named=True)}
    old_rows = {row["event_id"]: row for row in old.iter_rows(named=True)}
    gone = [i for i, row in old_rows.items() if new_rows.get(i) != row]
    fresh = [i for i, row in new_rows.items() if old_rows.get(i) != row]
    frame = new if len(fresh) == new.height else new.filter(pl.col("event_id").is_in(fresh))
    return gone, frame, len(new_rows) - len(fresh)


def _insert_events(con: duckdb.DuckDBPyConnection, events: pl.DataFrame) -> None:
    """Insert ``events`` (the detection's columns), stamped with ``detected_utc`` now."""
    batch = events.with_columns(pl.lit(_utc_now()).alias("detected_utc"))
    con.register("event_batch", batch)
    try:
        con.execute(sql("q_insert_events"))
    finally:
        con.unregister("event_batch")


_NO_EVENTS = pl.DataFrame(schema=EVENT_COLUMNS)


def _holding_events(wh: Warehouse, wagon_ids: list[str]) -> set[str]:
    """Which of ``wagon_ids`` hold stored events, in one query: the others' (every wagon of
    a first run) have none to compare with, and are not read again one by one."""
    if not wagon_ids:
        return set()
    rows = wh.con.execute(sql("q_events_holding_wagons"), {"wagon_ids": wagon_ids}).fetchall()
    return {str(r[0]) for r in rows}


def _events_in(
    wh: Warehouse, wagon_id: str, windows: list[tuple[dt.datetime, dt.datetime]]
) -> pl.DataFrame:
    """The stored events of a wagon overlapping one of the sorted disjoint ``windows``."""
    if not windows:
        return pl.DataFrame(schema=EVENT_COLUMNS)
    stored = wh.con.sql(
        sql("q_events_stored"),
        params={"wagon_id": wagon_id, "from_utc": windows[0][0], "to_utc": windows[-1][1]},
    ).pl()
    keep = [
        _overlaps(windows, start, end)
        for start, end in zip(stored["start_utc"], stored["end_utc"], strict=True)
    ]
    return stored.filter(pl.Series(keep, dtype=pl.Boolean)).cast(EVENT_COLUMNS)


def _utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(tzinfo=None)
