"""What a recording shows, read from the warehouse: the samples, predictions, contact estimates,
events and flags of a wagon (or of one event's window, or of a time window), the model revision,
and notes on what is missing.

::

    from fleetbrake.viz.data import load_record_data, open_read_only

    with open_read_only("warehouse/fleet.duckdb", wait_s=0.0) as wh:
        data = load_record_data(wh, "SGG-0001", event_id="SGG-0001-20240301T101500")

The database is only read. Its queries are ``warehouse/sql/q_record_*.sql``. A wagon, event or
revision that is not there raises :class:`RecordError` naming the database and the known ones.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from typing import Any

import duckdb
import numpy as np
import polars as pl

from fleetbrake.errors import DatabaseLockedError, FleetbrakeError
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.viz.entities import Floats, Times
from fleetbrake.viz.estimates import per_second_estimates
from fleetbrake.warehouse.connection import (
    Warehouse,
    WarehouseError,
    WarehouseLockedError,
    open_warehouse,
    sql,
)

__all__ = [
    "EVENT_LEAD_S",
    "EVENT_TAIL_S",
    "RecordData",
    "RecordError",
    "RecordLockedError",
    "frame_times",
    "frame_values",
    "instant",
    "load_record_data",
    "open_read_only",
]

EVENT_LEAD_S = 60.0
"""An event's recording begins this long before activation."""

EVENT_TAIL_S = 600.0
"""Without predictions, an event's recording ends this long after release."""

_WAIT_POLL_S = 0.5


class RecordError(FleetbrakeError):
    """The recording cannot be made; the message names the database, wagon, event or revision."""


class RecordLockedError(RecordError, DatabaseLockedError):
    """Another process is writing to the database: DuckDB lets no other process open it."""


@dataclass(frozen=True)
class RecordData:
    """Everything a recording shows, read from the warehouse (rows sorted by time)."""

    wagon_id: str
    event: dict[str, Any] | None
    """The event's row of ``events`` when one event is recorded."""
    revision: str | None
    """Model revision of the predictions; ``None`` when the wagon has none."""
    window: tuple[np.datetime64, np.datetime64] | None
    """Time range recorded (one event's, or the one asked for); ``None`` for the whole
    timeline."""
    samples: pl.DataFrame
    predictions: pl.DataFrame
    events: pl.DataFrame
    flags: pl.DataFrame
    notes: list[str] = field(default_factory=list)
    estimates: pl.DataFrame = field(default_factory=pl.DataFrame)
    """``v_contact_estimates`` rows of the revision (the virtual sensor), per second over the
    recorded range (recomputed where stored per minute:
    :func:`~fleetbrake.viz.estimates.per_second_estimates`); empty when the database has
    none."""
    stored_wagon: WagonConfig | None = None
    """The wagon's registry entry as the last ``run`` stored it (``wagon_registry``)."""
    stored_wagon_source: str | None = None
    """The ``fleet.toml`` that entry came from."""


def open_read_only(db: str | os.PathLike[str], wait_s: float) -> Warehouse:
    """The warehouse opened read-only, waiting up to ``wait_s`` while another process writes
    it (DuckDB lets no other process open the file meanwhile): :class:`RecordLockedError`
    after that, :class:`RecordError` when it cannot be opened at all."""
    deadline = time.monotonic() + max(wait_s, 0.0)
    while True:
        try:
            return open_warehouse(db, read_only=True)
        except WarehouseLockedError as error:
            if time.monotonic() >= deadline:
                raise RecordLockedError(
                    f"{db}: cannot be read now: another process is writing to it and DuckDB "
                    "lets no other process open it meanwhile. Run again when it has finished, "
                    f"or give --wait SECONDS. ({error})"
                ) from None
            time.sleep(_WAIT_POLL_S)
        except WarehouseError as error:
            raise RecordError(f"cannot open the database: {error}") from None


# --------------------------------------------------------------------------------------------
# Columns of the frames read.


def frame_times(frame: pl.DataFrame, column: str = "time_utc") -> Times:
    """A timestamp column as ``datetime64[ns]``."""
    return frame[column].to_numpy().astype("datetime64[ns]")


def frame_values(frame: pl.DataFrame, column: str) -> Floats:
    """A numeric column as float64, NaN where null."""
    return frame[column].cast(pl.Float64).fill_null(float("nan")).to_numpy()


def instant(value: Any) -> np.datetime64:
    """A timestamp (datetime, numpy or polars value) as ``datetime64[ns]``."""
    return np.datetime64(value, "ns")


