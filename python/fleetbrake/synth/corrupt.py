"""The faults of log files (``shared/spec/fleet-data.md``), made on purpose: what a synthetic
fleet's files suffer between the unit and the fleet directory, apart from the generator that
makes the sessions and from the format (``fleetbrake.fleet.logfile``) that reads and writes
them.

The primitives are small pure functions that the generator and the tests combine::

    rng = np.random.default_rng(7)
    frame = swap_neighbours(duplicate_rows(drop_gap(session, rng, gap_s=90), rng, 0.01), rng, 0.01)
    frame = pt1000_open_circuit(frame, rng, duration_s=300)
    write_log(fleet / log_relpath("SGG-0001", start_utc, gzip=True), frame)

    data = truncate_mid_row(to_csv_bytes(frame), rng)      # a unit that lost power
    (fleet / "logs/SGG-0001/SGG-0001_20240301T060000Z.csv").write_bytes(data)

Every frame-level injector takes a frame and a seeded :class:`numpy.random.Generator` and returns
a new frame; the byte-level ones take and return bytes. None of them mutates its input.

:func:`write_sessions` is the generator's use of them: it writes a fleet's sessions as files,
with the imperfections :class:`~fleetbrake.synth.config.SynthConfig` asks for (missing rows and
gaps, duplicated and swapped rows, empty cells, frozen and jumping GPS speed), the bad files
(cut mid-row, gzip cut mid-stream, garbage) and the sensor faults of single files (``open``,
``frozen``, ``loose``, ``drift``), and says in a :class:`~fleetbrake.synth.truth.FileTruth`
what it did to each.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from fleetbrake.fleet.logfile import (
    TIME_FORMAT,
    complete_rows,
    gzip_bytes,
    log_relpath,
    to_csv_bytes,
    write_log,
)
from fleetbrake.synth.config import SynthConfig, stream
from fleetbrake.synth.truth import Anomaly, FileTruth

__all__ = [
    "Session",
    "blank_cells",
    "drop_gap",
    "drop_rows",
    "duplicate_rows",
    "freeze_speed",
    "garbage_bytes",
    "garble_cells",
    "gps_dropout",
    "jump_speed",
    "pt1000_drift",
    "pt1000_drift_to_ambient",
    "pt1000_frozen",
    "pt1000_open_circuit",
    "swap_neighbours",
    "truncate_gzip",
    "truncate_mid_row",
    "write_sessions",
]

# --------------------------------------------------------------------------------------------
# Imperfections: frame level


def _pick(rng: np.random.Generator, n: int, fraction: float, *, low: int = 0) -> np.ndarray:
    """Sorted distinct row indices in ``[low, n)``, about ``fraction`` of the rows."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must be in [0, 1], got {fraction}")
    available = n - low
    if available <= 0:
        return np.empty(0, dtype=np.int64)
    count = round(fraction * available)
    return np.sort(rng.choice(available, size=count, replace=False)) + low


def _span(
    rng: np.random.Generator, n: int, length: int, start: int | None, *, low: int = 0
) -> tuple[int, int]:
    """A run of ``length`` rows ``[start, stop)``, random where ``start`` is None."""
    length = max(0, min(length, n - low))
    if start is None:
        start = int(rng.integers(low, n - length + 1)) if n - length >= low else low
    return start, min(start + length, n)


def drop_rows(frame: pl.DataFrame, rng: np.random.Generator, fraction: float) -> pl.DataFrame:
    """Missing samples: about ``fraction`` of the rows (never the first) removed, scattered."""
    gone = _pick(rng, frame.height, fraction, low=1)
    keep = np.ones(frame.height, dtype=bool)
    keep[gone] = False
    return frame.filter(pl.Series(keep))


def drop_gap(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    gap_s: int,
    *,
    start: int | None = None,
) -> pl.DataFrame:
    """A gap: ``gap_s`` consecutive rows removed (never the first row), at row ``start`` or anywhere."""
    first, stop = _span(rng, frame.height, gap_s, start, low=1)
    return pl.concat([frame.slice(0, first), frame.slice(stop)])


