"""Spans: the unit of work of the simulation, the estimate and the flags.

A span is a maximal stretch of a wagon's samples without a gap longer than
:data:`SPAN_GAP_S` (``ChainParams.bridge_max_s``, 6 h: the cut the simulation makes), keyed
by (``wagon_id``, ``span_start_utc``) and stored with its end, its sample count and a key of
its data (``spans``, ``warehouse/sql/schema_pipeline.sql``). Each stage keeps a ledger of the
spans it computed (``simulated_spans``, ``estimated_spans``, ``flagged_spans``) and
recomputes exactly the spans whose key changed, deleting the results of the spans that no
longer exist (two spans merged by a file landing between them).

::

    from fleetbrake.ingest.spans import stored_spans, update_spans

    update = update_spans(wh)       # after the event detection: cut where files changed
    for span in stored_spans(wh):
        span.wagon_id, span.start_utc, span.end_utc, span.data_key

:func:`update_spans` reads the ``files`` table for the files added, removed or replaced
since it last ran (``spanned_files``), widens each one's time range to the stored spans
within :data:`SPAN_GAP_S` of it, and cuts the samples of those ranges alone again
(``q_spans_cut.sql``): its cost follows the new files, not the history.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = [
    "SPAN_GAP_S",
    "LedgerSpan",
    "Span",
    "SpanKey",
    "SpanUpdate",
    "envelope",
    "orphan_spans",
    "ranges_of",
    "span_windows",
    "stale_spans",
    "stored_spans",
    "update_spans",
]

SPAN_GAP_S = 6 * 3600.0
"""s: a gap longer than this ends a span (the default of the simulation's
``ChainParams.bridge_max_s``, which says why 6 h)."""

SpanKey = tuple[str, dt.datetime]
"""(``wagon_id``, ``span_start_utc``): a span's key in every ledger."""


@dataclass(frozen=True)
class Span:
    """A row of ``spans``."""

    wagon_id: str
    start_utc: dt.datetime
    end_utc: dt.datetime
    sample_rows: int
    data_key: str

    @property
    def key(self) -> SpanKey:
        return (self.wagon_id, self.start_utc)

    @property
    def label(self) -> str:
        """How an engine and a log name it: ``wagon W span START``."""
        return f"{self.wagon_id}@{self.start_utc:%Y-%m-%dT%H:%M:%S}"

    def __str__(self) -> str:
        return f"wagon {self.wagon_id} span {self.start_utc:%Y-%m-%d %H:%M:%S}"


@dataclass(frozen=True)
class LedgerSpan:
    """A row of a stage's ledger (``simulated_spans``, ``estimated_spans``,
    ``flagged_spans``): the span as the stage computed it, from what and when."""

    wagon_id: str
    start_utc: dt.datetime
    end_utc: dt.datetime
    data_key: str
    model_key: str
    written_utc: dt.datetime

    @property
    def key(self) -> SpanKey:
        return (self.wagon_id, self.start_utc)


@dataclass
class SpanUpdate:
    """What :func:`update_spans` did: the spans it stored (new or cut again) and the ones it
    removed, by wagon."""

    stored: list[Span] = field(default_factory=list)
    removed: list[tuple[str, dt.datetime, dt.datetime]] = field(default_factory=list)


def _span(row: Sequence[object]) -> Span:
    wagon_id, start, end, rows, key = row
    assert isinstance(start, dt.datetime) and isinstance(end, dt.datetime)
    return Span(str(wagon_id), start, end, int(str(rows)), str(key))


def stored_spans(wh: Warehouse, wagon_ids: Iterable[str] | None = None) -> list[Span]:
    """The stored spans (of ``wagon_ids``; None: of every wagon), by wagon and start."""
    if wagon_ids is None:
        rows = wh.con.execute(sql("q_spans_all")).fetchall()
    else:
        ids = sorted(set(wagon_ids))
        rows = wh.con.execute(sql("q_spans_wagons"), {"wagon_ids": ids}).fetchall() if ids else []
    return [_span(r) for r in rows]


def span_windows(
    ranges: Sequence[tuple[str, dt.datetime, dt.datetime]],
) -> dict[str, list[object]]:
    """The parameters of a query over time ranges of wagons (``$wagon_ids``, ``$from_utc``,
    ``$to_utc``: lists of the same length)."""
    return {
        "wagon_ids": [r[0] for r in ranges],
        "from_utc": [r[1] for r in ranges],
        "to_utc": [r[2] for r in ranges],
    }


def envelope(ranges: Sequence[tuple[str, dt.datetime, dt.datetime]]) -> dict[str, dt.datetime]:
    """``$lo_utc`` and ``$hi_utc``: the earliest start and latest end of ``ranges`` (the
    range deletes of large tables skip the row groups outside by their time bounds)."""
    return {"lo_utc": min(r[1] for r in ranges), "hi_utc": max(r[2] for r in ranges)}


def _merge(
    intervals: list[tuple[dt.datetime, dt.datetime]], gap_s: float
) -> list[list[dt.datetime]]:
    """``intervals`` merged where they overlap or lie at most ``gap_s`` apart, in order."""
    merged: list[list[dt.datetime]] = []
    for a, b in sorted(intervals):
        if merged and (a - merged[-1][1]).total_seconds() <= gap_s:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return merged


