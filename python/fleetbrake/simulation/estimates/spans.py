"""The estimation stage's writes by span: a batch of spans' rows of ``contact_estimates``
replaced, with what each was estimated from (``estimated_spans``), in one transaction
(:func:`replace_span_estimates`), and the rows of spans that no longer exist removed
(:func:`forget_span_estimates`). Both delete by the spans' time ranges, every resolution
stored there."""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from typing import Any

import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.ingest.spans import envelope, span_windows
from fleetbrake.simulation.estimates.wagon import EstimateResult
from fleetbrake.simulation.store import utc_now
from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = ["forget_span_estimates", "replace_span_estimates"]


def _delete(
    con: Any, revision: str, ranges: Sequence[tuple[str, dt.datetime, dt.datetime]]
) -> None:
    params = {**span_windows(ranges), "revision": revision}
    con.execute(sql("q_estimates_delete_span_rows"), {**params, **envelope(ranges)})
    con.execute(sql("q_estimates_delete_estimated_spans"), params)


def replace_span_estimates(wh: Warehouse, revision: str, results: Sequence[EstimateResult]) -> None:
    """Replace the rows of ``revision`` of every span of ``results``, all in one transaction
    (each span whole-old or whole-new whatever happens): one delete by the spans' time
    ranges and one bulk insert per table (Arrow in), recording the keys and noise of each.
    The wagons' estimates of a revision a closed loop made before the current one are
    deleted with them (estimates are kept for ``declared`` and the current revision:
    ``q_estimates_delete_superseded.sql``)."""
    if not results:
        return
    spans = [r.span for r in results if r.span is not None]
    if len(spans) != len(results):
        raise ValueError("replace_span_estimates: a result without its span")
    if len({span.key for span in spans}) != len(results):
        raise ValueError("replace_span_estimates: a span given twice")
    tables = [r.rows for r in results if r.rows.num_rows]
    stamps = pa.table(
        {
            "wagon_id": pa.array([r.wagon_id for r in results], pa.string()),
            "model_revision": pa.array([revision] * len(results), pa.string()),
            "span_start_utc": pa.array([s.start_utc for s in spans], pa.timestamp("us")),
            "span_end_utc": pa.array([s.end_utc for s in spans], pa.timestamp("us")),
            "data_key": pa.array([r.data_key for r in results], pa.string()),
            "model_key": pa.array([r.model_key for r in results], pa.string()),
            "seconds": pa.array([r.seconds for r in results], pa.int64()),
            "measurement_k": pa.array(
                [None if r.noise is None else r.noise.measurement_k for r in results],
                pa.float64(),
            ),
            "power_w_per_sqrt_s": pa.array(
                [None if r.noise is None else r.noise.power_w_per_sqrt_s for r in results],
                pa.float64(),
            ),
            "created_utc": pa.array([utc_now()] * len(results), pa.timestamp("us")),
        }
    )
    ranges = [(s.wagon_id, s.start_utc, s.end_utc) for s in spans]
    wagon_ids = sorted({s.wagon_id for s in spans})
    with wh.transaction() as con:
        _delete(con, revision, ranges)
        # a closed loop's older revision: its estimates of these wagons replaced by these
        con.execute(
            sql("q_estimates_delete_superseded"), {"wagon_ids": wagon_ids, "revision": revision}
        )
        batches = [("estimated_batch", stamps, "q_estimates_insert_estimated_spans")]
        if tables:
            rows = tables[0] if len(tables) == 1 else pa.concat_tables(tables)
            batches.insert(0, ("estimate_batch", rows, "q_estimates_insert"))
        for name, table, statement in batches:
            con.register(name, table)
            try:
                con.execute(sql(statement))
            finally:
                con.unregister(name)


def forget_span_estimates(
    wh: Warehouse, revision: str, ranges: Sequence[tuple[str, dt.datetime, dt.datetime]]
) -> None:
    """Delete the rows of ``revision`` in the time ranges of spans that no longer exist
    (merged, cut again or gone), in one transaction."""
    if not ranges:
        return
    with wh.transaction() as con:
        _delete(con, revision, ranges)