def _microseconds(value: Any) -> np.datetime64:
    """A timestamp as ``datetime64[us]`` (``.item()`` gives a ``datetime`` to bind)."""
    return np.datetime64(value, "us")


# --------------------------------------------------------------------------------------------
# The queries. DuckDB 2: ``execute()`` returns the connection (no ``.pl()``) and leaves its
# result open until fetched to the end, so every query here goes through a relation, fully
# fetched.


def _rows(
    con: duckdb.DuckDBPyConnection, name: str, params: dict[str, Any] | None = None
) -> list[tuple[Any, ...]]:
    return con.sql(sql(name), params=params or {}).fetchall()


def _frame(con: duckdb.DuckDBPyConnection, name: str, params: dict[str, Any]) -> pl.DataFrame:
    return con.sql(sql(name), params=params).pl()


def _listing(names: list[str], limit: int = 12) -> str:
    shown = ", ".join(names[:limit])
    more = len(names) - limit
    return shown + (f", ... ({more} more)" if more > 0 else "") if names else "none"


def _check_wagon(con: duckdb.DuckDBPyConnection, tables: set[str], wagon_id: str, db: str) -> None:
    ((n_samples, n_events),) = _rows(con, "q_record_wagon_rows", {"wagon_id": wagon_id})
    if n_samples or n_events:
        return
    if "files" in tables:
        reasons = [r[0] for r in _rows(con, "q_record_quarantined_files", {"wagon_id": wagon_id})]
        if reasons:
            raise RecordError(
                f"{db}: wagon {wagon_id} has no samples: all its files were quarantined "
                f"({len(reasons)}; first: {reasons[0]})"
            )
    known = [r[0] for r in _rows(con, "q_record_wagons")]
    raise RecordError(
        f"{db}: unknown wagon {wagon_id}: it has no samples and no events there "
        f"(wagons: {_listing(known)})"
    )


def _resolve_revision(
    con: duckdb.DuckDBPyConnection,
    tables: set[str],
    wagon_id: str,
    requested: str | None,
    db: str,
) -> tuple[str | None, list[str]]:
    notes: list[str] = []
    revisions: list[str] = []
    current: str | None = None
    if "model_revisions" in tables:
        rows = _rows(con, "q_record_model_revisions")
        revisions = [r[0] for r in rows]
        currents = [r[0] for r in rows if r[1]]
        current = currents[-1] if currents else None
    predicted: list[str] = []
    if "predictions" in tables:
        predicted = [
            r[0] for r in _rows(con, "q_record_predicted_revisions", {"wagon_id": wagon_id})
        ]
    if requested is not None:
        if requested not in revisions and requested not in predicted:
            known = sorted(set(revisions) | set(predicted))
            raise RecordError(
                f"{db}: unknown model revision {requested!r} (revisions: {_listing(known)})"
            )
        return requested, notes
    if current is not None:
        return current, notes
    if "declared" in predicted or "declared" in revisions:
        return "declared", notes
    if predicted:
        notes.append(
            f"no current model revision recorded; predictions shown are of {predicted[0]!r}"
        )
        return predicted[0], notes
    return None, notes


def _event_window(
    con: duckdb.DuckDBPyConnection,
    tables: set[str],
    wagon_id: str,
    event_id: str,
    revision: str | None,
    db: str,
) -> tuple[dict[str, Any], tuple[np.datetime64, np.datetime64]]:
    """The event's row, and the time range its recording shows: from :data:`EVENT_LEAD_S`
    before activation to its last predicted second (else :data:`EVENT_TAIL_S` after release)."""
    found = _frame(con, "q_record_event", {"event_id": event_id})
    if found.height == 0:
        known = [r[0] for r in _rows(con, "q_record_event_ids", {"wagon_id": wagon_id})]
        raise RecordError(
            f"{db}: unknown event {event_id} (events of wagon {wagon_id}: {_listing(known)})"
        )
    event = found.row(0, named=True)
    if event["wagon_id"] != wagon_id:
        raise RecordError(
            f"{db}: event {event_id} is of wagon {event['wagon_id']}, not of wagon {wagon_id}"
        )
    start, release = _microseconds(event["start_utc"]), _microseconds(event["end_utc"])
    end = release + np.timedelta64(int(EVENT_TAIL_S), "s")
    if revision is not None and "predictions" in tables:
        ((last,),) = _rows(
            con,
            "q_record_event_last_prediction",
            {"event_id": event_id, "model_revision": revision},
        )
        if last is not None:
            end = max(_microseconds(last), release)
    return event, (start - np.timedelta64(int(EVENT_LEAD_S), "s"), end)


