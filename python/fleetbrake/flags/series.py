"""What the flags read of one wagon: its samples on the 1 Hz grid of each span, and the
timeline the simulation stage stored for the revision on the same grid (the flags never
simulate).

::

    from fleetbrake.flags.series import load_spans

    for series, timeline in load_spans(wh, "SGG-0001", ambient_default_c=10.0, stored=stored):
        timeline.predicted_c, timeline.bounds, timeline.kinds   # None: readings only
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from fleetbrake.simulation.chains import ChainParams
from fleetbrake.simulation.series import FloatArray, WagonSeries, seconds_since, strictly_increasing
from fleetbrake.simulation.store import StoredTimeline, TimelineSpan, wagon_events, wagon_samples
from fleetbrake.warehouse.connection import Warehouse

__all__ = ["SpanTimeline", "load_spans", "span_timeline", "spans_of"]


@dataclass(frozen=True)
class SpanTimeline:
    """The stored timeline of one span on its series' grid."""

    predicted_c: FloatArray
    """The predicted sensor temperature (NaN at seconds without a row)."""
    bounds: list[int]
    """Segment starts, then the end of the series."""
    kinds: list[str]
    """``braking``, ``quiet`` or ``gap``, per segment."""
    gaps: list[tuple[int, int]]
    """The last row before and the first row after each ``gap`` segment."""


def span_timeline(series: WagonSeries, span: TimelineSpan) -> SpanTimeline:
    """``span`` (stored for the same samples) on ``series``' grid."""
    predicted = np.full(series.n, np.nan)
    if span.values.height:
        k = seconds_since(span.values["time_utc"], series.t0)
        inside = (k >= 0) & (k < series.n)
        predicted[k[inside]] = span.values["predicted_sensor_c"].to_numpy()[inside]
    starts = [series.index(t) for t in span.segments["start_utc"]]
    stops = [series.index(t) for t in span.segments["stop_utc"]]
    kinds = [str(kind) for kind in span.segments["kind"]]
    gaps = [(a - 1, b) for a, b, kind in zip(starts, stops, kinds, strict=True) if kind == "gap"]
    return SpanTimeline(predicted, [*starts, series.n], kinds, gaps)


def load_spans(
    wh: Warehouse,
    wagon_id: str,
    *,
    ambient_default_c: float,
    stored: StoredTimeline | None,
) -> list[tuple[WagonSeries, SpanTimeline | None]]:
    """The wagon's spans of samples, each with its stored timeline: the spans the simulation
    cut when ``stored`` is given (it must be of the wagon's data as they are), else those of
    the default :class:`ChainParams` with no timeline (the readings alone are judged)."""
    return spans_of(
        wagon_id,
        wagon_samples(wh, wagon_id),
        wagon_events(wh, wagon_id),
        ambient_default_c=ambient_default_c,
        stored=stored,
    )


def spans_of(
    wagon_id: str,
    samples: pl.DataFrame,
    events: pl.DataFrame,
    *,
    ambient_default_c: float,
    stored: StoredTimeline | None,
) -> list[tuple[WagonSeries, SpanTimeline | None]]:
    """:func:`load_spans` from the wagon's ``samples`` and ``events`` as read by
    ``q_simulation_wagon_samples.sql`` and ``q_simulation_wagon_events.sql`` (no database)."""
    if samples.height == 0:
        return []
    if stored is None or not stored.spans:
        spans = WagonSeries.spans_from_frame(
            wagon_id,
            samples,
            ambient_default_c=ambient_default_c,
            bridge_max_s=ChainParams().bridge_max_s,
            events=events,
        )
        return [(series, None) for series in spans]
    out: list[tuple[WagonSeries, SpanTimeline | None]] = []
    times = samples["time_utc"]
    ordered = strictly_increasing(times)  # a span's rows: a slice, no polars query
    at = times.to_numpy() if ordered else None
    for span in stored.spans:
        if at is not None:
            lo = int(np.searchsorted(at, np.datetime64(span.start_utc, "us"), "left"))
            hi = int(np.searchsorted(at, np.datetime64(span.end_utc, "us"), "right"))
            part = samples.slice(lo, hi - lo)
        else:
            part = samples.filter(pl.col("time_utc").is_between(span.start_utc, span.end_utc))
        if part.height == 0:
            continue
        own = events.filter(pl.col("start_utc").is_between(span.start_utc, span.end_utc))
        series = WagonSeries.from_frame(
            wagon_id, part, ambient_default_c=ambient_default_c, events=own, ordered=ordered
        )
        out.append((series, span_timeline(series, span)))
    return out
