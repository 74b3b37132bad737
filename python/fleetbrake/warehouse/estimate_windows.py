"""The storage of the contact estimates (interface.md v3, ``v_contact_estimates``): per second
inside the *estimate windows*, per minute elsewhere (:func:`compact_estimates`).

::

    from fleetbrake.warehouse.estimate_windows import compact_estimates

    done = compact_estimates(wh.con, [("SGG-0001", span_start_utc, span_end_utc)], "declared")
    done.minutes, done.seconds_removed

The estimator runs through every logged second and its stage stores a row per second
(``resolution_s`` = 1); a run then compacts the spans it estimated, after its flags are
judged. The estimate windows of a wagon and revision: every event window of the revision's
predictions, every flag's window, every stretch of per-second rows whose unexplained power's
95 % band excludes zero, each widened by :data:`WINDOW_MARGIN_S` on both sides and rounded
outward to whole minutes, so that a minute is either all its per-second rows or one minute
row. Outside them a minute's per-second rows become one row (``resolution_s`` = 60) at the
minute's start: the means its means, the maxima and upper bounds its largest, the lower
bounds its smallest, the innovation and its sd their root mean squares
(``warehouse/sql/q_estimates_compact_*.sql``, each bounded in time by the ranges so that
DuckDB skips the row groups of the rest of the history). Compacting again changes nothing:
minute rows are never aggregated again, and the per-second rows left are those of the
windows, which they define again.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import dataclass

import duckdb
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.warehouse.sqlfiles import sql

__all__ = ["WINDOW_MARGIN_S", "Compaction", "EstimateRange", "compact_estimates"]

WINDOW_MARGIN_S = 60.0
"""An estimate window is widened by this much on both sides (interface.md, v3)."""

EstimateRange = tuple[str, dt.datetime | None, dt.datetime | None]
"""(wagon_id, start_utc, end_utc): a wagon's time range to compact, both ends included
(rounded outward to whole minutes); None: unbounded. A run gives the spans it estimated (a
span: a stretch of a wagon's samples without a gap of 6 h, so that no minute holds two)."""


@dataclass(frozen=True)
class Compaction:
    """What :func:`compact_estimates` did."""

    minutes: int
    """Minute rows written."""
    seconds_removed: int
    """Per-second rows they replaced."""


def compact_estimates(
    con: duckdb.DuckDBPyConnection,
    ranges: Sequence[EstimateRange],
    revision: str,
    *,
    transaction: bool = True,
) -> Compaction:
    """Replace the per-second rows of ``revision`` in ``ranges`` outside the estimate windows
    by per-minute rows, in DuckDB, in one transaction (``transaction=False``: in the caller's).
    Idempotent."""
    if not ranges:
        return Compaction(0, 0)
    table = pa.table(
        {
            "wagon_id": pa.array([r[0] for r in ranges], pa.string()),
            "start_utc": pa.array([r[1] for r in ranges], pa.timestamp("us")),
            "end_utc": pa.array([r[2] for r in ranges], pa.timestamp("us")),
        }
    )
    starts = [r[1] for r in ranges if r[1] is not None]
    ends = [r[2] for r in ranges if r[2] is not None]
    reach = dt.timedelta(seconds=WINDOW_MARGIN_S + 180.0)  # the windows read around them
    scan = {
        "scan_from_utc": min(starts) - reach if len(starts) == len(ranges) else None,
        "scan_to_utc": max(ends) + reach if len(ends) == len(ranges) else None,
    }
    if transaction:
        con.execute("BEGIN TRANSACTION")
    try:
        con.register("compact_ranges", table)
        try:
            con.execute(
                sql("q_estimates_compact_minutes"),
                {"revision": revision, "margin_s": WINDOW_MARGIN_S} | scan,
            )
        finally:
            con.unregister("compact_ranges")
        first, end = con.execute(sql("q_estimates_compact_bounds")).fetchone() or (None, None)
        minutes = removed = 0
        if first is not None:
            bounds = {"revision": revision, "scan_from_utc": first, "scan_to_utc": end}
            minutes = _count(con.execute(sql("q_estimates_compact_insert"), bounds))
            removed = _count(con.execute(sql("q_estimates_compact_delete"), bounds))
        con.execute(sql("q_estimates_compact_drop"))
        if transaction:
            con.execute("COMMIT")
    except BaseException:
        if transaction:
            con.execute("ROLLBACK")
        raise
    return Compaction(minutes, removed)


def _count(result: duckdb.DuckDBPyConnection) -> int:
    """The row count an INSERT or DELETE reports."""
    row = result.fetchone()
    return 0 if row is None else int(row[0])
