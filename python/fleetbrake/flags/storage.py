"""The flags' rows in the warehouse: a span's findings as flags with stable ids
(:func:`flag_ids`), its rows of ``flags`` (those starting in the span) replaced with its
judgement recorded in ``flagged_spans`` (:func:`store_flags`), and what is stored read back
(:func:`stored_flags`, :func:`stale_spans`).

``flag_id`` is ``<kind>-<wagon>-<start as YYYYMMDDTHHMMSS>`` (``-2``, ... if taken), so the
same data give the same ids, and a flag found again keeps its ``detected_utc``.

::

    from fleetbrake.flags.storage import stale_spans, stored_flags

    stale_spans(wh, "declared", FlagConfig())    # the spans a run must judge again
    stored_flags(wh)                             # every flag stored
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import polars as pl

from fleetbrake.flags.config import FlagConfig
from fleetbrake.flags.records import Finding, Flag
from fleetbrake.ingest.spans import LedgerSpan, Span, SpanKey, span_windows
from fleetbrake.simulation.store import ledger_spans, utc_now
from fleetbrake.warehouse.connection import Warehouse, sql

if TYPE_CHECKING:
    import duckdb

__all__ = [
    "flag_ids",
    "flag_range",
    "flagged_spans",
    "stale_spans",
    "store_flags",
    "stored_flags",
]


def flag_ids(wagon_id: str, findings: Sequence[Finding]) -> list[Flag]:
    """The findings as flags, with their stable ids (see the module docstring)."""
    taken: set[str] = set()
    flags = []
    for f in sorted(findings, key=lambda f: (f.start_utc, f.kind, f.end_utc, f.evidence)):
        base = f"{f.kind}-{wagon_id}-{f.start_utc:%Y%m%dT%H%M%S}"
        flag_id, k = base, 1
        while flag_id in taken:
            k += 1
            flag_id = f"{base}-{k}"
        taken.add(flag_id)
        flags.append(
            Flag(
                flag_id=flag_id,
                wagon_id=wagon_id,
                event_id=f.event_id,
                kind=f.kind,
                severity=f.severity,
                start_utc=f.start_utc,
                end_utc=f.end_utc,
                evidence=f.evidence,
                detail=f.detail,
            )
        )
    return flags


_FLAG_SCHEMA = pl.Schema(
    {
        "flag_id": pl.String(),
        "wagon_id": pl.String(),
        "event_id": pl.String(),
        "kind": pl.String(),
        "severity": pl.String(),
        "start_utc": pl.Datetime("us"),
        "end_utc": pl.Datetime("us"),
        "evidence": pl.String(),
        "detected_utc": pl.Datetime("us"),
    }
)


def stale_spans(wh: Warehouse, revision_name: str, config: FlagConfig) -> list[SpanKey]:
    """The spans whose stored flags are out of date for ``revision_name`` and ``config``
    (``q_flags_stale_spans.sql``; ``flagged_spans`` records each judgement): never judged
    with the revision, judged from other data, before their timeline or estimates of the
    revision were written, with other thresholds (:meth:`FlagConfig.key`), or whose rows of
    ``flags`` are not the ones their judgement stored. What a run must judge besides the
    spans its stages changed, so that a run that stopped between its simulation and its flags
    leaves nothing stale behind (``fleetbrake.app.run``)."""
    rows = wh.con.execute(
        sql("q_flags_stale_spans"), {"revision": revision_name, "config_key": config.key()}
    ).fetchall()
    return [(str(w), start) for w, start in rows]


def flagged_spans(wh: Warehouse, revision_name: str) -> dict[SpanKey, LedgerSpan]:
    """The spans judged with ``revision_name``: their data key, and their thresholds' key as
    the model key."""
    return ledger_spans(wh, "q_flags_flagged_spans", revision_name)


def stored_flags(wh: Warehouse) -> list[Flag]:
    """Every flag stored (``q_flags_all.sql``), by wagon, start and kind: the fleet's flags
    after a whole ``run``, those it judged and those that stood."""
    rows = wh.con.execute(sql("q_flags_all")).fetchall()
    return [
        Flag(
            flag_id=str(flag_id),
            wagon_id=str(wagon_id),
            event_id=None if event_id is None else str(event_id),
            kind=str(kind),
            severity=str(severity),
            start_utc=start_utc,
            end_utc=end_utc,
            evidence=str(evidence),
        )
        for flag_id, wagon_id, event_id, kind, severity, start_utc, end_utc, evidence in rows
    ]


def flag_range(span: Span | LedgerSpan) -> tuple[str, dt.datetime, dt.datetime]:
    """The time range whose flags belong to a span: those starting from its first sample to
    a second after its last (a finding ends, and may start, on the second after a sample)."""
    return (span.wagon_id, span.start_utc, span.end_utc + dt.timedelta(seconds=1))


def store_flags(
    wh: Warehouse,
    judged: Sequence[tuple[Span, int]],
    flags: Sequence[Flag],
    revision_name: str,
    config_key: str,
    orphans: Sequence[LedgerSpan] = (),
) -> None:
    """Replace the flags of the ``judged`` spans (each with its count of ``flags``) in one
    transaction, recording that they were judged with ``revision_name`` and the thresholds of
    ``config_key`` (``flagged_spans``), and remove the flags and judgements of the spans that
    no longer exist (``orphans``); a flag identical to a stored one keeps its
    ``detected_utc``."""
    now = utc_now()
    ranges = [flag_range(span) for span, _ in judged] + [flag_range(o) for o in orphans]
    if not ranges:
        return
    window = span_windows(ranges)
    stamps = pl.DataFrame(
        {
            "wagon_id": [span.wagon_id for span, _ in judged],
            "model_revision": [revision_name] * len(judged),
            "span_start_utc": [span.start_utc for span, _ in judged],
            "span_end_utc": [span.end_utc for span, _ in judged],
            "data_key": [span.data_key for span, _ in judged],
            "config_key": [config_key] * len(judged),
            "flag_count": [count for _, count in judged],
            "updated_utc": [now] * len(judged),
        },
        schema_overrides={
            "span_start_utc": pl.Datetime("us"),
            "span_end_utc": pl.Datetime("us"),
            "updated_utc": pl.Datetime("us"),
            "flag_count": pl.Int64(),
        },
    )
    with wh.transaction() as con:
        old = con.execute(sql("q_flags_stored_spans"), window).fetchall()
        kept = {tuple(r[:7]): r[7] for r in old}
        con.execute(sql("q_flags_delete_spans"), window)
        con.execute(sql("q_flags_delete_flagged_spans"), window)
        if flags:
            _insert_flags(con, flags, kept, now)
        if judged:
            con.register("flagged_batch", stamps)
            try:
                con.execute(sql("q_flags_insert_flagged_spans"))
            finally:
                con.unregister("flagged_batch")


def _insert_flags(
    con: duckdb.DuckDBPyConnection,
    flags: Sequence[Flag],
    kept: Mapping[tuple[object, ...], dt.datetime],
    now: dt.datetime,
) -> None:
    """Insert ``flags``; one identical to a stored one (``kept``) keeps its
    ``detected_utc``, the others are detected ``now``."""
    rows = pl.DataFrame(
        [
            {
                "flag_id": f.flag_id,
                "wagon_id": f.wagon_id,
                "event_id": f.event_id,
                "kind": f.kind,
                "severity": f.severity,
                "start_utc": f.start_utc,
                "end_utc": f.end_utc,
                "evidence": f.evidence,
                "detected_utc": kept.get(
                    (
                        f.flag_id,
                        f.event_id,
                        f.kind,
                        f.severity,
                        f.start_utc,
                        f.end_utc,
                        f.evidence,
                    ),
                    now,
                ),
            }
            for f in flags
        ],
        schema=_FLAG_SCHEMA,
    )
    con.register("flag_batch", rows)
    try:
        con.execute(sql("q_flags_insert"))
    finally:
        con.unregister("flag_batch")
