"""Reading one log file: its bytes (gzip or not) parsed into a frame of samples, repaired.

:func:`read_log` decompresses (gzip is recognised by its content, not its name), checks the
header, drops a last row cut short, parses the known columns with polars and hands the frame
to the per-row checks of :mod:`fleetbrake.ingest.validation`. A file that cannot be read at all
raises :class:`~fleetbrake.ingest.quarantine.Quarantine`.
"""

from __future__ import annotations

import datetime as dt
import zlib
from dataclasses import dataclass

import numpy as np
import polars as pl

from fleetbrake.fleet.logfile import FLOAT_COLUMNS, OPTIONAL_COLUMNS, REQUIRED_COLUMNS
from fleetbrake.ingest.config import IngestConfig
from fleetbrake.ingest.quarantine import Quarantine
from fleetbrake.ingest.validation import (
    Repairs,
    clear_implausible,
    clear_unparsable,
    field_counts,
    reject_ragged,
    repair_times,
    split_block_temp_faults,
)

__all__ = ["ParsedLog", "read_log"]

_GZIP_MAGIC = b"\x1f\x8b"


@dataclass(frozen=True)
class ParsedLog:
    """One log file read and repaired: the samples to store, sorted by time, and the repairs."""

    frame: pl.DataFrame
    repairs: Repairs

    @property
    def first_utc(self) -> dt.datetime | None:
        """Time of the first sample (None if there is none)."""
        return self.frame["time_utc"].min() if self.frame.height else None  # type: ignore[return-value]

    @property
    def last_utc(self) -> dt.datetime | None:
        """Time of the last sample (None if there is none)."""
        return self.frame["time_utc"].max() if self.frame.height else None  # type: ignore[return-value]


def _gunzip(data: bytes, relpath: str) -> bytes:
    """Every member of a gzip stream; :class:`Quarantine` if corrupt or cut short."""
    parts: list[bytes] = []
    rest = data
    try:
        while rest:
            inflater = zlib.decompressobj(wbits=31)
            parts.append(inflater.decompress(rest))
            if not inflater.eof:
                raise Quarantine(
                    "gzip",
                    f"{relpath}: gzip stream truncated after {len(data)} bytes (no end of "
                    "stream): the file was cut short",
                )
            rest = inflater.unused_data
            if not rest.strip(b"\x00"):
                break
    except zlib.error as error:
        raise Quarantine("gzip", f"{relpath}: corrupt gzip stream ({error})") from None
    return b"".join(parts)


def _header(data: bytes, relpath: str) -> tuple[list[str], bytes]:
    """Column names of the first line, and the rest of the data."""
    end = data.find(b"\n")
    if end < 0:
        raise Quarantine("header", f"{relpath}: no complete first line (no header)")
    line, body = data[:end], data[end + 1 :]
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError:
        raise Quarantine(
            "binary", f"{relpath}: not a CSV log: line 1 is not UTF-8 text (binary content)"
        ) from None
    text = text.removeprefix("\ufeff").removesuffix("\r")
    if any(ord(c) < 32 and c != "\t" for c in text):
        raise Quarantine("binary", f"{relpath}: not a CSV log: line 1 holds control characters")
    names = [name.strip() for name in text.split(",")]
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        shown = text if len(text) <= 120 else text[:117] + "..."
        raise Quarantine(
            "header",
            f"{relpath}: line 1 is not a log header: it lacks {', '.join(missing)} "
            f"(found {shown!r})",
        )
    repeated = sorted(
        {n for n in names if n in REQUIRED_COLUMNS + OPTIONAL_COLUMNS and names.count(n) > 1}
    )
    if repeated:
        raise Quarantine("header", f"{relpath}: line 1 names {', '.join(repeated)} more than once")
    return names, body


def _complete_rows(body: bytes, repairs: Repairs) -> bytes:
    """``body`` without a last row cut short (no final newline)."""
    if not body or body.endswith(b"\n"):
        return body
    end = body.rfind(b"\n")
    kept = body[: end + 1]
    line = kept.count(b"\n") + 2
    repairs.partial_row_dropped = True
    repairs.reject(
        f"file ends inside line {line} (cut short): that partial row dropped",
        np.array([line]),
        "cut short: the file ends inside it",
    )
    return kept


