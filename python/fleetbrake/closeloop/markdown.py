"""The close-loop report for people: Markdown with plots (residual before and after, per
wagon, per phase), written beside the JSON report. Its first line is the verdict
(:func:`verdict_line`): ``found: ...``, ``partly explained: ...`` or ``nothing added ...``; then the
sensor noise, whether the new revision is adequate and what is left unexplained, and each
fitted parameter with its 95 % interval (``parameter_intervals``).

The report is read from the warehouse (:func:`read_markdown_report`: its residuals) and
written apart (:meth:`MarkdownReport.write`), so that ``close-loop`` writes it, its plots
drawn on one of the engine's workers, while the warehouse closes (DuckDB's checkpoint)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import polars as pl

from fleetbrake.closeloop.candidates import HeldOut
from fleetbrake.closeloop.report import CloseLoopReport
from fleetbrake.engine import Engine
from fleetbrake.warehouse.connection import Warehouse, sql


def _residuals(wh: Warehouse, revisions: list[str]) -> pl.DataFrame:
    frames = []
    for rev in revisions:
        frames.append(wh.con.sql(sql("q_closeloop_residuals"), params={"revision": rev}).pl())
    return pl.concat(frames) if frames else pl.DataFrame()


def plot_residual_by_wagon(frame: pl.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = (
        frame.group_by("wagon_id", "model_revision")
        .agg((pl.col("residual_k") ** 2).mean().sqrt().alias("rmse_k"))
        .sort("wagon_id", "model_revision")
    )
    fig, ax = plt.subplots(figsize=(8, 3.5))
    revisions = summary["model_revision"].unique(maintain_order=True).to_list()
    wagons = summary["wagon_id"].unique(maintain_order=True).to_list()
    width = 0.8 / max(len(revisions), 1)
    for i, rev in enumerate(revisions):
        part = summary.filter(pl.col("model_revision") == rev)
        lookup = dict(zip(part["wagon_id"], part["rmse_k"], strict=True))
        ax.bar(
            [w + i * width for w in range(len(wagons))],
            [lookup.get(w, 0.0) for w in wagons],
            width,
            label=rev,
        )
    ax.set_xticks([w + 0.4 - width / 2 for w in range(len(wagons))], wagons, rotation=30)
    ax.set_ylabel("RMSE measured - predicted (K)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_residual_by_phase(frame: pl.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5), sharey=True)
    for ax, phase in zip(axes, ("heating", "cooling"), strict=True):
        for rev in frame["model_revision"].unique(maintain_order=True).to_list():
            values = frame.filter((pl.col("phase") == phase) & (pl.col("model_revision") == rev))[
                "residual_k"
            ].to_numpy()
            if values.size:
                ax.hist(values, bins=60, alpha=0.6, label=rev, density=True)
        ax.set_title(phase)
        ax.set_xlabel("measured - predicted (K)")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _k(value: Any) -> str:
    return "-" if value is None else f"{float(value):.3g}"


def _judged(report: CloseLoopReport) -> str:
    """``, 0.105 K without 2 outlier events`` when the verdict was judged on a fit RMSE other
    than the one shown (outlier events left out), else nothing."""
    judged = report.adequacy.rmse_judged_k
    after = report.fit.rmse_after_k
    count = report.outliers.events or 0
    if judged is None or after is None or not count or f"{judged:.3g}" == f"{after:.3g}":
        return ""
    return f", {_k(judged)} K without {count} outlier event{'s' if count > 1 else ''}"


def verdict_line(report: CloseLoopReport) -> str:
    """The report in one line: ``found: X ...`` (an effect added and the model adequate),
    ``partly explained: X explains 76 % of the residual; 1.2 K remains, correlated with
    speed ...`` (added, not adequate), or ``nothing added ...``."""
    before, after = report.fit.rmse_before_k, report.fit.rmse_after_k
    noise_part = f", sensor noise {_k(report.noise_k)} K"
    unexplained = report.unexplained
    if report.new_revision:
        effect = report.effect
        if not report.adequate:
            if unexplained:
                return str(unexplained)
            share = ""
            if before and after is not None:
                share = (
                    f" explains {100 * max(1 - (after / before) ** 2, 0.0):.0f} % of the residual;"
                )
            return f"partly explained: {effect}{share} {_k(after)} K remains{noise_part}"
        hold = report.holdout
        held = ""
        if hold.rmse_before_k is not None:
            held = f"; holdout {_k(hold.rmse_before_k)} -> {_k(hold.rmse_after_k)} K"
        return (
            f"found: {effect} (fit RMSE {_k(before)} -> {_k(after)} K{_judged(report)}"
            f"{noise_part}{held})"
        )
    line = (
        "nothing added: no candidate effect explains a significant part of the residual "
        f"(fit RMSE {_k(before)} K{noise_part})"
    )
    if not report.adequate and unexplained:
        line += f"; {unexplained}"
    elif report.adequate:
        line += "; the baseline revision is adequate"
    return line


def _intervals_table(report: CloseLoopReport) -> list[str]:
    """The fitted parameters with their 95 % intervals and what they are made of."""
    if not report.parameter_intervals:
        return []
    values = report.parameters
    methods = report.interval_methods
    widest = methods.widest if methods is not None else {}
    numerical = methods.numerical_half_width if methods is not None else {}
    inputs = methods.input_half_width if methods is not None else {}
    lines = [
        "| parameter | value | 95 % low | 95 % high | statistical: widest of | "
        "numerical (GCI) +- | input (speed) +- |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, (lo, hi) in report.parameter_intervals.items():
        lines.append(
            f"| {name} | {_k(values.get(name))} | {_k(lo)} | {_k(hi)} | "
            f"{widest.get(name, '-')} | {_k(numerical.get(name))} | {_k(inputs.get(name))} |"
        )
    lines.append("")
    return lines


def _cell(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def render_markdown(report: CloseLoopReport, plots: ResidualPlots | None = None) -> str:
    """The Markdown report of ``report``, its first line the :func:`verdict_line`. With
    ``plots``, it shows the residual plots (drawn apart: :func:`draw_residual_plots`)."""
    lines = [
        verdict_line(report),
        "",
        "# Closed loop",
        "",
        f"Baseline revision `{report.baseline_revision}`; "
        + (
            f"new revision `{report.new_revision}` adds **{report.effect}** with "
            f"`{report.parameters}`."
            if report.new_revision
            else "no effect was added."
        ),
        "",
        f"Evidence: {report.evidence}.",
        "",
        "| adequacy | |",
        "|---|---|",
        f"| sensor noise (K, from the residual) | {_k(report.noise_k)} |",
        f"| adequate | {'yes' if report.adequate else 'no'} |",
    ]
    judged = report.adequacy
    if judged.judged_on:
        lines.append(
            f"| judged on | fit RMSE {_k(judged.rmse_judged_k)} K "
            f"({judged.judged_on}), ratio {_k(judged.ratio)} "
            f"(adequate at most {_k(judged.max_ratio)}) |"
        )
    if report.unexplained:
        lines.append(f"| unexplained | {report.unexplained} |")
    lines.append("")
    lines += _intervals_table(report)
    lines += [
        "| events | count | RMSE before (K) | RMSE after (K) |",
        "|---|---|---|---|",
    ]
    sets = (("fit", report.fit), ("holdout", report.holdout))
    for key, part in sets:
        lines.append(
            f"| {key} | {part.events} | {_cell(part.rmse_before_k)} | {_cell(part.rmse_after_k)} |"
        )
    for key, part in sets:
        lines.append(
            f"| {key}, flagged included | {part.events_all} | "
            f"{_cell(part.rmse_before_all_k)} | {_cell(part.rmse_after_all_k)} |"
        )
    lines += ["", f"Events: {report.exclusion}."]
    lines += [
        "",
        "## Candidates",
        "",
        "| candidate | score | RMSE fit (K) | RMSE holdout (K) | held-out gain | refused |",
        "|---|---|---|---|---|---|",
    ]
    for c in report.candidates:
        gain = f"{100 * c.held_out.gain:+.1f} %" if isinstance(c.held_out, HeldOut) else "-"
        lines.append(
            f"| {c.label} | {c.score:.1f} | {_cell(c.rmse_fit_k)} | "
            f"{_cell(c.rmse_holdout_k)} | {gain} | {c.refused or '-'} |"
        )
    if report.selection:
        lines += ["", report.selection]
    lines.append("")
    if plots is not None:
        lines += [
            "## Residual per wagon",
            "",
            f"![residual per wagon]({plots.by_wagon.name})",
            "",
            "## Residual per phase",
            "",
            f"![residual per phase]({plots.by_phase.name})",
            "",
        ]
    return "\n".join(lines)


@dataclass(frozen=True)
class ResidualPlots:
    """The residual plots of a report: the residuals they show (``q_closeloop_residuals``'s
    columns, as an Arrow table: what an engine ships to a worker) and their files."""

    residuals: Any  # pyarrow.Table (pyarrow ships no type information)
    by_wagon: Path
    by_phase: Path


def draw_residual_plots(plots: ResidualPlots) -> None:
    """Draw the residual plots into their files (in a worker: matplotlib is imported there)."""
    frame = pl.DataFrame(plots.residuals)
    plot_residual_by_wagon(frame, plots.by_wagon)
    plot_residual_by_phase(frame, plots.by_phase)


@dataclass(frozen=True)
class MarkdownReport:
    """A Markdown report read from the warehouse and not yet written: its text and, when
    there are residuals, its plots."""

    path: Path
    text: str
    plots: ResidualPlots | None

    def write(self, engine: Engine) -> None:
        """Draw the plots (on one of ``engine``'s workers: in this process for the inline
        engine), then write the text."""
        if self.plots is not None:
            deque(engine.map(draw_residual_plots, [self.plots], name=_plots_name), maxlen=0)
        self.path.write_text(self.text, encoding="utf-8")


def _plots_name(plots: ResidualPlots) -> str:
    return f"the residual plots {plots.by_wagon.name}, {plots.by_phase.name}"


def read_markdown_report(wh: Warehouse, report: CloseLoopReport, path: Path) -> MarkdownReport:
    """The Markdown report of ``report`` at ``path`` (its plots beside it, named after it),
    its residuals (the baseline and the new revision's) read from ``wh`` now."""
    revisions = [report.baseline_revision]
    if report.new_revision:
        revisions.append(report.new_revision)
    frame = _residuals(wh, revisions)
    plots = None
    if frame.height:
        stem = path.with_suffix("")
        plots = ResidualPlots(
            frame.to_arrow(),
            stem.parent / f"{stem.name}-by-wagon.png",
            stem.parent / f"{stem.name}-by-phase.png",
        )
    return MarkdownReport(path, render_markdown(report, plots), plots)
