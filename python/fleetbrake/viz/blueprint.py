"""The layout of a recording (rerun blueprint) for an engineer reviewing an incident."""

from __future__ import annotations

import rerun.blueprint as rrb

from fleetbrake.viz.entities import (
    BLOCK,
    COLORMAP,
    PRESSURE,
    RESIDUAL,
    SPEED,
    TIMELINE,
    UNEXPLAINED_POWER,
)

__all__ = ["blueprint"]


def blueprint(*, block_range_c: tuple[float, float] | None = None) -> rrb.Blueprint:
    """The layout for an engineer reviewing an incident: the temperature (measured, the
    open-loop prediction, and the virtual sensor's contact estimate with its 95 % band), the
    unexplained heat power (with its band), speed, pressure and residual plots stacked on the
    left; for an event, the
    block's temperature field on the right (its name says the colour range); the event, flag
    and sensor-fault ranges, and the text log of flags, events and notes below."""
    plots = rrb.Vertical(
        rrb.TimeSeriesView(
            name="Block temperature °C: measured vs predicted, contact estimate (95 % band)",
            origin="/wagon/temperature",
            plot_legend=rrb.PlotLegend(visible=True),
        ),
        rrb.TimeSeriesView(
            name="Unexplained heat power W (estimate, 95 % band)",
            origin=f"/{UNEXPLAINED_POWER}",
        ),
        rrb.TimeSeriesView(name="Speed km/h", origin="/", contents=f"/{SPEED}"),
        rrb.TimeSeriesView(name="Brake pressure bar", origin="/", contents=f"/{PRESSURE}"),
        rrb.TimeSeriesView(
            name="Residual K (measured - predicted sensor)", origin="/", contents=f"/{RESIDUAL}"
        ),
        row_shares=[3.0, 1.6, 1.2, 1.2, 1.6],
    )
    top: rrb.Container | rrb.View = plots
    if block_range_c is not None:
        low, high = block_range_c
        top = rrb.Horizontal(
            plots,
            rrb.Spatial3DView(
                name=f"Block temperature field ({COLORMAP}: {low:.0f} to {high:.0f} °C)",
                origin=f"/{BLOCK}",
            ),
            column_shares=[3.0, 2.0],
        )
    return rrb.Blueprint(
        rrb.Vertical(
            top,
            rrb.StateTimelineView(name="Events, flags, faulty readings", origin="/state"),
            rrb.TextLogView(name="Flags, events, notes", origin="/log"),
            row_shares=[6.0, 1.2, 2.0],
        ),
        rrb.TimePanel(timeline=TIMELINE),
        auto_views=False,
    )