def _parse_cells(body: bytes, names: list[str]) -> tuple[pl.DataFrame, pl.DataFrame | None]:
    """The known columns of ``body``: ``time_utc`` as text, numbers as Float64.

    The body is parsed under a clean copy of its header (so the header, not the first data
    line, says how many cells a line has). Fast path: typed parse. If a cell is not a number,
    a line has more cells than the header, or the bytes are not UTF-8, every column is parsed
    as text (extra cells ignored, bad bytes replaced) and cast cell by cell; then the text is
    returned too, for the notes. A line with fewer cells has empty trailing cells.
    """
    wanted = [i for i, name in enumerate(names) if name in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    placeholders = [name if i in wanted else f"_ignored_{i}" for i, name in enumerate(names)]
    data = ",".join(placeholders).encode() + b"\n" + body
    typed = pl.Schema(
        {name: (pl.Float64 if name in FLOAT_COLUMNS else pl.String) for name in placeholders}
    )
    try:
        frame = pl.read_csv(data, schema=typed, columns=wanted, quote_char=None)
        return frame, None
    except pl.exceptions.PolarsError:
        pass
    text = pl.read_csv(
        data,
        schema=pl.Schema({name: pl.String for name in placeholders}),
        columns=wanted,
        quote_char=None,
        truncate_ragged_lines=True,
        encoding="utf8-lossy",
    )
    numbers = text.with_columns(
        pl.col(c).str.strip_chars().cast(pl.Float64, strict=False)
        for c in FLOAT_COLUMNS
        if c in text.columns
    )
    return numbers, text


def read_log(
    data: bytes,
    relpath: str,
    start_utc: dt.datetime,
    config: IngestConfig | None = None,
) -> ParsedLog:
    """Read and repair one log file's bytes (gzip or not); :class:`Quarantine` if unusable.

    ``start_utc`` is the time of the file name. The frame has ``time_utc`` (Datetime, sorted,
    distinct), every numeric column of :data:`~fleetbrake.fleet.logfile.FLOAT_COLUMNS` (Float64, null
    where empty), ``block_temp_raw_c`` and ``block_temp_fault``.
    """
    config = config or IngestConfig()
    if not data:
        raise Quarantine("empty", f"{relpath}: empty file (0 bytes)")
    repairs = Repairs()
    if data.startswith(_GZIP_MAGIC):
        data = _gunzip(data, relpath)
        if not relpath.endswith(".gz"):
            repairs.notes.append("gzip content in a file named .csv: decompressed")
    elif relpath.endswith(".gz"):
        repairs.notes.append("plain CSV in a file named .csv.gz: read as it is")
    names, body = _header(data, relpath)
    body = _complete_rows(body, repairs)
    frame, text = _parse_cells(body, names)
    repairs.rows_in_file = frame.height + int(repairs.partial_row_dropped)
    ragged = None
    # A line of more fields fails the typed parse (then ``text`` is set); one of fewer fields, or
    # a blank one, makes the commas fewer than the header's: else every line has its fields.
    if text is not None or body.count(b",") != (len(names) - 1) * frame.height:
        fields = field_counts(body)
        frame, text, ragged = reject_ragged(frame, text, fields, len(names), repairs)
    frame = clear_unparsable(frame, text, repairs)
    frame = clear_implausible(frame, config.plausible_ranges, repairs)
    for name in OPTIONAL_COLUMNS:
        if name not in frame.columns:
            frame = frame.with_columns(pl.lit(None, dtype=pl.Float64).alias(name))
    text_time = (text if text is not None else frame)["time_utc"]
    frame = repair_times(frame, text_time, start_utc, config, repairs, ragged)
    frame = split_block_temp_faults(frame, config, repairs)
    frame = frame.select("time_utc", *FLOAT_COLUMNS, "block_temp_raw_c", "block_temp_fault")
    return ParsedLog(frame, repairs)


# --------------------------------------------------------------------------------------------