def duplicate_rows(frame: pl.DataFrame, rng: np.random.Generator, fraction: float) -> pl.DataFrame:
    """Duplicated samples: about ``fraction`` of the rows written twice, the copy right after."""
    twice = _pick(rng, frame.height, fraction)
    counts = np.ones(frame.height, dtype=np.int64)
    counts[twice] = 2
    order = np.repeat(np.arange(frame.height), counts)
    return frame[order]


def swap_neighbours(frame: pl.DataFrame, rng: np.random.Generator, fraction: float) -> pl.DataFrame:
    """Slightly out of order: about ``fraction`` of the rows swapped with the next one.

    Swaps never overlap and never move the first row (whose time names the file).
    """
    order = np.arange(frame.height)
    if frame.height < 3:
        return frame.clone()
    candidates = _pick(rng, frame.height - 1, fraction, low=1)
    last = -2
    for i in candidates:
        if i > last + 1:
            order[i], order[i + 1] = order[i + 1], order[i]
            last = i
    return frame[order]


def blank_cells(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    fraction: float,
    columns: tuple[str, ...] | None = None,
) -> pl.DataFrame:
    """Empty cells: in each of ``columns`` (default: every column), about ``fraction`` of the
    cells set to null (written as empty)."""
    columns = tuple(frame.columns) if columns is None else columns
    updates = []
    for name in columns:
        blank = np.zeros(frame.height, dtype=bool)
        blank[_pick(rng, frame.height, fraction)] = True
        updates.append(pl.when(pl.Series(blank)).then(None).otherwise(pl.col(name)).alias(name))
    return frame.with_columns(updates)


def garble_cells(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    fraction: float,
    columns: tuple[str, ...],
    *,
    text: str = "#VALUE!",
) -> pl.DataFrame:
    """Non-parsable values: about ``fraction`` of the cells of ``columns`` replaced by ``text``.

    The columns become strings (a datetime ``time_utc`` formatted as the writer would).
    """
    updates = []
    for name in columns:
        garbled = np.zeros(frame.height, dtype=bool)
        garbled[_pick(rng, frame.height, fraction)] = True
        column = pl.col(name)
        if frame.schema[name].is_temporal():
            as_text = column.dt.strftime(TIME_FORMAT)
        else:
            as_text = column.cast(pl.String)
        updates.append(
            pl.when(pl.Series(garbled)).then(pl.lit(text)).otherwise(as_text).alias(name)
        )
    return frame.with_columns(updates)


def freeze_speed(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    duration_s: int,
    *,
    start: int | None = None,
) -> pl.DataFrame:
    """GPS speed frozen while the fix is poor: ``duration_s`` rows repeat the speed of the first."""
    return _freeze(frame, "speed_kmh", rng, duration_s, start)


def gps_dropout(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    duration_s: int,
    *,
    start: int | None = None,
) -> pl.DataFrame:
    """The fix lost for ``duration_s`` rows: their speed empty and their distance held at the
    last row's before (the jump comes with the first row after)."""
    first, stop = _span(rng, frame.height, duration_s, start)
    speed = frame["speed_kmh"].to_numpy().astype(np.float64, copy=True)
    distance = frame["distance_m"].to_numpy().astype(np.float64, copy=True)
    speed[first:stop] = np.nan
    if first > 0:
        distance[first:stop] = distance[first - 1]
    return frame.with_columns(
        pl.Series("speed_kmh", speed, dtype=pl.Float64, nan_to_null=True),
        pl.Series("distance_m", distance, dtype=pl.Float64),
    )


