"""The flags' rows in the warehouse: a wagon's findings as flags with stable ids
(:func:`flag_ids`), its rows of ``flags`` replaced with its judgement recorded in
``flagged_wagons`` (:func:`store_flags`), and what is stored read back (:func:`stored_flags`,
:func:`stale_wagons`).

``flag_id`` is ``<kind>-<wagon>-<start as YYYYMMDDTHHMMSS>`` (``-2``, ... if taken), so the
same data give the same ids, and a flag found again keeps its ``detected_utc``.

::

    from fleetbrake.flags.storage import stale_wagons, stored_flags

    stale_wagons(wh, "declared", FlagConfig())   # the wagons a run must judge again
    stored_flags(wh)                             # every flag stored
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import polars as pl

from fleetbrake.flags.config import FlagConfig
from fleetbrake.flags.records import Finding, Flag
from fleetbrake.simulation.store import utc_now
from fleetbrake.warehouse.connection import Warehouse, sql

if TYPE_CHECKING:
    import duckdb

__all__ = ["flag_ids", "stale_wagons", "store_flags", "stored_flags"]


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


def stale_wagons(wh: Warehouse, revision_name: str, config: FlagConfig) -> list[str]:
    """The wagons with samples whose stored flags are out of date for ``revision_name`` and
    ``config`` (``q_flags_stale_wagons.sql``; ``flagged_wagons`` records each judgement):
    never judged with the revision, judged before a file of theirs was ingested or their
    timeline or estimates of the revision were written, judged with other thresholds
    (:meth:`FlagConfig.key`; or before the key was recorded), or whose rows of ``flags``
    are not the ones their judgement stored. What a run must judge besides the wagons its
    stages changed, so that a run that stopped between its simulation and its flags leaves
    nothing stale behind (``fleetbrake.app.run``)."""
    rows = wh.con.execute(
        sql("q_flags_stale_wagons"), {"revision": revision_name, "config_key": config.key()}
    ).fetchall()
    return [str(r[0]) for r in rows]


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


def store_flags(
    wh: Warehouse,
    wagons: Sequence[str],
    flags: Sequence[Flag],
    revision_name: str,
    config_key: str,
) -> None:
    """Replace the flags of ``wagons`` in one transaction, recording that they were judged
    with ``revision_name`` and the thresholds of ``config_key``, and how many flags each
    has (``flagged_wagons``); a flag identical to a stored one keeps its ``detected_utc``."""
    now = utc_now()
    wagon_ids = list(wagons)
    with wh.transaction() as con:
        old = con.execute(sql("q_flags_stored"), {"wagon_ids": wagon_ids}).fetchall()
        kept = {tuple(r[:7]): r[7] for r in old}
        con.execute(sql("q_flags_delete"), {"wagon_ids": wagon_ids})
        con.execute(sql("q_flags_delete_flagged_wagons"), {"wagon_ids": wagon_ids})
        if flags:
            _insert_flags(con, flags, kept, now)
        judged = {
            "wagon_ids": wagon_ids,
            "revision": revision_name,
            "updated_utc": now,
            "config_key": config_key,
        }
        if wagon_ids:  # after the flags: each wagon's count of them is recorded
            con.execute(sql("q_flags_insert_flagged_wagons"), judged)


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
