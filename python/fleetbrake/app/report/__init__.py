"""The fleet report: Markdown with PNG plots, read from a warehouse's views only.

::

    from fleetbrake.app.report import write_report

    result = write_report("demo-out/fleet.duckdb", "demo-out", close_loop=report_dict)
    result.path      # demo-out/report.md
    result.pictures  # the PNGs beside it, each referenced from the Markdown

Everything comes from the public views (``v_files``, ``v_events``, ``v_predictions``,
``v_flags``, ``v_model_revisions``, ``v_contact_estimates``; ``shared/spec/interface.md``),
opened read-only, so the report shows what an analyst querying the database would see.
Optional extras: the close-loop report (the dict ``run_close_loop`` returns) and, for a
synthetic fleet, its truth (the effect and anomalies the generator put in, to compare with
what was found).

One module per part: :mod:`~fleetbrake.app.report.data` (what is read, once),
:mod:`~fleetbrake.app.report.plots` (one function per picture),
:mod:`~fleetbrake.app.report.markdown` (a section's lines and pictures, tables), the sections
:mod:`~fleetbrake.app.report.overview`, :mod:`~fleetbrake.app.report.closeloop`,
:mod:`~fleetbrake.app.report.predictions`, :mod:`~fleetbrake.app.report.flags`,
:mod:`~fleetbrake.app.report.estimates` and :mod:`~fleetbrake.app.report.events`, and
:mod:`~fleetbrake.app.report.document` (:func:`write_report`: the sections in order).

The tables give the peak contact temperature with its bounds: the virtual sensor's
(``v_contact_estimates``) beside the open-loop prediction's, per wagon and per braking.
"""

from fleetbrake.app.report.closeloop import effect_verdict
from fleetbrake.app.report.data import (
    ReportData,
    ReportInputError,
    ReportLockedError,
    flag_windows,
    load_report_data,
)
from fleetbrake.app.report.document import ReportResult, write_report
from fleetbrake.app.report.plots import (
    FLAG_COLORS,
    plot_close_loop_error,
    plot_contact_estimates,
    plot_contact_temperatures,
    plot_event_predictions,
    plot_flag_timeline,
)

__all__ = [
    "FLAG_COLORS",
    "ReportData",
    "ReportInputError",
    "ReportLockedError",
    "ReportResult",
    "effect_verdict",
    "flag_windows",
    "load_report_data",
    "plot_close_loop_error",
    "plot_contact_estimates",
    "plot_contact_temperatures",
    "plot_event_predictions",
    "plot_flag_timeline",
    "write_report",
]