def _braking_start(frame: pl.DataFrame, rng: np.random.Generator, duration_s: int) -> int | None:
    """A row a few seconds after a braking's activation with ``duration_s`` rows after it."""
    pressure = frame["brake_pressure_bar"].to_numpy().astype(np.float64)
    on = np.nan_to_num(pressure, nan=0.0) > 0.3
    starts = np.flatnonzero(on[1:] & ~on[:-1]) + 1
    starts = starts[(starts + 10 + duration_s < frame.height)]
    if starts.size == 0:
        return None
    return int(starts[int(rng.integers(0, starts.size))] + rng.integers(3, 11))


def _freeze(
    frame: pl.DataFrame,
    column: str,
    rng: np.random.Generator,
    duration_s: int,
    start: int | None,
) -> pl.DataFrame:
    """``duration_s`` rows of ``column`` (a span drawn by :func:`_span`) repeat the first's value."""
    first, stop = _span(rng, frame.height, duration_s, start)
    values = frame[column].to_numpy().copy()
    values[first:stop] = values[first]
    return frame.with_columns(pl.Series(column, values, dtype=pl.Float64))


def jump_speed(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    count: int,
    *,
    jump_kmh: float = 60.0,
    max_length_s: int = 3,
) -> pl.DataFrame:
    """GPS speed jumps: ``count`` short runs (1..``max_length_s`` rows) off by ±``jump_kmh``,
    never below zero."""
    speed = frame["speed_kmh"].to_numpy().copy()
    for _ in range(count):
        length = int(rng.integers(1, max_length_s + 1))
        first, stop = _span(rng, frame.height, length, None)
        sign = 1.0 if rng.random() < 0.5 else -1.0
        speed[first:stop] = np.maximum(speed[first:stop] + sign * jump_kmh, 0.0)
    return frame.with_columns(pl.Series("speed_kmh", speed, dtype=pl.Float64))


def pt1000_open_circuit(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    duration_s: int,
    *,
    start: int | None = None,
    reading_c: float | None = None,
) -> pl.DataFrame:
    """A broken Pt1000 wire: ``duration_s`` rows read far out of range.

    ``reading_c`` defaults to a random value above 600 °C (open wire) or below -60 °C (short).
    """
    first, stop = _span(rng, frame.height, duration_s, start)
    if reading_c is None:
        reading_c = float(
            rng.uniform(850.0, 1200.0) if rng.random() < 0.5 else rng.uniform(-250.0, -200.0)
        )
    temp_c = frame["block_temp_c"].to_numpy().copy()
    temp_c[first:stop] = reading_c
    return frame.with_columns(pl.Series("block_temp_c", temp_c, dtype=pl.Float64))


def pt1000_frozen(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    duration_s: int,
    *,
    start: int | None = None,
) -> pl.DataFrame:
    """A loose Pt1000 reading a frozen value: ``duration_s`` rows repeat the first one's reading."""
    return _freeze(frame, "block_temp_c", rng, duration_s, start)


def pt1000_drift_to_ambient(
    frame: pl.DataFrame,
    rng: np.random.Generator,
    *,
    tau_s: float = 600.0,
    ambient_c: float | None = None,
    start: int | None = None,
) -> pl.DataFrame:
    """A Pt1000 coming loose: from row ``start`` (random if None) on, the reading decouples from
    the block and relaxes towards ambient with time constant ``tau_s``.

    ``ambient_c`` defaults to the frame's ``ambient_temp_c`` (row by row), else 10 °C.
    """
    first, _ = _span(rng, frame.height, 1, start)
    temp_c = frame["block_temp_c"].to_numpy().copy()
    if ambient_c is not None:
        ambient = np.full(frame.height, ambient_c)
    elif "ambient_temp_c" in frame.columns:
        ambient = frame["ambient_temp_c"].fill_null(10.0).to_numpy().astype(np.float64)
    else:
        ambient = np.full(frame.height, 10.0)
    elapsed_s = np.arange(frame.height - first, dtype=np.float64)
    weight = np.exp(-elapsed_s / tau_s)
    temp_c[first:] = weight * temp_c[first:] + (1.0 - weight) * ambient[first:]
    return frame.with_columns(pl.Series("block_temp_c", temp_c, dtype=pl.Float64))


