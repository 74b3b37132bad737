"""The ingestion ledger: what the warehouse holds about each file, and the batches that write
new files to it.

A file's ``files`` row, its samples and the time range whose events must be recomputed
(``event_dirty``) are always written in the same transaction, with the removal of what its
path held before (:class:`Batch`). A file recorded with the same bytes is not stored again
(:func:`unchanged`): its row only takes the size and modification time it has now.

Every row read is stored or rejected: ``files.rows_rejected`` counts the rejected ones,
``files.reason`` sums them up (each kind with its lines) and ``file_rejections`` holds every
rejected run of lines with why (``v_file_rejections``), written with the file's row.
"""

from __future__ import annotations

import datetime as dt
import time
from dataclasses import dataclass

import duckdb
import polars as pl

from fleetbrake.engine.writer import WriteBehind
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.prepare import Prepared
from fleetbrake.ingest.quarantine import RETRIED_CODES
from fleetbrake.ingest.scan import LogEntry
from fleetbrake.ingest.validation import Repairs
from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = ["Batch", "FileResult", "Known", "known_files", "needs_reading", "unchanged"]


@dataclass(frozen=True)
class FileResult:
    """What this run did with one file."""

    path: str
    wagon_id: str | None
    status: str
    """``ingested`` or ``quarantined``."""
    rows: int
    reason: str | None = None
    """Why it is quarantined; for an ingested file, which rows were rejected and why."""
    rows_rejected: int = 0
    """Rows read but not stored (each named in ``reason``)."""
    repairs: str | None = None
    replaced: bool = False
    """The path was recorded before: with other bytes, or quarantined for a cause that is
    judged again at every run (registry, unreadable, reader error)."""
    size_bytes: int | None = None
    mtime_ns: int | None = None
    """The size and modification time the ledger recorded for it (as stat saw the file
    before it was read: a file written meanwhile has others now)."""


@dataclass(frozen=True)
class Known:
    """What the warehouse already holds about a path."""

    file_id: int
    sha256: str
    size_bytes: int
    mtime_ns: int
    status: str
    quarantine_code: str | None
    reason: str | None
    wagon_id: str | None
    first_utc: dt.datetime | None
    last_utc: dt.datetime | None


def known_files(wh: Warehouse) -> dict[str, Known]:
    rows = wh.con.execute(sql("q_ingest_known_files")).fetchall()
    return {row[0]: Known(*row[1:]) for row in rows}


def needs_reading(entry: LogEntry, known: Known | None, config: IngestConfig) -> bool:
    if known is None or config.verify_hashes or known.quarantine_code in RETRIED_CODES:
        return True
    return (known.size_bytes, known.mtime_ns) != (entry.size_bytes, entry.mtime_ns)


def _utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(tzinfo=None)


_FILES_SCHEMA = pl.Schema(
    {
        "file_id": pl.Int64(),
        "path": pl.String(),
        "wagon_id": pl.String(),
        "sha256": pl.String(),
        "size_bytes": pl.Int64(),
        "mtime_ns": pl.Int64(),
        "status": pl.String(),
        "quarantine_code": pl.String(),
        "reason": pl.String(),
        "rows": pl.Int64(),
        "rows_in_file": pl.Int64(),
        "rows_rejected": pl.Int64(),
        "rows_no_time": pl.Int64(),
        "rows_outside_session": pl.Int64(),
        "rows_duplicate": pl.Int64(),
        "rows_out_of_order": pl.Int64(),
        "cells_unparsable": pl.Int64(),
        "block_temp_faults": pl.Int64(),
        "partial_row_dropped": pl.Boolean(),
        "repairs": pl.String(),
        "first_utc": pl.Datetime("us"),
        "last_utc": pl.Datetime("us"),
        "ingested_utc": pl.Datetime("us"),
    }
)
"""Columns of a ``files`` row, as :class:`Batch` collects them."""

_DIRTY_SCHEMA = pl.Schema(
    {
        "wagon_id": pl.String(),
        "from_utc": pl.Datetime("us"),
        "to_utc": pl.Datetime("us"),
        "file_id": pl.Int64(),
    }
)

_REJECTIONS_SCHEMA = pl.Schema(
    {
        "file_id": pl.Int64(),
        "first_line": pl.Int64(),
        "last_line": pl.Int64(),
        "rows": pl.Int64(),
        "reason": pl.String(),
    }
)
"""Columns of a ``file_rejections`` row: a run of rejected lines of one file."""

_REFRESH_SCHEMA = pl.Schema(
    {"file_id": pl.Int64(), "size_bytes": pl.Int64(), "mtime_ns": pl.Int64()}
)
"""Columns of a ledger refresh (:meth:`Batch.refresh`)."""


