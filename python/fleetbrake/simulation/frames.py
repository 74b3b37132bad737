"""One wagon's simulated spans as the rows of the stage's tables: ``predictions`` (each event
window, one row per second), ``timeline`` (the block at every logged second) and
``timeline_segments`` (where and how each segment was anchored), as polars frames with the
tables' columns (``shared/spec/interface.md``). Built column by column in bulk: numpy arrays
per window or span, the strings gathered from one value per window.

::

    from fleetbrake.simulation.frames import prediction_frame, segment_frame, timeline_frame

    predictions = prediction_frame("SGG-0001", "declared", windows)
"""

from __future__ import annotations

import numpy as np
import polars as pl

from fleetbrake.simulation.chains import EventWindow, SpanResult
from fleetbrake.simulation.series import FloatArray, WagonSeries

__all__ = [
    "PREDICTION_SCHEMA",
    "SEGMENT_SCHEMA",
    "TIMELINE_SCHEMA",
    "prediction_frame",
    "segment_frame",
    "timeline_frame",
]


def _times(series: WagonSeries, k: np.ndarray) -> np.ndarray:
    return np.datetime64(series.t0, "us") + (k.astype(np.int64) * 1_000_000).astype(
        "timedelta64[us]"
    )


PREDICTION_SCHEMA = pl.Schema(
    {
        "event_id": pl.String(),
        "wagon_id": pl.String(),
        "time_utc": pl.Datetime("us"),
        "model_revision": pl.String(),
        "phase": pl.String(),
        "measured_sensor_c": pl.Float64(),
        "predicted_sensor_c": pl.Float64(),
        "predicted_contact_mean_c": pl.Float64(),
        "predicted_contact_max_c": pl.Float64(),
        "speed_kmh": pl.Float64(),
        "brake_pressure_bar": pl.Float64(),
        "ambient_c": pl.Float64(),
        "flux_w_m2": pl.Float64(),
    }
)


def prediction_frame(
    wagon_id: str, rev: str, windows: list[tuple[WagonSeries, EventWindow, FloatArray]]
) -> pl.DataFrame:
    """The windows as rows of ``predictions`` (built column by column, in bulk)."""
    if not windows:
        return pl.DataFrame(schema=PREDICTION_SCHEMA)
    columns: dict[str, list[np.ndarray]] = {name: [] for name in PREDICTION_SCHEMA}
    window_of: list[np.ndarray] = []  # each row's window (index into ``windows``)
    heating: list[np.ndarray] = []
    for i, (series, w, speed) in enumerate(windows):
        k = np.arange(w.start, w.stop + 1)
        assert w.sensor_c is not None and w.contact_mean_c is not None
        assert w.contact_max_c is not None and w.flux_w_m2 is not None
        window_of.append(np.full(k.size, i, dtype=np.uint32))
        heating.append(k <= w.release)
        columns["time_utc"].append(_times(series, k))
        columns["measured_sensor_c"].append(series.measured_c[k])
        columns["predicted_sensor_c"].append(w.sensor_c)
        columns["predicted_contact_mean_c"].append(w.contact_mean_c)
        columns["predicted_contact_max_c"].append(w.contact_max_c)
        columns["speed_kmh"].append(speed[k])
        columns["brake_pressure_bar"].append(series.pressure_bar[k])
        columns["ambient_c"].append(series.ambient_c[k])
        columns["flux_w_m2"].append(w.flux_w_m2)
    # the strings made by polars from one value per window, not one Python object per row
    event_ids = pl.Series("event_id", [w.event_id for _, w, _ in windows], dtype=pl.String)
    strings = {
        "event_id": event_ids.gather(np.concatenate(window_of)),
        "phase": pl.Series("phase", ["cooling", "heating"], dtype=pl.String).gather(
            np.concatenate(heating).astype(np.uint32)
        ),
    }
    constant = {"wagon_id": wagon_id, "model_revision": rev}
    frame = pl.DataFrame(
        [
            *strings.values(),
            *(
                pl.Series(name, np.concatenate(parts), dtype=PREDICTION_SCHEMA[name])
                for name, parts in columns.items()
                if parts
            ),
        ]
    )
    return frame.with_columns(
        *(pl.lit(value, dtype=pl.String).alias(name) for name, value in constant.items()),
        pl.col("measured_sensor_c").fill_nan(None),
    ).select(list(PREDICTION_SCHEMA))


TIMELINE_SCHEMA = pl.Schema(
    {
        "wagon_id": pl.String(),
        "model_revision": pl.String(),
        "time_utc": pl.Datetime("us"),
        "predicted_sensor_c": pl.Float64(),
        "predicted_contact_mean_c": pl.Float64(),
        "predicted_contact_max_c": pl.Float64(),
    }
)


def timeline_frame(
    wagon_id: str, rev: str, spans: list[tuple[WagonSeries, SpanResult]]
) -> pl.DataFrame:
    """The timeline at every logged second of the spans."""
    parts = []
    for series, result in spans:
        k = np.flatnonzero(series.present & np.isfinite(result.sensor_c))
        parts.append(
            pl.DataFrame(
                {
                    "wagon_id": wagon_id,
                    "model_revision": rev,
                    "time_utc": _times(series, k),
                    "predicted_sensor_c": result.sensor_c[k],
                    "predicted_contact_mean_c": result.contact_mean_c[k],
                    "predicted_contact_max_c": result.contact_max_c[k],
                },
                schema=TIMELINE_SCHEMA,
            )
        )
    return pl.concat(parts) if parts else pl.DataFrame(schema=TIMELINE_SCHEMA)


SEGMENT_SCHEMA = pl.Schema(
    {
        "wagon_id": pl.String(),
        "model_revision": pl.String(),
        "span_start_utc": pl.Datetime("us"),
        "span_end_utc": pl.Datetime("us"),
        "start_utc": pl.Datetime("us"),
        "stop_utc": pl.Datetime("us"),
        "kind": pl.String(),
        "event_id": pl.String(),
        "anchor": pl.String(),
        "shift_k": pl.Float64(),
        "reference_c": pl.Float64(),
    }
)


def segment_frame(
    wagon_id: str, rev: str, spans: list[tuple[WagonSeries, SpanResult]]
) -> pl.DataFrame:
    rows = [
        {
            "wagon_id": wagon_id,
            "model_revision": rev,
            "span_start_utc": series.t0,
            "span_end_utc": series.utc(series.n - 1),
            "start_utc": series.utc(s.start),
            "stop_utc": series.utc(s.stop),
            "kind": s.kind,
            "event_id": s.event_id,
            "anchor": s.anchor,
            "shift_k": s.shift_k,
            "reference_c": s.reference_c,
        }
        for series, result in spans
        for s in result.segments
    ]
    return pl.DataFrame(rows, schema=SEGMENT_SCHEMA)
