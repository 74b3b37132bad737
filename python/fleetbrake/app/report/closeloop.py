"""The report's closed-loop section: the effect added (or none), against the generator's
truth when there is one, and the RMSE before and after on the fit and holdout events."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fleetbrake.app.report.markdown import Section, fmt, table
from fleetbrake.app.report.plots import plot_close_loop_error

if TYPE_CHECKING:
    from fleetbrake.synth.generator import FleetTruth

__all__ = ["closeloop_section", "effect_verdict"]


def closeloop_section(
    close_loop: Mapping[str, Any], truth: FleetTruth | None, picture: Path
) -> Section:
    """The closed loop's outcome (the close-loop report's dict) and its error plot, written
    to ``picture``."""
    lines = ["## Closed loop", ""]
    if close_loop.get("new_revision"):
        params = ", ".join(f"{k} = {v:.3g}" for k, v in close_loop["parameters"].items())
        lines.append(
            f"The model lacked **{close_loop['effect']}** ({params}); it was added as "
            f"revision `{close_loop['new_revision']}` on top of "
            f"`{close_loop['baseline_revision']}`."
        )
    else:
        lines.append("No significant effect is missing: nothing was added.")
    if truth is not None:
        lines += [
            "",
            f"Against the truth (the generator's `{truth.effects}`): "
            f"{effect_verdict(close_loop, truth.effects.names)}.",
        ]
    lines += ["", f"Evidence: {close_loop.get('evidence', '-')}.", ""]
    if truth is not None and truth.effects:
        lines += _parameters_table(close_loop, truth)
    rows = []
    for key in ("fit", "holdout"):
        part = close_loop.get(key, {})
        rows.append(
            (
                key,
                part.get("events", 0),
                fmt(part.get("rmse_before_k"), 3),
                fmt(part.get("rmse_after_k"), 3),
            )
        )
    lines += table(["events", "count", "RMSE before (K)", "RMSE after (K)"], rows)
    png = plot_close_loop_error(close_loop, picture)
    lines += [f"![closed-loop error]({png.name})", ""]
    return Section(lines, [png])


def effect_verdict(close_loop: Mapping[str, Any] | None, truth_effects: Sequence[str]) -> str:
    """One sentence: the effect the closed loop added against the one(s) the generator used."""
    found = (close_loop or {}).get("effect")
    found_names = set(found.split("+")) if found else set()
    truth_names = set(truth_effects)
    if not truth_names:
        return f"found {found or 'nothing'}; the data had no undeclared effect"
    said = " + ".join(sorted(truth_names))
    if found_names == truth_names:
        return f"**matched**: found {found}, the effect the generator used"
    if found_names & truth_names:
        return f"**partly matched**: found {found}, the generator used {said}"
    return f"**not matched**: found {found or 'nothing'}, the generator used {said}"


def _parameters_table(close_loop: Mapping[str, Any], truth: FleetTruth) -> list[str]:
    """Each true effect's parameters against the fitted ones (when the effect was found)."""
    found = {e["name"]: e.get("parameters", {}) for e in close_loop.get("effects", [])}
    rows = []
    for effect in truth.effects:
        fitted = found.get(effect.name, {})
        for key, value in effect.parameters.items():
            got = fitted.get(key)
            rows.append(
                (
                    effect.name,
                    key,
                    f"{value:.4g}",
                    "-" if got is None else f"{got:.4g}",
                    "-" if got is None or not value else f"{100 * (got - value) / value:+.1f} %",
                )
            )
    return table(["effect", "parameter", "truth", "fitted", "difference"], rows)
