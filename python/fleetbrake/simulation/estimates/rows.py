"""The rows of ``contact_estimates`` (``warehouse/sql/schema_estimates.sql``): their columns
(:data:`ESTIMATE_SCHEMA`) and a wagon's estimate as those rows in Arrow
(:func:`estimate_rows`)."""

from __future__ import annotations

import datetime as dt

import numpy as np
import polars as pl
import pyarrow as pa  # type: ignore[import-untyped]  # ships no type information

from fleetbrake.model.estimator import ContactEstimate

__all__ = ["ESTIMATE_SCHEMA", "ROWS_SCHEMA", "estimate_rows"]


ESTIMATE_SCHEMA = pl.Schema(
    {
        "wagon_id": pl.String(),
        "time_utc": pl.Datetime("us"),
        "model_revision": pl.String(),
        "contact_mean_c": pl.Float64(),
        "contact_mean_lo_c": pl.Float64(),
        "contact_mean_hi_c": pl.Float64(),
        "contact_max_c": pl.Float64(),
        "contact_max_hi_c": pl.Float64(),
        "smoothed_contact_mean_c": pl.Float64(),
        "smoothed_contact_mean_lo_c": pl.Float64(),
        "smoothed_contact_mean_hi_c": pl.Float64(),
        "unexplained_power_w": pl.Float64(),
        "unexplained_power_lo_w": pl.Float64(),
        "unexplained_power_hi_w": pl.Float64(),
        "innovation_k": pl.Float64(),
        "innovation_sd_k": pl.Float64(),
        "smoothed_contact_max_c": pl.Float64(),
        "smoothed_contact_max_hi_c": pl.Float64(),
        "smoothed_unexplained_power_w": pl.Float64(),
        "smoothed_unexplained_power_lo_w": pl.Float64(),
        "smoothed_unexplained_power_hi_w": pl.Float64(),
    }
)
"""The columns of ``contact_estimates`` (those of ``v_contact_estimates`` first)."""


ROWS_SCHEMA = pa.schema(
    [
        (
            name,
            pa.float64()
            if kind == pl.Float64()
            else pa.timestamp("us")
            if kind == pl.Datetime("us")
            else pa.large_string(),
        )
        for name, kind in ESTIMATE_SCHEMA.items()
    ]
)
"""The Arrow schema of a wagon's rows (:func:`estimate_rows`): :data:`ESTIMATE_SCHEMA`'s
columns, the strings large (as polars hands them over)."""


def estimate_rows(
    wagon_id: str, revision: str, t0: dt.datetime | None, est: ContactEstimate | None
) -> pa.Table:
    """The wagon's rows of ``contact_estimates`` as Arrow, built from the estimate's arrays
    (a NaN is stored as null; a column not smoothed is null throughout)."""
    if est is None or t0 is None or est.time_s.size == 0:
        return ROWS_SCHEMA.empty_table()
    n = est.time_s.size
    times = np.datetime64(t0, "us") + (np.rint(est.time_s).astype(np.int64) * 1_000_000).astype(
        "timedelta64[us]"
    )
    columns: dict[str, np.ndarray | None] = {
        "contact_mean_c": est.contact_mean_c,
        "contact_mean_lo_c": est.contact_mean_lo_c,
        "contact_mean_hi_c": est.contact_mean_hi_c,
        "contact_max_c": est.contact_max_c,
        "contact_max_hi_c": est.contact_max_hi_c,
        "smoothed_contact_mean_c": est.smoothed_contact_mean_c,
        "smoothed_contact_mean_lo_c": est.smoothed_contact_mean_lo_c,
        "smoothed_contact_mean_hi_c": est.smoothed_contact_mean_hi_c,
        "unexplained_power_w": est.unexplained_power_w,
        "unexplained_power_lo_w": est.unexplained_power_lo_w,
        "unexplained_power_hi_w": est.unexplained_power_hi_w,
        "innovation_k": est.innovation_k,
        "innovation_sd_k": np.sqrt(est.innovation_var_k2),
        "smoothed_contact_max_c": est.smoothed_contact_max_c,
        "smoothed_contact_max_hi_c": est.smoothed_contact_max_hi_c,
        "smoothed_unexplained_power_w": est.smoothed_unexplained_power_w,
        "smoothed_unexplained_power_lo_w": est.smoothed_unexplained_power_lo_w,
        "smoothed_unexplained_power_hi_w": est.smoothed_unexplained_power_hi_w,
    }

    def floats(values: np.ndarray | None) -> pa.Array:
        if values is None:
            return pa.nulls(n, pa.float64())
        return pa.array(values, pa.float64(), from_pandas=True)  # NaN: null

    arrays = {
        "wagon_id": pa.repeat(pa.scalar(wagon_id, pa.large_string()), n),
        "time_utc": pa.array(times, pa.timestamp("us")),
        "model_revision": pa.repeat(pa.scalar(revision, pa.large_string()), n),
        **{name: floats(values) for name, values in columns.items()},
    }
    return pa.table([arrays[name] for name in ROWS_SCHEMA.names], schema=ROWS_SCHEMA)
