"""The close-loop report for people: Markdown with plots (residual before and after, per
wagon, per phase), written beside the JSON report."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import polars as pl

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


def write_markdown_report(wh: Warehouse, report: dict[str, Any], path: Path) -> None:
    revisions = [report["baseline_revision"]]
    if report.get("new_revision"):
        revisions.append(report["new_revision"])
    frame = _residuals(wh, revisions)
    stem = path.with_suffix("")
    lines = [
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
    lines += ["", "## Candidates", "", "| effect | score | RMSE fit (K) | RMSE holdout (K) |"]
    lines.append("|---|---|---|---|")
    for c in report["candidates"]:
        hold = c["rmse_holdout_k"]
        lines.append(
            f"| {c['effect']} | {c['score']:.1f} | {c['rmse_fit_k']:.3f} | "
            f"{'-' if hold is None else f'{hold:.3f}'} |"
        )
    lines += ["", report["selection"], ""]
    if frame.height:
        by_wagon = stem.parent / f"{stem.name}-by-wagon.png"
        by_phase = stem.parent / f"{stem.name}-by-phase.png"
        plot_residual_by_wagon(frame, by_wagon)
        plot_residual_by_phase(frame, by_phase)
        lines += [
            "## Residual per wagon",
            "",
            f"![residual per wagon]({by_wagon.name})",
            "",
            "## Residual per phase",
            "",
            f"![residual per phase]({by_phase.name})",
            "",
        ]
    path.write_text("\n".join(lines), encoding="utf-8")