# --------------------------------------------------------------------------------------------
# Imperfections: byte level


def truncate_mid_row(csv_bytes: bytes, rng: np.random.Generator) -> bytes:
    """A unit that lost power: plain CSV cut inside a random data row (not at its end).

    The result keeps :func:`complete_rows` complete rows and ends in a partial one. Needs at
    least one data row.
    """
    line_ends = np.flatnonzero(np.frombuffer(csv_bytes, dtype=np.uint8) == ord("\n"))
    if len(line_ends) < 2:
        raise ValueError("truncate_mid_row needs a header and at least one data row")
    row = int(rng.integers(1, len(line_ends)))  # data row: between line_ends[row-1] and [row]
    row_start, row_end = int(line_ends[row - 1]) + 1, int(line_ends[row])
    if row_end - row_start < 2:
        return csv_bytes[:row_start]
    cut = int(rng.integers(row_start + 1, row_end))
    return csv_bytes[:cut]


def truncate_gzip(gz_bytes: bytes, rng: np.random.Generator) -> bytes:
    """A gzip file cut mid-stream (between 10 % and 90 % of its length)."""
    if len(gz_bytes) < 20:
        raise ValueError("truncate_gzip needs a gzip stream of at least 20 bytes")
    cut = int(rng.integers(int(0.1 * len(gz_bytes)) + 10, int(0.9 * len(gz_bytes))))
    return gz_bytes[:cut]


def garbage_bytes(rng: np.random.Generator, size: int = 4096, *, kind: str = "binary") -> bytes:
    """A file that is not CSV at all.

    ``kind="binary"``: random bytes. ``"text"``: readable lines that are no log (an error
    page). ``"zeros"``: NUL bytes (a file system that lost its data).
    """
    if kind == "binary":
        return rng.bytes(size)
    if kind == "zeros":
        return bytes(size)
    if kind == "text":
        words = ["error", "unit", "restart", "flash", "sector", "retry", "ok", "0x1f", "boot"]
        lines: list[str] = []
        while sum(len(line) + 1 for line in lines) < size:
            lines.append(" ".join(str(w) for w in rng.choice(words, size=int(rng.integers(3, 9)))))
        return ("\n".join(lines) + "\n").encode()[:size]
    raise ValueError(f"kind must be 'binary', 'text' or 'zeros', got {kind!r}")


def pt1000_drift(frame: pl.DataFrame, start: int, rate_k_per_h: float) -> pl.DataFrame:
    """A calibration drift: from row ``start`` on, an offset growing at ``rate_k_per_h``
    (readings to 0.01 K)."""
    temp_c = frame["block_temp_c"].to_numpy().copy()
    elapsed_h = np.arange(frame.height - start, dtype=np.float64) / 3600.0
    temp_c[start:] = np.round(temp_c[start:] + rate_k_per_h * elapsed_h, 2)
    return frame.with_columns(pl.Series("block_temp_c", temp_c, dtype=pl.Float64))


# --------------------------------------------------------------------------------------------
# A fleet's sessions written as files


@dataclass(frozen=True)
class Session:
    """One recording session of a wagon, as the unit logged it, before anything befell it."""

    wagon_id: str
    wagon_index: int
    """The wagon's number in the fleet (seeds the file's random stream)."""
    number: int
    """The session's number among the wagon's."""
    registered: bool
    """Whether the wagon has a good registry entry (only their files are made bad)."""
    frame: pl.DataFrame
    """One row per second, the columns in the order the unit writes them."""
    first_utc: dt.datetime
    """First sample."""
    last_utc: dt.datetime
    """Last sample."""
    odd_columns: bool = False
    """The unit writes its columns in another order, with an extra one."""
    ambient_c: float | None = None
    """The air temperature a loose sensor relaxes towards where the log has none (the
    registry's); None: the logged one."""


