"""Per-row checks of a parsed log file: what is repaired, counted and noted.

Each check takes the frame of one file (:func:`fleetbrake.ingest.reading.read_log` calls them
in order) and returns it repaired, counting what it changed in a :class:`Repairs` with a note
naming the file's line numbers:

* :func:`reject_ragged`: a row with more or fewer fields than the header is rejected (its
  cells cannot be trusted to be in their columns);
* :func:`clear_unparsable`: a numeric cell that is not a finite number becomes empty;
* :func:`clear_implausible`: a numeric cell outside the range its channel can physically take
  (``IngestConfig.plausible_ranges``) becomes empty, counted with the unparsable ones;
* :func:`repair_times`: rows without a usable time, timed outside the session or repeating an
  earlier row's time are rejected (dropped, each run of lines named in a :class:`RejectedRun`),
  rows out of order sorted;
* :func:`split_block_temp_faults`: a ``block_temp_c`` reading outside its valid range is a
  broken wire: kept as ``block_temp_raw_c`` with ``block_temp_fault``, not as a temperature.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import polars as pl

from fleetbrake.fleet.logfile import BLOCK_TEMP_VALID_C, FLOAT_COLUMNS, TIME_FORMAT
from fleetbrake.ingest.config import IngestConfig

__all__ = [
    "RejectedRun",
    "Repairs",
    "clear_implausible",
    "clear_unparsable",
    "field_counts",
    "reject_ragged",
    "repair_times",
    "split_block_temp_faults",
]

_EPOCH = dt.datetime(1970, 1, 1)
_EXAMPLES = 5
"""How many line numbers (or values) a repair note lists before 'and N more'."""
_SHOWN_CHARS = 40
"""How much of a cell a repair note quotes (a 1 MB cell is not copied into the ledger)."""


class RejectedRun(NamedTuple):
    """Consecutive lines of a file rejected for the same reason (the header is line 1)."""

    first_line: int
    last_line: int
    why: str
    """What is wrong with these rows, a short phrase (\"no time\", \"cut short\", ...)."""

    @property
    def rows(self) -> int:
        """How many rows the run holds."""
        return self.last_line - self.first_line + 1


def rejected_runs(lines: np.ndarray, why: str) -> list[RejectedRun]:
    """Sorted line numbers cut into runs of consecutive lines, each with ``why``."""
    if not lines.size:
        return []
    breaks = np.flatnonzero(np.diff(lines) != 1)
    firsts = np.concatenate(([lines[0]], lines[breaks + 1]))
    lasts = np.concatenate((lines[breaks], [lines[-1]]))
    return [RejectedRun(int(a), int(b), why) for a, b in zip(firsts, lasts, strict=True)]


@dataclass
class Repairs:
    """What was repaired in one file; every count is also described in :meth:`text`.

    A row is read (``rows_in_file``) and then stored or rejected: the rejected ones are those
    of other than the header's fields, without a time, outside the session, repeating an
    earlier row's time, and a last row cut short (:attr:`rows_rejected`), each named in
    :attr:`rejected` and :meth:`rejected_text`.
    """

    rows_in_file: int = 0
    """Data lines read (after the header), a last one cut short included."""
    rows_ragged: int = 0
    """Rows rejected for holding more or fewer fields than the header."""
    rows_no_time: int = 0
    rows_outside_session: int = 0
    rows_duplicate: int = 0
    rows_out_of_order: int = 0
    cells_unparsable: int = 0
    """Cells not a finite number or outside their channel's plausible range (now empty)."""
    block_temp_faults: int = 0
    partial_row_dropped: bool = False
    notes: list[str] = field(default_factory=list)
    rejected: list[RejectedRun] = field(default_factory=list)
    """Every rejected row, as runs of lines, in the order the checks found them."""
    rejection_notes: list[str] = field(default_factory=list)
    """The notes (also in :attr:`notes`) that say which rows were rejected and why."""

    @property
    def rows_rejected(self) -> int:
        """Rows read but not stored."""
        return (
            self.rows_ragged
            + self.rows_no_time
            + self.rows_outside_session
            + self.rows_duplicate
            + int(self.partial_row_dropped)
        )

    def text(self) -> str | None:
        """The notes as one sentence list, or None when nothing was repaired."""
        return "; ".join(self.notes) if self.notes else None

    def rejected_text(self) -> str | None:
        """``"2 rows rejected: ..."`` with the lines and why, or None when none was."""
        count = self.rows_rejected
        if not count:
            return None
        return f"{count} row{'s' if count > 1 else ''} rejected: " + "; ".join(self.rejection_notes)

    def reject(self, note: str, lines: np.ndarray, why: str) -> None:
        """Record rejected rows: ``note`` for people, ``lines`` (sorted) as runs of ``why``."""
        self.notes.append(note)
        self.rejection_notes.append(note)
        self.rejected.extend(rejected_runs(lines, why))


def _lines(line_numbers: list[int], total: int) -> str:
    shown = ", ".join(str(n) for n in line_numbers[:_EXAMPLES])
    more = total - min(total, _EXAMPLES)
    word = "line" if total == 1 else "lines"
    return f"{word} {shown}" + (f" and {more} more" if more else "")


def _shown(value: object) -> str:
    """``repr(value)``, cut to :data:`_SHOWN_CHARS` characters."""
    text = repr(value)
    if len(text) <= _SHOWN_CHARS:
        return text
    return f"{text[: _SHOWN_CHARS - 3]}... ({len(str(value))} characters)"


def field_counts(body: bytes) -> np.ndarray:
    """The number of fields of each line of ``body`` (complete lines, ending in a newline),
    0 for a blank line (judged by the time check: no time)."""
    raw = np.frombuffer(body, dtype=np.uint8)
    ends = np.flatnonzero(raw == ord("\n"))
    commas = np.flatnonzero(raw == ord(","))
    counts = np.diff(np.searchsorted(commas, ends), prepend=0) + 1
    starts = np.concatenate(([0], ends[:-1] + 1))
    carriage = (ends > starts) & (raw[np.maximum(ends - 1, 0)] == ord("\r"))
    blank = (counts == 1) & (ends - starts - carriage <= 0)
    return np.where(blank, 0, counts)


def reject_ragged(
    frame: pl.DataFrame,
    text: pl.DataFrame | None,
    fields: np.ndarray,
    expected: int,
    repairs: Repairs,
) -> tuple[pl.DataFrame, pl.DataFrame | None, np.ndarray | None]:
    """Reject the rows whose line has other than the header's ``expected`` fields (``fields``:
    of each line, :func:`field_counts`): a cell added or lost moves the others out of their
    columns. Their cells are emptied (the later checks skip them); returns the frames and the
    rejected rows' mask (None if none)."""
    if fields.size != frame.height:
        return frame, text, None
    ragged = (fields != expected) & (fields != 0)
    count = int(ragged.sum())
    if not count:
        return frame, text, None
    rows = np.flatnonzero(ragged)
    lines = rows + 2
    shown = ", ".join(
        f"line {n} has {fields[r]}" for n, r in zip(lines[:_EXAMPLES], rows, strict=False)
    )
    more = count - min(count, _EXAMPLES)
    repairs.rows_ragged = count
    note = (
        f"{count} row{'s' if count > 1 else ''} with other than the header's {expected} fields "
        f"dropped (cells out of their columns): {shown}" + (f" and {more} more" if more else "")
    )
    repairs.notes.append(note)
    repairs.rejection_notes.append(note)
    for n_fields in np.unique(fields[rows]):
        repairs.rejected.extend(
            rejected_runs(
                lines[fields[rows] == n_fields], f"{n_fields} fields ({expected} expected)"
            )
        )
    mask = pl.Series(ragged)
    frame = frame.with_columns(
        pl.when(mask).then(None).otherwise(pl.col(c)).alias(c) for c in frame.columns
    )
    if text is not None:
        text = text.with_columns(
            pl.when(mask).then(None).otherwise(pl.col(c)).alias(c) for c in text.columns
        )
    return frame, text, ragged


def _line_numbers(frame: pl.DataFrame, mask: pl.Series) -> list[int]:
    """File line numbers of the rows where ``mask`` holds (header = line 1)."""
    if "_line" in frame.columns:
        return frame["_line"].filter(mask).to_list()  # one column, not the whole frame
    return (mask.arg_true() + 2).to_list()


def clear_unparsable(
    frame: pl.DataFrame, text: pl.DataFrame | None, repairs: Repairs
) -> pl.DataFrame:
    """Numeric cells that are not a finite number become null; counted and noted."""
    present = [c for c in FLOAT_COLUMNS if c in frame.columns]
    not_finite = {c: pl.col(c).is_not_null() & ~pl.col(c).is_finite() for c in present}
    if text is None:
        (count,) = frame.select(pl.sum_horizontal(e.sum() for e in not_finite.values())).row(0)
        if not count:
            return frame
        bad = frame.select(e.alias(c) for c, e in not_finite.items())
    else:
        raw = text.select(pl.col(c).str.strip_chars() for c in present)
        bad = frame.select(
            (
                not_finite[c] | pl.lit(raw[c].is_not_null() & (raw[c] != "") & frame[c].is_null())
            ).alias(c)
            for c in present
        )
    counts = bad.sum().row(0, named=True)
    total = sum(counts.values())
    if not total:
        return frame
    repairs.cells_unparsable = total
    examples = []
    for c, count in counts.items():
        if not count:
            continue
        rows = bad[c].arg_true().head(_EXAMPLES).to_list()
        source = text if text is not None else frame
        shown = [_shown(source[c][r]) for r in rows[:2]]
        examples.append(
            f"{c} {_lines([r + 2 for r in rows], count)} ({', '.join(shown)}"
            + (", ..." if count > 2 else "")
            + ")"
        )
    repairs.notes.append(
        f"{total} cell{'s' if total > 1 else ''} not a finite number, now empty: "
        + "; ".join(examples)
    )
    return frame.with_columns(
        pl.when(bad[c]).then(None).otherwise(pl.col(c)).alias(c) for c in present if counts[c]
    )


def clear_implausible(
    frame: pl.DataFrame, ranges: Mapping[str, tuple[float, float]], repairs: Repairs
) -> pl.DataFrame:
    """Numeric cells outside their channel's plausible range become null; counted with the
    unparsable ones and noted. ``block_temp_c`` is left to :func:`split_block_temp_faults`."""
    checked = {c: ranges[c] for c in FLOAT_COLUMNS if c in ranges and c in frame.columns}
    checked.pop("block_temp_c", None)
    if not checked or frame.height == 0:
        return frame
    # fast path (every file of a working unit): each column's extremes within its range
    lowest = frame.select(pl.col(c).min() for c in checked).row(0, named=True)
    highest = frame.select(pl.col(c).max() for c in checked).row(0, named=True)
    inside = [
        (lowest[c] is None or lowest[c] >= lo) and (highest[c] is None or highest[c] <= hi)
        for c, (lo, hi) in checked.items()
    ]
    if all(inside):
        return frame
    bad = frame.select(
        (~pl.col(c).is_between(lo, hi)).fill_null(False).alias(c) for c, (lo, hi) in checked.items()
    )
    counts = bad.sum().row(0, named=True)
    total = sum(counts.values())
    repairs.cells_unparsable += total
    examples = []
    for c, n in counts.items():
        if not n:
            continue
        low, high = checked[c]
        rows = bad[c].arg_true()
        shown = [f"{v:g}" for v in frame[c].gather(rows.head(2)).to_list()]
        examples.append(
            f"{c} outside [{low:g}, {high:g}] {_lines((rows + 2).head(_EXAMPLES).to_list(), n)} "
            f"({', '.join(shown)}" + (", ..." if n > 2 else "") + ")"
        )
    repairs.notes.append(
        f"{total} cell{'s' if total > 1 else ''} outside the range the channel can take (not a "
        "measurement), now empty: " + "; ".join(examples)
    )
    return frame.with_columns(
        pl.when(bad[c]).then(None).otherwise(pl.col(c)).alias(c) for c in counts if counts[c]
    )


def _in_order(time_utc: pl.Series, start_utc: dt.datetime, latest_utc: dt.datetime) -> bool:
    """Every time present, within the session, strictly increasing: nothing to repair."""
    if time_utc.null_count() or time_utc.is_empty():
        return time_utc.is_empty()
    us = time_utc.to_physical().to_numpy()
    start_us = int((start_utc - _EPOCH) / dt.timedelta(microseconds=1))
    latest_us = int((latest_utc - _EPOCH) / dt.timedelta(microseconds=1))
    return bool(us[0] >= start_us and us[-1] <= latest_us and np.all(np.diff(us) > 0))


def repair_times(
    frame: pl.DataFrame,
    text_time: pl.Series,
    start_utc: dt.datetime,
    config: IngestConfig,
    repairs: Repairs,
    ragged: np.ndarray | None = None,
) -> pl.DataFrame:
    """Parse ``time_utc``, drop rows without a usable time, keep the first of repeated times,
    sort; counted and noted. Adds ``_line`` (file line numbers) when rows move or go.
    ``ragged``: rows already rejected (:func:`reject_ragged`), dropped here too."""
    frame = frame.with_columns(
        pl.col("time_utc").str.to_datetime(TIME_FORMAT, time_unit="us", strict=False, cache=False)
    )
    latest_utc = start_utc + dt.timedelta(seconds=config.max_session_s)
    if ragged is None and _in_order(frame["time_utc"], start_utc, latest_utc):
        return frame
    frame = frame.with_columns(pl.int_range(2, frame.height + 2, dtype=pl.Int64).alias("_line"))
    # The repairs are judged in numpy on the times alone (each polars call on a column costs
    # about as much as the judgement); the whole frame is gathered once at the end.
    time_utc = frame["time_utc"]
    rows = np.arange(frame.height)
    if ragged is not None:
        rows = rows[~ragged]
    no_time = time_utc.is_null().to_numpy()[rows]
    if no_time.any():
        lines = (rows[no_time] + 2).tolist()
        raw = text_time.gather(rows[no_time])
        empty = int((raw.is_null() | (raw.str.strip_chars() == "")).sum())
        repairs.rows_no_time = len(lines)
        examples = [_shown(v) for v in raw.drop_nulls().to_list() if v.strip()][:2]
        detail = f"{empty} empty" + (
            f", {len(lines) - empty} not a time ({', '.join(examples)})"
            if len(lines) > empty
            else ""
        )
        repairs.reject(
            f"{len(lines)} row{'s' if len(lines) > 1 else ''} without a time dropped "
            f"({detail}): {_lines(lines, len(lines))}",
            rows[no_time] + 2,
            "no time: the time_utc cell is empty or not YYYY-MM-DDTHH:MM:SSZ",
        )
        rows = rows[~no_time]
    us = time_utc.to_physical().fill_null(0).to_numpy()[rows]
    start_us = int((start_utc - _EPOCH) / dt.timedelta(microseconds=1))
    latest_us = int((latest_utc - _EPOCH) / dt.timedelta(microseconds=1))
    outside = (us < start_us) | (us > latest_us)
    if outside.any():
        lines = (rows[outside] + 2).tolist()
        repairs.rows_outside_session = len(lines)
        named = f"{start_utc:%Y-%m-%dT%H:%M:%SZ}"
        repairs.reject(
            f"{len(lines)} row{'s' if len(lines) > 1 else ''} timed before the file name's "
            f"time {named} or more than {config.max_session_s} s after "
            f"it dropped: {_lines(lines, len(lines))}",
            rows[outside] + 2,
            f"timed before the file name's time {named} or more than "
            f"{config.max_session_s} s after it",
        )
        rows, us = rows[~outside], us[~outside]
    repeated = np.ones(us.size, dtype=bool)
    repeated[np.unique(us, return_index=True)[1]] = False  # the first of each time is kept
    if repeated.any():
        lines = (rows[repeated] + 2).tolist()
        repairs.rows_duplicate = len(lines)
        repairs.reject(
            f"{len(lines)} row{'s' if len(lines) > 1 else ''} repeating an earlier row's time "
            f"dropped (the first kept): {_lines(lines, len(lines))}",
            rows[repeated] + 2,
            "repeats the time of an earlier row of the file (the first kept)",
        )
        rows, us = rows[~repeated], us[~repeated]
    if rows.size < frame.height:
        frame = frame.gather(rows)  # the kept rows, in file order
    late = np.zeros(us.size, dtype=bool)
    late[1:] = us[1:] < np.maximum.accumulate(us)[:-1]
    if late.any():
        lines = (rows[late] + 2).tolist()
        repairs.rows_out_of_order = len(lines)
        repairs.notes.append(
            f"{len(lines)} row{'s' if len(lines) > 1 else ''} out of time order, sorted: "
            f"{_lines(lines, len(lines))}"
        )
        frame = frame.sort("time_utc", maintain_order=True)
    return frame


def split_block_temp_faults(
    frame: pl.DataFrame, config: IngestConfig, repairs: Repairs
) -> pl.DataFrame:
    """Split ``block_temp_c`` into valid readings and out-of-range faults (raw value kept)."""
    low_c, high_c = config.plausible_ranges.get("block_temp_c", BLOCK_TEMP_VALID_C)
    raw = pl.col("block_temp_c")
    fault = (raw < low_c) | (raw > high_c)
    faulty = frame.select(fault.fill_null(False)).to_series()
    count = int(faulty.sum())
    if not count:
        return frame.with_columns(
            pl.lit(None, dtype=pl.Float64).alias("block_temp_raw_c"),
            pl.lit(False).alias("block_temp_fault"),
        )
    lines = _line_numbers(frame, faulty)
    values = frame.filter(faulty)["block_temp_c"]
    lowest, highest = float(values.min()), float(values.max())  # type: ignore[arg-type]
    repairs.block_temp_faults = count
    repairs.notes.append(
        f"{count} block_temp_c reading{'s' if count > 1 else ''} outside "
        f"[{low_c:g}, {high_c:g}] degC (broken wire; {lowest:g} to {highest:g}) "
        f"kept as faults, not temperatures: {_lines(lines, count)}"
    )
    return frame.with_columns(
        pl.when(fault).then(None).otherwise(raw).alias("block_temp_c"),
        pl.when(fault).then(raw).otherwise(None).alias("block_temp_raw_c"),
        faulty.alias("block_temp_fault"),
    )