def _file_row(prepared: Prepared, file_id: int) -> dict[str, object]:
    """The ``files`` row of a prepared file."""
    entry, parsed, problem = prepared.entry, prepared.parsed, prepared.quarantine
    repairs = parsed.repairs if parsed is not None else Repairs()
    rejected = repairs.rejected_text()
    if problem is not None:
        reason: str | None = problem.reason
    else:
        reason = f"{entry.relpath}: {rejected}" if rejected is not None else None
    return {
        "file_id": file_id,
        "path": entry.relpath,
        "wagon_id": prepared.wagon_id,
        "sha256": prepared.sha256,
        "size_bytes": entry.size_bytes,
        "mtime_ns": entry.mtime_ns,
        "status": "quarantined" if problem is not None else "ingested",
        "quarantine_code": problem.code if problem else None,
        "reason": reason,
        "rows": parsed.frame.height if parsed is not None else 0,
        "rows_in_file": repairs.rows_in_file if parsed is not None else None,
        "rows_rejected": repairs.rows_rejected if parsed is not None else None,
        "rows_no_time": repairs.rows_no_time,
        "rows_outside_session": repairs.rows_outside_session,
        "rows_duplicate": repairs.rows_duplicate,
        "rows_out_of_order": repairs.rows_out_of_order,
        "cells_unparsable": repairs.cells_unparsable,
        "block_temp_faults": repairs.block_temp_faults,
        "partial_row_dropped": repairs.partial_row_dropped,
        "repairs": repairs.text(),
        "first_utc": parsed.first_utc if parsed is not None else None,
        "last_utc": parsed.last_utc if parsed is not None else None,
        "ingested_utc": _utc_now(),
    }


@dataclass(frozen=True)
class _Held:
    """A batch handed to the writer thread (:meth:`Batch.flush`): its files' rows, samples,
    rejected runs of lines, dirty ranges, the file ids they replace and the ledger refreshes."""

    files: list[dict[str, object]]
    samples: list[pl.DataFrame]
    rejections: list[dict[str, object]]
    dirty: list[dict[str, object]]
    replaced: list[int]
    refreshed: list[dict[str, object]]