def write_sessions(
    out_dir: Path,
    config: SynthConfig,
    sessions: Sequence[Session],
    fault_plan: Mapping[str, Sequence[str]],
    registered: Sequence[str],
    start_utc: dt.datetime,
) -> tuple[list[FileTruth], list[Anomaly]]:
    """Write ``sessions`` under ``out_dir/logs`` as ``config`` asks: each with its
    imperfections, ``config.truncated_files`` cut mid-row and ``config.truncated_gzip_files``
    gzip files cut mid-stream (long sessions of registered wagons), the sensor faults of
    ``fault_plan`` (wagon id -> subtypes, one long file each, never a file made bad), and
    ``config.garbage_files`` files of garbage named as sessions of the ``registered`` wagons
    (ids in fleet order) at times their unit slept (or just after ``start_utc``). Returns what
    was written and the sensor faults."""
    rng = stream(config.seed, "bad_files")
    long_enough = [
        i
        for i, session in enumerate(sessions)
        if session.registered and session.frame.height >= 900
    ]
    # sensor faults: one file each, long sessions, never a file that is made bad
    fault_of: dict[int, str] = {}
    for wagon_id, subtypes in fault_plan.items():
        candidates = [i for i in long_enough if sessions[i].wagon_id == wagon_id]
        if not candidates:
            continue
        chosen = rng.choice(candidates, size=min(len(subtypes), len(candidates)), replace=False)
        for index, subtype in zip(sorted(int(c) for c in chosen), subtypes, strict=False):
            fault_of[index] = subtype
    free = [i for i in long_enough if i not in fault_of]
    n_bad = min(config.truncated_files + config.truncated_gzip_files, len(free))
    bad_pick = [int(i) for i in rng.choice(free, size=n_bad, replace=False)] if n_bad else []
    bad_of = {i: "truncated_mid_row" for i in bad_pick[: config.truncated_files]}
    bad_of.update({i: "truncated_gzip" for i in bad_pick[config.truncated_files :]})

    files: list[FileTruth] = []
    faults: list[Anomaly] = []
    for i, session in enumerate(sessions):
        file, fault = _write_session(out_dir, config, session, fault_of.get(i), bad_of.get(i))
        files.append(file)
        if fault is not None:
            faults.append(fault)
    files += _write_garbage(out_dir, config, rng, files, registered, start_utc)
    files.sort(key=lambda f: (f.wagon_id, f.start_utc, f.path))
    return files, faults


