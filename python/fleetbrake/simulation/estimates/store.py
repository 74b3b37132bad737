"""The estimation stage's tables (``warehouse/sql/schema_estimates.sql``): the partitions read
for the workers (:func:`estimate_task`, :func:`estimation_chunk`: spans), the keys each span
was estimated from (``estimated_spans``, :func:`estimated_spans`), a revision's fitted noise
(``estimator_noise``, :func:`stored_noise`, :func:`store_noise`), and the rows written
(:func:`replace_estimates`: whole wagons, one transaction) and read back
(:func:`wagon_estimates`)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.ingest.spans import LedgerSpan, Span, SpanKey, ranges_of
from fleetbrake.model.estimator import EstimatorNoise
from fleetbrake.simulation.estimates.config import EstimationConfig
from fleetbrake.simulation.estimates.rows import ESTIMATE_SCHEMA
from fleetbrake.simulation.estimates.wagon import EstimateChunk, EstimateResult, EstimateTask
from fleetbrake.simulation.predictions import Revision
from fleetbrake.simulation.store import span_table, utc_now
from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = [
    "EstimatedSpan",
    "StoredNoise",
    "estimate_task",
    "estimated_spans",
    "estimation_chunk",
    "forget_wagon",
    "replace_estimates",
    "store_noise",
    "stored_noise",
    "wagon_estimates",
]


@dataclass(frozen=True)
class EstimatedSpan:
    """A row of ``estimated_spans``: the span as estimated (``ledger``) and its noise."""

    ledger: LedgerSpan
    seconds: int
    measurement_k: float | None = None
    """σ_v it was estimated with (the span's own unless given)."""
    power_w_per_sqrt_s: float | None = None
    """σ_w it was estimated with (the revision's)."""


@dataclass(frozen=True)
class StoredNoise:
    """A row of ``estimator_noise``."""

    noise: EstimatorNoise
    method: str
    fit_wagons: str | None
    fit_readings: int | None
    log_likelihood: float | None
    at_floor: bool | None


def estimate_task(
    wh: Warehouse,
    wagon: WagonConfig,
    span: Span,
    rev: Revision,
    config: EstimationConfig,
    power_noise_w_per_sqrt_s: float,
    *,
    model_key: str,
) -> EstimateTask:
    """The span's partition, read from the warehouse by the parent."""
    params = {"wagon_id": wagon.wagon_id, "from_utc": span.start_utc, "to_utc": span.end_utc}
    samples = wh.con.sql(sql("q_simulation_span_samples"), params=params).to_arrow_table()
    return EstimateTask(
        wagon, samples, rev, config, power_noise_w_per_sqrt_s, span.data_key, model_key, span
    )


def estimation_chunk(
    wh: Warehouse,
    units: Iterable[tuple[WagonConfig, Span, str]],
    rev: Revision,
    config: EstimationConfig,
    power_noise_w_per_sqrt_s: float,
) -> EstimateChunk:
    """The chunk's partitions, read from the warehouse with one query, the spans' time ranges
    only (by the parent: the workers never open it)."""
    todo = tuple(units)
    ranges = ranges_of(s for _, s, _ in todo)
    samples = span_table(wh, "q_simulation_chunk_span_samples", ranges)
    return EstimateChunk(todo, samples, rev, config, power_noise_w_per_sqrt_s)


def stored_noise(wh: Warehouse, revision: str) -> StoredNoise | None:
    """The σ_w fitted for ``revision`` (None: none is stored, the default applies)."""
    rows = wh.con.execute(sql("q_estimates_noise"), {"revision": revision}).fetchall()
    if not rows:
        return None
    v, w, method, wagons, readings, loglik, at_floor, _ = rows[0]
    return StoredNoise(
        EstimatorNoise(float(v), float(w)), method, wagons, readings, loglik, at_floor
    )


def store_noise(wh: Warehouse, revision: str, stored: StoredNoise) -> None:
    """Store ``revision``'s fitted noise (replacing any stored for it)."""
    wh.con.execute(
        sql("q_estimates_insert_noise"),
        {
            "revision": revision,
            "measurement_k": stored.noise.measurement_k,
            "power_w_per_sqrt_s": stored.noise.power_w_per_sqrt_s,
            "method": stored.method,
            "fit_wagons": stored.fit_wagons,
            "fit_readings": stored.fit_readings,
            "log_likelihood": stored.log_likelihood,
            "at_floor": stored.at_floor,
            "created_utc": utc_now(),
        },
    )


def estimated_spans(wh: Warehouse, revision: str) -> dict[SpanKey, EstimatedSpan]:
    """The spans estimated with ``revision``, from what and with which noise."""
    rows = wh.con.execute(sql("q_estimates_estimated_spans"), {"revision": revision}).fetchall()
    out = {}
    for r in rows:
        row = LedgerSpan(str(r[0]), r[1], r[2], str(r[3]), str(r[4]), r[5])
        out[row.key] = EstimatedSpan(row, int(r[6]), r[7], r[8])
    return out


def replace_estimates(
    wh: Warehouse, revision: str, results: Sequence[EstimateResult], *, delete: bool = True
) -> None:
    """Replace the rows of ``revision`` of every wagon of ``results``, all in one transaction
    (each wagon whole-old or whole-new whatever happens), one bulk insert per table (Arrow
    in), recording the keys of each.

    ``delete=False``: none of the wagons holds rows of ``revision``
    (:func:`estimated_wagon_ids`), so the deletes, each a scan of its whole table (which grows
    with the fleet), are skipped. The wagons' rows of a revision a closed loop made other than
    ``revision`` are deleted in any case (estimates are kept for ``declared`` and the last
    close-loop revision: ``q_estimates_delete_superseded.sql``)."""
    if not results:
        return
    if len({r.wagon_id for r in results}) != len(results):
        raise ValueError("replace_estimates: a wagon given twice")
    key = {"wagon_ids": [r.wagon_id for r in results], "revision": revision}
    tables = [r.rows for r in results if r.rows.num_rows]
    stamps = pa.table(
        {
            "wagon_id": pa.array([r.wagon_id for r in results], pa.string()),
            "model_revision": pa.array([revision] * len(results), pa.string()),
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
    with wh.transaction() as con:
        if delete:
            con.execute(sql("q_estimates_delete_wagons"), key)
            con.execute(sql("q_estimates_delete_estimated_wagons"), key)
        con.execute(sql("q_estimates_delete_superseded"), key)
        batches = [("estimated_batch", stamps, "q_estimates_insert_estimated_wagons")]
        if tables:
            rows = tables[0] if len(tables) == 1 else pa.concat_tables(tables)
            batches.insert(0, ("estimate_batch", rows, "q_estimates_insert"))
        for name, table, statement in batches:
            con.register(name, table)
            try:
                con.execute(sql(statement))
            finally:
                con.unregister(name)


def forget_wagon(wh: Warehouse, wagon_id: str) -> None:
    """Delete every row of a wagon whose samples are gone, of every revision."""
    with wh.transaction() as con:
        con.execute(sql("q_estimates_forget_wagon"), {"wagon_id": wagon_id})
        con.execute(sql("q_estimates_forget_estimated_wagon"), {"wagon_id": wagon_id})


def wagon_estimates(wh: Warehouse, wagon_id: str, revision: str) -> pl.DataFrame:
    """One wagon's stored estimates of ``revision`` by time, every column of
    ``contact_estimates`` (:data:`~fleetbrake.simulation.estimates.rows.ESTIMATE_SCHEMA`; empty
    if none)."""
    frame = wh.con.sql(
        sql("q_estimates_wagon"), params={"wagon_id": wagon_id, "revision": revision}
    ).pl()
    if frame.height == 0:
        return pl.DataFrame(schema=ESTIMATE_SCHEMA)
    return frame.select(list(ESTIMATE_SCHEMA)).cast(dict(ESTIMATE_SCHEMA))
