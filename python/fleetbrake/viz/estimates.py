"""The contact estimates a recording shows: per second over the whole recorded range
(interface.md v3). The warehouse stores them per second inside the estimate windows and per
minute elsewhere (:mod:`fleetbrake.warehouse.estimate_windows`); where the range holds minute
rows, :func:`per_second_estimates` recomputes the seconds by running the estimation stage's
own computation (:func:`~fleetbrake.simulation.estimates.wagon.estimate_wagon`, deterministic)
over each of the wagon's spans that overlap the range, from the span's samples, with the
revision's effects and σ_w and the wagon's stored registry entry, and the default estimation
configuration (the one ``run`` uses unless told otherwise). Inside the windows the recomputed
seconds are the stored ones.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import polars as pl

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.simulation.estimates import (
    EstimateTask,
    EstimationConfig,
    estimate_wagon,
    revision_power_noise,
)
from fleetbrake.simulation.predictions import revision as stored_revision
from fleetbrake.warehouse.connection import Warehouse, sql

__all__ = ["MINUTE_S", "per_second_estimates"]

MINUTE_S = 60
"""``resolution_s`` of a stored minute row."""


def per_second_estimates(
    wh: Warehouse,
    wagon_id: str,
    wagon: WagonConfig | None,
    revision: str,
    window: tuple[np.datetime64, np.datetime64] | None,
    stored: pl.DataFrame,
    notes: list[str],
) -> pl.DataFrame:
    """``stored`` (the rows of ``q_record_estimates.sql`` in ``window``, None: the whole
    timeline) when they are all per second; else the per-second estimates of the range,
    recomputed (the same columns, ``resolution_s`` 1), a note saying so added to ``notes``.
    Without the wagon's stored registry entry (``wagon`` None) the stored rows are shown,
    with a note."""
    if stored.height == 0 or not (stored["resolution_s"] == MINUTE_S).any():
        return stored
    if wagon is None:
        notes.append(
            f"wagon {wagon_id} has no stored registry entry: its contact estimates are shown "
            "per minute where they are stored so"
        )
        return stored
    config = EstimationConfig()
    rev = stored_revision(wh, revision)
    power, _ = revision_power_noise(wh, rev, config)
    bounds: dict[str, Any] = {
        "from_utc": None if window is None else window[0].item(),
        "to_utc": None if window is None else window[1].item(),
    }
    spans = wh.con.sql(
        sql("q_record_estimate_spans"),
        params={"wagon_id": wagon_id, "gap_s": config.chain.bridge_max_s} | bounds,
    ).fetchall()
    parts = []
    for start_utc, end_utc in spans:
        samples = wh.con.sql(
            sql("q_record_span_samples"),
            params={"wagon_id": wagon_id, "from_utc": start_utc, "to_utc": end_utc},
        ).to_arrow_table()
        result = estimate_wagon(EstimateTask(wagon, samples, rev, config, power, "", ""))
        part = pl.from_arrow(result.rows)
        if isinstance(part, pl.DataFrame) and part.height:
            parts.append(part)
    if not parts:
        return stored
    frame = pl.concat(parts, how="vertical")
    if window is not None:
        frame = frame.filter(pl.col("time_utc").is_between(bounds["from_utc"], bounds["to_utc"]))
    notes.append(
        f"wagon {wagon_id}: contact estimates recomputed per second over "
        f"{len(spans)} span(s) (stored per minute outside the estimate windows)"
    )
    return frame.select(
        [pl.col(c).cast(stored.schema[c]) for c in stored.columns if c != "resolution_s"]
    ).with_columns(pl.lit(1, dtype=stored.schema["resolution_s"]).alias("resolution_s"))