class Batch:
    """Partitions of files written together, in one transaction, once they hold
    ``batch_rows`` rows (or ``batch_files`` files).

    A partition, and so a file, is never split: a file's ``files`` row, its samples and its
    dirty time range (and the removal of what its path held before) are in the same
    transaction, with the other files of its partition and batch. Few large inserts are much
    faster in DuckDB than many small ones (full row groups are written straight to the
    database file, in parallel).

    The transactions run on a thread of their own (:class:`~fleetbrake.engine.writer.WriteBehind`),
    one at a time and in order, while the caller gathers the next batch and keeps the
    engine's workers fed (a writer blocked in its inserts leaves them idle: the ingestion
    waits 3.3-3.7 s on writes per 100 wagon-days that way, 0.6-0.8 s with the thread,
    ``docs/decisions/0007-reading-and-writing-in-chunks.md``). The caller must not use the
    warehouse's connection until the block ends (the ingestion's loop does not).
    """

    def __init__(self, wh: Warehouse, config: IngestConfig) -> None:
        self._wh = wh
        self._config = config
        self.write_s = 0.0
        """Seconds the caller waited for its writes (a batch's transaction not yet done when
        the next is handed over, the last one), of the whole ingestion."""
        self._writer: WriteBehind[_Held] = WriteBehind(self._write)
        self._clear()

    def _clear(self) -> None:
        self._files: list[dict[str, object]] = []
        self._samples: list[pl.DataFrame] = []
        self._rejections: list[dict[str, object]] = []
        self._dirty: list[dict[str, object]] = []
        self._replaced: list[int] = []
        self._refreshed: list[dict[str, object]] = []
        self._rows = 0

    def add(self, prepared: Prepared, known: Known | None, file_id: int) -> FileResult:
        """Queue one file (replacing what its path held); see :meth:`end_partition`."""
        row = _file_row(prepared, file_id)
        if known is not None:
            self._replaced.append(known.file_id)
            if known.status == "ingested" and known.first_utc is not None:
                self._dirty.append(
                    _dirty_row(known.wagon_id, known.first_utc, known.last_utc, file_id)
                )
        self._files.append(row)
        parsed = prepared.parsed
        if parsed is not None:
            self._rejections.extend(
                {
                    "file_id": file_id,
                    "first_line": run.first_line,
                    "last_line": run.last_line,
                    "rows": run.rows,
                    "reason": run.why,
                }
                for run in parsed.repairs.rejected
            )
        if parsed is not None and parsed.frame.height:
            self._samples.append(
                parsed.frame.with_columns(
                    pl.lit(prepared.wagon_id, dtype=pl.String).alias("wagon_id"),
                    pl.lit(file_id, dtype=pl.Int64).alias("file_id"),
                )
            )
            self._dirty.append(
                _dirty_row(prepared.wagon_id, parsed.first_utc, parsed.last_utc, file_id)
            )
            self._rows += parsed.frame.height
        return FileResult(
            path=prepared.entry.relpath,
            wagon_id=prepared.wagon_id,
            status=str(row["status"]),
            rows=int(row["rows"]),  # type: ignore[call-overload]
            reason=row["reason"],  # type: ignore[arg-type]
            rows_rejected=int(row["rows_rejected"] or 0),  # type: ignore[call-overload]
            repairs=row["repairs"],  # type: ignore[arg-type]
            replaced=known is not None,
            size_bytes=prepared.entry.size_bytes,
            mtime_ns=prepared.entry.mtime_ns,
        )

    def refresh(self, prepared: Prepared, known: Known | None) -> None:
        """The file is recorded with these bytes (:func:`unchanged`): its ledger row takes
        the size and modification time it has now, if they differ."""
        entry = prepared.entry
        if known is not None and (known.size_bytes, known.mtime_ns) != (
            entry.size_bytes,
            entry.mtime_ns,
        ):
            self._refreshed.append(
                {
                    "file_id": known.file_id,
                    "size_bytes": entry.size_bytes,
                    "mtime_ns": entry.mtime_ns,
                }
            )

    def end_partition(self) -> None:
        """A partition's files are queued: flush when the batch is full. A partition is never
        split between transactions; small ones share one (few large inserts are much faster
        in DuckDB than many small ones)."""
        if self._rows >= self._config.batch_rows or len(self._files) >= self._config.batch_files:
            self.flush()

    def flush(self) -> None:
        """Hand the queued files to the writer thread, to be written in one transaction
        (after the batch before it, which this waits for)."""
        if not self._files and not self._refreshed:
            return
        held = _Held(
            self._files,
            self._samples,
            self._rejections,
            self._dirty,
            self._replaced,
            self._refreshed,
        )
        self._clear()
        began = time.perf_counter()
        self._writer.submit(held)
        self.write_s += time.perf_counter() - began

    def _write(self, held: _Held) -> None:
        """One batch's transaction (on the writer thread)."""
        con = self._wh.con
        files = pl.DataFrame(held.files, schema=_FILES_SCHEMA, orient="row")
        dirty = pl.DataFrame(held.dirty, schema=_DIRTY_SCHEMA, orient="row")
        refreshed = pl.DataFrame(held.refreshed, schema=_REFRESH_SCHEMA, orient="row")
        rejections = pl.DataFrame(held.rejections, schema=_REJECTIONS_SCHEMA, orient="row")
        samples = pl.concat(held.samples) if held.samples else None
        with self._wh.transaction():
            if held.replaced:
                ids = {"ids": held.replaced}
                con.execute(sql("q_ingest_delete_samples"), ids)
                con.execute(sql("q_ingest_delete_rejections"), ids)
                con.execute(sql("q_ingest_delete_files"), ids)
            if files.height:
                _insert(con, "file_batch", files, sql("q_insert_files"))
            if samples is not None:
                _insert(con, "sample_batch", samples, sql("q_insert_samples"))
            if rejections.height:
                _insert(con, "rejection_batch", rejections, sql("q_insert_file_rejections"))
            if dirty.height:
                _insert(con, "dirty_batch", dirty, sql("q_insert_event_dirty"))
            if refreshed.height:
                _insert(con, "refresh_batch", refreshed, sql("q_ingest_refresh_files"))

    def __enter__(self) -> Batch:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        """Write what is queued and wait for it (an error: only the batch being written
        ends, nothing more is written)."""
        try:
            if exc_type is None:
                self.flush()
                began = time.perf_counter()
                self._writer.wait()
                self.write_s += time.perf_counter() - began
        finally:
            self._writer.__exit__(exc_type, *rest)


def _insert(con: duckdb.DuckDBPyConnection, name: str, frame: pl.DataFrame, statement: str) -> None:
    """Run ``statement`` with ``frame`` registered as ``name``."""
    con.register(name, frame)
    try:
        con.execute(statement)
    finally:
        con.unregister(name)


def _dirty_row(
    wagon_id: str | None,
    from_utc: dt.datetime | None,
    to_utc: dt.datetime | None,
    file_id: int,
) -> dict[str, object]:
    return {"wagon_id": wagon_id, "from_utc": from_utc, "to_utc": to_utc, "file_id": file_id}


def unchanged(prepared: Prepared, known: Known | None) -> bool:
    """The file is recorded with these bytes and would be recorded the same way again."""
    if known is None or known.sha256 != prepared.sha256:
        return False
    if known.quarantine_code not in RETRIED_CODES:
        return True
    problem = prepared.quarantine
    return problem is not None and (problem.code, problem.reason) == (
        known.quarantine_code,
        known.reason,
    )