def _write_session(
    out_dir: Path,
    config: SynthConfig,
    session: Session,
    fault_subtype: str | None,
    bad: str | None,
) -> tuple[FileTruth, Anomaly | None]:
    """One session's file: its sensor fault (if any), its imperfections, and the file made
    bad (``truncated_mid_row``, ``truncated_gzip``) or not (None)."""
    frng = stream(config.seed, "files", session.wagon_index * 100_000 + session.number)
    frame = session.frame
    session_rows = frame.height
    t_first = session.first_utc
    imperfections: dict[str, Any] = {}
    if session.odd_columns:
        imperfections["odd_columns"] = list(frame.columns)
    # sensor fault (rows are seconds here)
    fault = None
    if fault_subtype is not None:
        frame, fault = _inject_sensor_fault(frame, frng, fault_subtype, session)
    # GPS speed
    if frng.random() < config.frozen_speed_probability and frame.height > 200:
        seconds = int(frng.integers(20, 121))
        at = int(frng.integers(1, frame.height - seconds))
        frame = freeze_speed(frame, frng, seconds, start=at)
        imperfections["frozen_speed"] = {
            "start_utc": t_first + dt.timedelta(seconds=at),
            "seconds": seconds,
        }
    if config.gps_dropout_probability > 0 and frng.random() < config.gps_dropout_probability:
        seconds = int(frng.integers(30, 181))
        lost = _braking_start(frame, frng, seconds)
        if lost is not None:
            frame = gps_dropout(frame, frng, seconds, start=lost)
            imperfections["gps_dropout"] = {
                "start_utc": t_first + dt.timedelta(seconds=lost),
                "seconds": seconds,
            }
    if frng.random() < config.speed_jump_probability and frame.height > 60:
        count = int(frng.integers(1, 3))
        frame = jump_speed(frame, frng, count)
        imperfections["speed_jumps"] = count
    # cells and rows
    if config.empty_cell_fraction > 0:
        before = frame.null_count().sum_horizontal().item()
        frame = blank_cells(frame, frng, config.empty_cell_fraction)
        imperfections["empty_cells"] = int(frame.null_count().sum_horizontal().item() - before)
    if frng.random() < config.gap_probability and frame.height > 400:
        seconds = int(frng.integers(5, 121))
        at = int(frng.integers(1, frame.height - seconds))
        frame = drop_gap(frame, frng, seconds, start=at)
        imperfections["gap"] = {
            "start_utc": t_first + dt.timedelta(seconds=at),
            "seconds": seconds,
        }
    if config.missing_row_fraction > 0:
        height = frame.height
        frame = drop_rows(frame, frng, config.missing_row_fraction)
        imperfections["missing_rows"] = height - frame.height
    if config.duplicate_fraction > 0:
        height = frame.height
        frame = duplicate_rows(frame, frng, config.duplicate_fraction)
        imperfections["duplicated_rows"] = frame.height - height
    if config.swap_fraction > 0:
        marker = pl.Series("__row", np.arange(frame.height))
        swapped = swap_neighbours(frame.with_columns(marker), frng, config.swap_fraction)
        rows = swapped["__row"].to_numpy()
        imperfections["swapped_pairs"] = int(np.sum(np.diff(rows) < 0))
        frame = swapped.drop("__row")
    imperfections = {k: v for k, v in imperfections.items() if v}

    gz = bool(frng.random() < config.gzip_fraction)
    if bad == "truncated_mid_row":
        gz = False
    elif bad == "truncated_gzip":
        gz = True
    rel = log_relpath(session.wagon_id, t_first, gzip=gz)
    data = to_csv_bytes(frame)
    rows_written = complete_rows(data)
    reason = None
    readable = data
    if bad == "truncated_mid_row":
        data = readable = truncate_mid_row(data, frng)
        rows_written = complete_rows(data)
        reason = f"cut inside data row {rows_written + 1} (the unit lost power)"
    elif bad == "truncated_gzip":
        data = truncate_gzip(gzip_bytes(data), frng)
        readable = zlib.decompressobj(wbits=31).decompress(data)
        rows_written = complete_rows(readable)
        reason = f"gzip stream cut after {len(data)} bytes ({rows_written} complete rows)"
    if bad is not None:
        imperfections["last_complete_utc"] = last_complete_time(readable)
    write_log(out_dir / rel, data, gzip=gz and bad != "truncated_gzip")
    if fault is not None:
        fault = dataclasses.replace(fault, file=rel.as_posix())
    file = FileTruth(
        path=rel.as_posix(),
        wagon_id=session.wagon_id,
        start_utc=t_first,
        end_utc=session.last_utc,
        gzip=gz,
        session_rows=session_rows,
        rows_written=rows_written,
        imperfections=imperfections,
        bad=bad,
        reason=reason,
        registered=session.registered,
    )
    return file, fault


