"""The close-loop report for people: Markdown with plots (residual before and after, per
wagon, per phase), written beside the JSON report. Its first line is the verdict
(:func:`verdict`): ``found: ...``, ``partly explained: ...`` or ``nothing added ...``; then the
sensor noise, whether the new revision is adequate and what is left unexplained, and each
fitted parameter with its 95 % interval (``parameter_intervals``).

The report is read from the warehouse (:func:`read_markdown_report`: its residuals) and
written apart (:meth:`MarkdownReport.write`), so that ``close-loop`` writes it, its plots
drawn on one of the engine's workers, while the warehouse closes (DuckDB's checkpoint)."""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import polars as pl

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


def _judged(report: Mapping[str, Any]) -> str:
    """``, 0.105 K without 2 outlier events`` when the verdict was judged on a fit RMSE other
    than the one shown (outlier events left out), else nothing."""
    judged = (report.get("adequacy") or {}).get("rmse_judged_k")
    after = (report.get("fit") or {}).get("rmse_after_k")
    count = (report.get("outliers") or {}).get("events") or 0
    if judged is None or after is None or not count or f"{judged:.3g}" == f"{after:.3g}":
        return ""
    return f", {_k(judged)} K without {count} outlier event{'s' if count > 1 else ''}"


def verdict(report: Mapping[str, Any]) -> str:
    """The report in one line: ``found: X ...`` (an effect added and the model adequate),
    ``partly explained: X explains 76 % of the residual; 1.2 K remains, correlated with
    speed ...`` (added, not adequate), or ``nothing added ...``. Reports without the v2
    adequacy fields read as adequate when an effect was added."""
    fit = report.get("fit", {})
    before, after = fit.get("rmse_before_k"), fit.get("rmse_after_k")
    noise = report.get("noise_k")
    noise_part = f", sensor noise {_k(noise)} K" if noise is not None else ""
    unexplained = report.get("unexplained")
    adequate = report.get("adequate")
    if report.get("new_revision"):
        effect = report.get("effect")
        if adequate is False:
            if unexplained:
                return str(unexplained)
            share = ""
            if before and after is not None:
                share = (
                    f" explains {100 * max(1 - (after / before) ** 2, 0.0):.0f} % of the residual;"
                )
            return f"partly explained: {effect}{share} {_k(after)} K remains{noise_part}"
        hold = report.get("holdout", {})
        held = ""
        if hold.get("rmse_before_k") is not None:
            held = f"; holdout {_k(hold['rmse_before_k'])} -> {_k(hold.get('rmse_after_k'))} K"
        return (
            f"found: {effect} (fit RMSE {_k(before)} -> {_k(after)} K{_judged(report)}"
            f"{noise_part}{held})"
        )
    line = (
        "nothing added: no candidate effect explains a significant part of the residual "
        f"(fit RMSE {_k(before)} K{noise_part})"
    )
    if adequate is False and unexplained:
        line += f"; {unexplained}"
    elif adequate is True:
        line += "; the baseline revision is adequate"
    return line


def render_markdown(report: Mapping[str, Any], plots: ResidualPlots | None = None) -> str:
    """The Markdown report of a JSON report dict (keys as in ``interface.md``), its first line
    the :func:`verdict`. With ``plots``, it shows the residual plots (drawn apart:
    :func:`draw_residual_plots`)."""
    lines = [
        verdict(report),
        "",
        "# Closed loop",
        "",
        f"Baseline revision `{report['baseline_revision']}`; "
        + (
            f"new revision `{report['new_revision']}` adds **{report['effect']}** with "
            f"`{report['parameters']}`."
            if report.get("new_revision")
            else "no effect was added."
        ),
        "",
        f"Evidence: {report['evidence']}.",
        "",
    ]
    if "adequate" in report or "noise_k" in report:
        adequate = report.get("adequate")
        lines += [
            "| adequacy | |",
            "|---|---|",
            f"| sensor noise (K, from the residual) | {_k(report.get('noise_k'))} |",
            f"| adequate | {'-' if adequate is None else ('yes' if adequate else 'no')} |",
        ]
        judged = report.get("adequacy") or {}
        if judged.get("judged_on"):
            lines.append(
                f"| judged on | fit RMSE {_k(judged.get('rmse_judged_k'))} K "
                f"({judged['judged_on']}), ratio {_k(judged.get('ratio'))} "
                f"(adequate at most {_k(judged.get('max_ratio'))}) |"
            )
        if report.get("unexplained"):
            lines.append(f"| unexplained | {report['unexplained']} |")
        lines.append("")
    intervals = report.get("parameter_intervals") or {}
    if intervals:
        values = report.get("parameters") or {}
        methods = report.get("interval_methods") or {}
        widest = methods.get("widest") or {}
        numerical = (methods.get("numerical") or {}).get("half_width") or {}
        inputs = (methods.get("input") or {}).get("half_width") or {}
        lines += [
            "| parameter | value | 95 % low | 95 % high | statistical: widest of | "
            "numerical (GCI) +- | input (speed) +- |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, (lo, hi) in intervals.items():
            lines.append(
                f"| {name} | {_k(values.get(name))} | {_k(lo)} | {_k(hi)} | "
                f"{widest.get(name, '-')} | {_k(numerical.get(name))} | {_k(inputs.get(name))} |"
            )
        lines.append("")
    lines += [
        "| events | count | RMSE before (K) | RMSE after (K) |",
        "|---|---|---|---|",
    ]

    def cell(value: float | None) -> str:
        return "-" if value is None else f"{value:.3f}"

    for key in ("fit", "holdout"):
        part = report[key]
        lines.append(
            f"| {key} | {part['events']} | {cell(part.get('rmse_before_k'))} | "
            f"{cell(part.get('rmse_after_k'))} |"
        )
    for key in ("fit", "holdout"):
        part = report[key]
        if "events_all" in part:
            lines.append(
                f"| {key}, flagged included | {part['events_all']} | "
                f"{cell(part.get('rmse_before_all_k'))} | {cell(part.get('rmse_after_all_k'))} |"
            )
    if "exclusion" in report:
        lines += ["", f"Events: {report['exclusion']}."]
    lines += [
        "",
        "## Candidates",
        "",
        "| candidate | score | RMSE fit (K) | RMSE holdout (K) | held-out gain | refused |",
        "|---|---|---|---|---|---|",
    ]
    for c in report["candidates"]:
        held = c.get("held_out") or {}
        gain = f"{100 * held['gain']:+.1f} %" if "gain" in held else "-"
        lines.append(
            f"| {c.get('label', c['effect'])} | {c['score']:.1f} | {cell(c.get('rmse_fit_k'))} | "
            f"{cell(c.get('rmse_holdout_k'))} | {gain} | {c.get('refused') or '-'} |"
        )
    if report.get("selection"):
        lines += ["", report["selection"]]
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


def read_markdown_report(wh: Warehouse, report: Mapping[str, Any], path: Path) -> MarkdownReport:
    """The Markdown report of ``report`` at ``path`` (its plots beside it, named after it),
    its residuals (the baseline and the new revision's) read from ``wh`` now."""
    revisions = [report["baseline_revision"]]
    if report.get("new_revision"):
        revisions.append(report["new_revision"])
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
