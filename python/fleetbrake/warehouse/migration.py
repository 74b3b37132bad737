"""The migration of a warehouse to schema version 3 (:func:`migrate_to_v3`): the contact
estimates stored per second inside the estimate windows, per minute elsewhere
(:mod:`fleetbrake.warehouse.estimate_windows`), kept for ``declared`` and the current revision.

Run by :func:`fleetbrake.warehouse.connection.apply_schema` on a database of an older version
opened for writing, after the schema statements gave ``contact_estimates.resolution_s`` (1 on
the rows of before) and before the version is recorded: each step is a transaction that leaves
the warehouse consistent, so an interrupted migration leaves the old version recorded and the
next open runs it again, which completes it (compacting a compacted wagon changes nothing).
"""

from __future__ import annotations

import logging
from itertools import groupby

import duckdb

from fleetbrake.warehouse.estimate_windows import compact_estimates
from fleetbrake.warehouse.sqlfiles import sql

__all__ = ["WAGONS_PER_STEP", "migrate_to_v3"]

logger = logging.getLogger(__name__)

WAGONS_PER_STEP = 20
"""Wagons compacted per transaction (and per progress line) by the migration."""


def migrate_to_v3(
    con: duckdb.DuckDBPyConnection, db_label: str, wagons_per_step: int | None = None
) -> None:
    """Bring the contact estimates of the database ``db_label`` to schema version 3:
    ``resolution_s`` NOT NULL without a default, the estimates of the closed-loop revisions
    other than the current one deleted (one transaction), then every wagon's estimates of each
    revision kept compacted, ``wagons_per_step`` wagons per transaction, a progress line
    logged after each (None: :data:`WAGONS_PER_STEP`)."""
    per_step = wagons_per_step or WAGONS_PER_STEP
    con.execute("BEGIN TRANSACTION")
    try:
        con.execute(sql("q_migrate3_resolution_not_null"))
        con.execute(sql("q_migrate3_resolution_no_default"))
        con.execute(sql("q_migrate3_superseded"))
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise
    pairs = con.execute(sql("q_migrate3_estimated")).fetchall()
    if not pairs:
        return
    logger.info(
        "%s: schema version 3: compacting the contact estimates of %d wagon revisions",
        db_label,
        len(pairs),
    )
    done = 0
    for revision, rows in groupby(pairs, key=lambda pair: str(pair[0])):
        wagon_ids = [str(wagon_id) for _, wagon_id in rows]
        for start in range(0, len(wagon_ids), per_step):
            step = wagon_ids[start : start + per_step]
            result = compact_estimates(con, [(w, None, None) for w in step], revision)
            done += len(step)
            logger.info(
                "%s: schema version 3: %d of %d wagon revisions compacted (revision %s: %d "
                "per-second rows become %d minute rows)",
                db_label,
                done,
                len(pairs),
                revision,
                result.seconds_removed,
                result.minutes,
            )