def _write_garbage(
    out_dir: Path,
    config: SynthConfig,
    rng: np.random.Generator,
    files: Sequence[FileTruth],
    registered: Sequence[str],
    start_utc: dt.datetime,
) -> list[FileTruth]:
    """Files that are not CSV at all, named as sessions of registered wagons at times the unit
    slept (a few minutes after the end of one of its sessions)."""
    ok_ids = list(registered)
    taken = {f.path for f in files}
    kinds = ("binary", "text", "zeros")
    out: list[FileTruth] = []
    for g in range(config.garbage_files):
        if not ok_ids:
            break
        wagon_id = ok_ids[int(rng.integers(0, len(ok_ids)))]
        own = sorted((f for f in files if f.wagon_id == wagon_id), key=lambda f: f.start_utc)
        slot = own[int(rng.integers(0, len(own)))].end_utc if own else start_utc
        when = slot + dt.timedelta(seconds=int(rng.integers(60, 300)))
        kind = kinds[g % len(kinds)]
        gz = bool(rng.random() < config.gzip_fraction)
        rel = log_relpath(wagon_id, when, gzip=gz)
        if rel.as_posix() in taken:
            continue
        data = garbage_bytes(rng, int(rng.integers(512, 8192)), kind=kind)
        write_log(out_dir / rel, data, gzip=False)
        taken.add(rel.as_posix())
        out.append(
            FileTruth(
                path=rel.as_posix(),
                wagon_id=wagon_id,
                start_utc=when,
                end_utc=when,
                gzip=gz,
                session_rows=0,
                rows_written=0,
                imperfections={"garbage_kind": kind},
                bad="garbage",
                reason=f"not CSV at all ({kind} bytes" + (", though named .csv.gz)" if gz else ")"),
                registered=True,
            )
        )
    return out


def last_complete_time(csv_bytes: bytes) -> dt.datetime | None:
    """Latest ``time_utc`` of the complete rows of plain CSV bytes (None if none)."""
    text = csv_bytes.decode("utf-8", errors="replace")
    lines = text.split("\n")
    header = lines[0].split(",")
    if "time_utc" not in header:
        return None
    col = header.index("time_utc")
    latest = None
    for line in lines[1:-1]:  # the last piece is partial (or empty)
        cells = line.split(",")
        if col < len(cells) and cells[col]:
            try:
                when = dt.datetime.strptime(cells[col], TIME_FORMAT)
            except ValueError:
                continue
            latest = when if latest is None or when > latest else latest
    return latest


def _inject_sensor_fault(
    frame: pl.DataFrame, rng: np.random.Generator, subtype: str, session: Session
) -> tuple[pl.DataFrame, Anomaly]:
    """A sensor fault of ``subtype`` in one session's frame, from a random row in its middle."""
    n = frame.height
    at = int(rng.integers(n // 5, n // 2))
    parameters: dict[str, float] = {}
    if subtype == "open":
        seconds = int(rng.integers(60, min(600, n - at)))
        frame = pt1000_open_circuit(frame, rng, seconds, start=at)
        parameters["reading_c"] = float(frame["block_temp_c"][at])
        stop = at + seconds
    elif subtype == "frozen":
        seconds = int(rng.integers(300, max(301, min(1800, n - at))))
        frame = pt1000_frozen(frame, rng, seconds, start=at)
        parameters["reading_c"] = float(frame["block_temp_c"][at])
        stop = at + seconds
    elif subtype == "loose":
        tau_s = float(rng.uniform(300.0, 900.0))
        # towards the air: the logged one, or the registry's where the wagon has no sensor
        frame = pt1000_drift_to_ambient(
            frame, rng, tau_s=tau_s, start=at, ambient_c=session.ambient_c
        )
        temp = np.round(frame["block_temp_c"].to_numpy(), 2)
        frame = frame.with_columns(pl.Series("block_temp_c", temp, dtype=pl.Float64))
        parameters["tau_s"] = tau_s
        stop = n
    elif subtype == "drift":
        rate = float(rng.uniform(3.0, 8.0)) * (1.0 if rng.random() < 0.5 else -1.0)
        frame = pt1000_drift(frame, at, rate)
        parameters["rate_k_per_h"] = rate
        stop = n
    else:
        raise ValueError(f"unknown sensor fault {subtype!r}")
    return frame, Anomaly(
        session.wagon_id,
        "sensor_fault",
        session.first_utc + dt.timedelta(seconds=at),
        session.first_utc + dt.timedelta(seconds=stop),
        subtype=subtype,
        parameters=parameters,
    )