def _stored_wagon(
    con: duckdb.DuckDBPyConnection, tables: set[str], wagon_id: str, notes: list[str]
) -> tuple[WagonConfig | None, str | None]:
    """The wagon's entry in ``wagon_registry`` (what the last ``run`` simulated it with)."""
    if "wagon_registry" not in tables:
        return None, None
    rows = _rows(con, "q_record_stored_wagon", {"wagon_id": wagon_id})
    if not rows:
        return None, None
    try:
        return WagonConfig(**json.loads(rows[0][0])), rows[0][1]
    except (ValueError, TypeError) as error:
        notes.append(f"wagon {wagon_id}: stored registry entry unusable ({error})")
        return None, None


def load_record_data(
    wh: Warehouse,
    wagon_id: str,
    *,
    event_id: str | None = None,
    revision: str | None = None,
    window: tuple[np.datetime64, np.datetime64] | None = None,
) -> RecordData:
    """Read what a recording of ``wagon_id`` (or of one of its events, or of the time range
    ``window``, both ends included) shows.

    ``revision``: the model revision of the predictions and estimates; default the current
    one (``model_revisions.is_current``), else ``declared``. Raises :class:`RecordError`
    naming the database and the unknown wagon, event or revision.
    """
    con = wh.con
    db = str(wh.path)
    tables = {r[0] for r in _rows(con, "q_record_tables")}
    for needed in ("samples", "events"):
        if needed not in tables:
            raise RecordError(f"{db}: not a fleetbrake warehouse (no table {needed})")
    _check_wagon(con, tables, wagon_id, db)
    chosen, notes = _resolve_revision(con, tables, wagon_id, revision, db)

    event: dict[str, Any] | None = None
    if window is not None:
        window = (_microseconds(window[0]), _microseconds(window[1]))
    if event_id is not None:
        event, window = _event_window(con, tables, wagon_id, event_id, chosen, db)
    # rows at an instant inside the window, ranges overlapping it (no window: every row)
    bounds: dict[str, Any] = {
        "from_utc": None if window is None else window[0].item(),
        "to_utc": None if window is None else window[1].item(),
    }
    of_wagon = {"wagon_id": wagon_id} | bounds

    samples = _frame(con, "q_record_samples", of_wagon)
    events = _frame(con, "q_record_events", of_wagon)
    if "flags" in tables:
        # an event's flags, and the wagon's others in its window
        flags = _frame(con, "q_record_flags", of_wagon | {"event_id": event_id})
    else:
        flags = pl.DataFrame()
        notes.append("the database has no flags table yet (no `run` has raised flags)")

    predictions = pl.DataFrame()
    if chosen is None or "predictions" not in tables:
        notes.append(
            f"wagon {wagon_id} has no predictions yet (its events were not simulated): "
            "measurements only"
        )
    else:
        predictions = _frame(con, "q_record_predictions", of_wagon | {"model_revision": chosen})
        if predictions.height == 0:
            what = f"event {event_id}" if event_id is not None else f"wagon {wagon_id}"
            notes.append(
                f"{what} has no predictions of model revision {chosen!r} yet: measurements only"
            )
    stored, source = _stored_wagon(con, tables, wagon_id, notes)
    estimates = pl.DataFrame()
    old_estimates = (
        "v_contact_estimates" in tables and not _rows(con, "q_estimates_view_current")[0][0]
    )
    if old_estimates:
        notes.append(
            f"{db}: its contact estimates are of an older fleetbrake (schema version 2): a "
            "`fleetbrake run` on it brings them up to date"
        )
    elif chosen is not None and "v_contact_estimates" in tables:
        estimates = per_second_estimates(
            wh,
            wagon_id,
            stored,
            chosen,
            window,
            _frame(con, "q_record_estimates", of_wagon | {"model_revision": chosen}),
            notes,
        )
    if chosen is not None and estimates.height == 0 and not old_estimates:
        notes.append(
            f"wagon {wagon_id} has no contact estimates of model revision {chosen!r} in the "
            "recorded time range: open-loop prediction only"
        )
    if samples.height == 0:
        notes.append(f"wagon {wagon_id} has no samples in the recorded time range")
    return RecordData(
        wagon_id=wagon_id,
        event=event,
        revision=chosen,
        window=window,
        samples=samples,
        predictions=predictions,
        events=events,
        flags=flags,
        notes=notes,
        estimates=estimates,
        stored_wagon=stored,
        stored_wagon_source=source,
    )