def _regions(
    changed: Mapping[str, list[tuple[dt.datetime, dt.datetime]]],
    stored: Mapping[str, list[Span]],
    gap_s: float,
) -> list[tuple[str, dt.datetime, dt.datetime]]:
    """The ranges to cut again, per wagon: the changed files' time ranges, widened to every
    stored span within ``gap_s`` of them (and of the spans so taken in), merged."""
    out = []
    for wagon_id, ranges in sorted(changed.items()):
        regions = _merge(list(ranges), gap_s)
        spans = stored.get(wagon_id, [])
        while True:
            near = [
                (s.start_utc, s.end_utc)
                for s in spans
                if any(
                    (s.start_utc - b).total_seconds() <= gap_s
                    and (a - s.end_utc).total_seconds() <= gap_s
                    for a, b in regions
                )
            ]
            widened = _merge([(a, b) for a, b in regions] + near, gap_s)
            if widened == regions:
                break
            regions = widened
        out += [(wagon_id, a, b) for a, b in regions]
    return out


def update_spans(wh: Warehouse, gap_s: float = SPAN_GAP_S) -> SpanUpdate:
    """Cut the spans again where files were added, removed or replaced since the last call
    (after the event detection: a span's key holds its events), in one transaction: the
    changed files' time ranges widened to the stored spans near them, only their samples
    read (``q_spans_cut.sql``), their stored spans replaced and the files recorded as seen.
    A second call without new files reads the ``files`` table and nothing else."""
    report = SpanUpdate()
    rows = wh.con.execute(sql("q_spans_changed_files")).fetchall()
    if not rows:
        return report
    changed: dict[str, list[tuple[dt.datetime, dt.datetime]]] = {}
    for _, wagon_id, first, last, _ in rows:
        changed.setdefault(str(wagon_id), []).append((first, last))
    file_ids = sorted({int(r[0]) for r in rows})
    stored: dict[str, list[Span]] = {}
    for span in stored_spans(wh, changed):
        stored.setdefault(span.wagon_id, []).append(span)
    regions = _regions(changed, stored, gap_s)
    window = span_windows(regions)
    cut = wh.con.sql(sql("q_spans_cut"), params={**window, "gap_s": gap_s}).pl()
    report.stored = [_span(r) for r in cut.rows()]
    fresh = {s.key for s in report.stored}
    for wagon_id, a, b in regions:
        report.removed += [
            (s.wagon_id, s.start_utc, s.end_utc)
            for s in stored.get(wagon_id, [])
            if s.start_utc <= b and s.end_utc >= a and s.key not in fresh
        ]
    with wh.transaction() as con:
        con.execute(sql("q_spans_delete"), window)
        if cut.height:
            con.register("span_batch", cut)
            try:
                con.execute(sql("q_spans_insert"))
            finally:
                con.unregister("span_batch")
        con.execute(sql("q_spans_delete_files"), {"file_ids": file_ids})
        con.execute(sql("q_spans_insert_files"), {"file_ids": file_ids})
    return report


def orphan_spans(ledger: Mapping[SpanKey, LedgerSpan], spans: Iterable[Span]) -> list[LedgerSpan]:
    """The ledger's spans that are no longer stored spans (merged, cut shorter or longer, or
    gone): a stage deletes their results before it writes (:func:`stale_spans`)."""
    current = {(s.wagon_id, s.start_utc, s.end_utc) for s in spans}
    return [r for r in ledger.values() if (r.wagon_id, r.start_utc, r.end_utc) not in current]


def stale_spans(
    spans: Iterable[Span],
    ledger: Mapping[SpanKey, LedgerSpan],
    model_key: Callable[[Span], str | None],
    forced: Collection[SpanKey] = (),
) -> tuple[list[tuple[Span, str]], list[LedgerSpan]]:
    """What a stage must do: the spans to compute, each with its model key (``model_key``;
    None: the span is not computed, its wagon has no registry entry), and the ledger's
    orphans (:func:`orphan_spans`), whose results are deleted first. A span is computed
    when it is ``forced``, never was, was from another ``data_key``, ``model_key`` or end,
    or overlaps an orphan (its rows were deleted with the orphan's)."""
    spans = list(spans)
    orphans = orphan_spans(ledger, spans)
    todo = []
    for span in spans:
        key = model_key(span)
        if key is None:
            continue
        stored = ledger.get(span.key)
        overlaps = any(
            o.wagon_id == span.wagon_id
            and o.start_utc <= span.end_utc
            and o.end_utc >= span.start_utc
            for o in orphans
        )
        if (
            span.key in forced
            or stored is None
            or overlaps
            or (stored.data_key, stored.model_key, stored.end_utc)
            != (span.data_key, key, span.end_utc)
        ):
            todo.append((span, key))
    return todo, orphans


def ranges_of(
    spans: Iterable[Span | LedgerSpan],
) -> list[tuple[str, dt.datetime, dt.datetime]]:
    """Each span's (``wagon_id``, first, last sample): what the range queries take
    (:func:`span_windows`)."""
    return [(s.wagon_id, s.start_utc, s.end_utc) for s in spans]
