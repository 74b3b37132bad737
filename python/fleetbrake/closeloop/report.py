"""The close loop's last phase, report: what the phases found, as the typed report
(:class:`CloseLoopReport`, its values as reported: rounded where the JSON rounds them), built
once (:func:`build_report`), its verdict judged again on the figure it shows
(:func:`judged_on_report`), and serialised in one place (:meth:`CloseLoopReport.to_dict`: the
JSON of ``shared/spec/interface.md``, "close-loop report", and the fields beyond it). The
Markdown report (:mod:`fleetbrake.closeloop.markdown`) is rendered from the same object."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from fleetbrake.closeloop.candidates import (
    Candidate,
    Families,
    HeldOut,
    HeldOutFailed,
    report_parameters,
)
from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.evidence import (
    Evidence,
    ResidualSummary,
    event_sets,
    rmse_from_predictions,
)
from fleetbrake.closeloop.fit import Fitted, Outliers
from fleetbrake.closeloop.revision import NewRevision
from fleetbrake.closeloop.selection import Selection
from fleetbrake.closeloop.stats import (
    MAX_NOISE_RATIO,
    DriftReport,
    describe_drivers,
    intervals_for_json,
)
from fleetbrake.closeloop.terms import InputTerm, Numerical
from fleetbrake.closeloop.verdict import Verdict
from fleetbrake.model.effects import Effect
from fleetbrake.warehouse.connection import Warehouse

__all__ = [
    "AdequacyReport",
    "CandidateReport",
    "CloseLoopReport",
    "Cost",
    "EventSetFigures",
    "IntervalMethods",
    "OnBound",
    "UnknownHeat",
    "bounds_verdict",
    "build_report",
    "drift_verdict",
    "judged_on_report",
    "parameters_on_bound",
]

Intervals = dict[str, list[float | None]]
"""Intervals as the report gives them: name -> [low, high] (None: unbounded)."""


@dataclass(frozen=True)
class EventSetFigures:
    """The report's ``fit`` or ``holdout``: the events used and the RMSE (K) over every second
    of their windows with a valid measurement, before and after; ``*_all`` over every event
    of the set, flagged ones included (None: no events)."""

    events: int
    rmse_before_k: float | None
    rmse_after_k: float | None
    events_all: int
    rmse_before_all_k: float | None
    rmse_after_all_k: float | None


@dataclass(frozen=True)
class CandidateReport:
    """One candidate as the report lists it."""

    effect: str
    """The vocabulary names, ``+``-joined."""
    label: str
    """The added laws (``convection_speed[flat_plate]``)."""
    parameters: dict[str, dict[str, float]]
    rmse_fit_k: float
    rmse_holdout_k: float | None
    score: float
    """Criterion improvement over the baseline."""
    fitted_on: str
    held_out: HeldOut | HeldOutFailed | None
    refused: str | None


@dataclass(frozen=True)
class UnknownHeat:
    """Events left out for braking over a frozen GPS speed."""

    events: int
    event_ids: list[str]


@dataclass(frozen=True)
class AdequacyReport:
    """The figures behind ``adequate``: at the choice (``rmse_k`` .. ``correlations``) and, once
    judged on the report's own fit events (:func:`judged_on_report`), that figure too."""

    rmse_k: float
    ratio: float
    whiteness: float
    explained_fraction: float | None
    correlations: dict[str, float]
    rmse_choice_k: float | None = None
    rmse_judged_k: float | None = None
    rmse_fit_k: float | None = None
    max_ratio: float | None = None
    judged_on: str | None = None


@dataclass(frozen=True)
class IntervalMethods:
    """The three statistical intervals the reported ones are the widest of (``widest`` names
    which, per parameter), and the numerical and input terms added to them in quadrature."""

    blocks: int
    widest: dict[str, str]
    jacobian: Intervals
    sandwich: Intervals
    jackknife: Intervals
    statistical: Intervals
    numerical: Numerical | None = None
    inputs: InputTerm | None = None

    @property
    def numerical_half_width(self) -> dict[str, float]:
        """The numerical term's half-widths as reported (none: empty)."""
        return _g6(self.numerical.half_width) if self.numerical is not None else {}

    @property
    def input_half_width(self) -> dict[str, float]:
        """The input term's half-widths as reported (none: empty)."""
        return _g6(self.inputs.half_width) if self.inputs is not None else {}


@dataclass(frozen=True)
class Cost:
    """What a run took: candidates fitted, chain-kernel calls, model evaluations per phase and
    seconds per phase."""

    candidates_fitted: int
    kernel_calls: int
    evaluations: dict[str, int]
    seconds: dict[str, float]


@dataclass(frozen=True)
class OnBound:
    """A fitted parameter on a limit of its family (``LIMITS``): its value or its reported
    95 % interval reaches the limit."""

    parameter: str
    """Its key in the report's ``parameters``."""
    effect: str
    side: str
    """``lower`` or ``upper``."""
    limit: float
    value: float


@dataclass(frozen=True)
class CloseLoopReport:
    """The close-loop report (``shared/spec/interface.md``, "close-loop report"), its values as
    reported. ``effects`` and ``interval_methods`` only when an effect was added (and
    fitted), ``cost`` once the run is done."""

    baseline_revision: str
    new_revision: str | None
    effect: str | None
    parameters: dict[str, float]
    evidence: str
    fit: EventSetFigures
    holdout: EventSetFigures
    candidates: list[CandidateReport]
    noise_k: float
    flags_judged_with: str
    solver: str
    residual: ResidualSummary
    n_eff: float
    selection: str
    exclusion: str
    outliers: Outliers
    unknown_heat: UnknownHeat
    effects: list[Effect] | None
    interval_methods: IntervalMethods | None
    parameter_intervals: Intervals
    adequate: bool
    unexplained: str | None
    adequacy: AdequacyReport
    cost: Cost | None = None
    drift: DriftReport | None = None
    """The added effects' parameters refitted per day of the fit events, and each one's
    change per day with its 95 % interval (:func:`drift_verdict`)."""
    on_bound: list[OnBound] = dataclasses.field(default_factory=list)
    """The added effects' parameters whose fitted value or 95 % interval reaches a limit of
    the family (:func:`bounds_verdict`)."""

    def to_dict(self) -> dict[str, Any]:
        """The report as JSON values, keys in the contract's order (the one place the report
        is serialised)."""
        out: dict[str, Any] = {
            "baseline_revision": self.baseline_revision,
            "new_revision": self.new_revision,
            "effect": self.effect,
            "parameters": dict(self.parameters),
            "evidence": self.evidence,
            "fit": dataclasses.asdict(self.fit),
            "holdout": dataclasses.asdict(self.holdout),
            "candidates": [_candidate_json(c) for c in self.candidates],
            "noise_k": self.noise_k,
            "flags_judged_with": self.flags_judged_with,
            "solver": self.solver,
            "residual": _residual_json(self.residual),
            "n_eff": self.n_eff,
            "selection": self.selection,
            "exclusion": self.exclusion,
            "outliers": _outliers_json(self.outliers),
            "unknown_heat": {
                "events": self.unknown_heat.events,
                "event_ids": list(self.unknown_heat.event_ids),
            },
        }
        if self.effects is not None:
            out["effects"] = [e.to_dict() for e in self.effects]
        if self.interval_methods is not None:
            out["interval_methods"] = _methods_json(self.interval_methods)
        out["parameter_intervals"] = dict(self.parameter_intervals)
        out["adequate"] = self.adequate
        out["unexplained"] = self.unexplained
        out["adequacy"] = _adequacy_json(self.adequacy)
        out["on_bound"] = [dataclasses.asdict(b) for b in self.on_bound]
        out["drift"] = None if self.drift is None else _drift_json(self.drift)
        if self.cost is not None:
            out["cost"] = dataclasses.asdict(self.cost)
        return out


# ---------------------------------------------------------------------------- serialising
def _g6(values: Mapping[str, float]) -> dict[str, float]:
    return {k: float(f"{v:.6g}") for k, v in values.items()}


def _candidate_json(c: CandidateReport) -> dict[str, Any]:
    out = dataclasses.asdict(c)
    held = c.held_out
    out["held_out"] = None if held is None else dataclasses.asdict(held)
    return out


def _residual_json(summary: ResidualSummary) -> dict[str, Any]:
    if summary.correlations is None:
        return {"seconds": summary.seconds}
    return dataclasses.asdict(summary)


def _outliers_json(outliers: Outliers) -> dict[str, Any]:
    if outliers.judged_with is None:
        return {"events": outliers.events}
    return {
        "events": outliers.events,
        "threshold_k": outliers.threshold_k,
        "median_event_rms_k": outliers.median_event_rms_k,
        "judged_with": outliers.judged_with,
        "event_ids": list(outliers.event_ids),
        "worst": [{"event_id": e, "rms_k": rms} for e, rms in outliers.worst],
    }


def _numerical_json(n: Numerical) -> dict[str, Any]:
    def g(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: g(v) for k, v in value.items()}
        return float(f"{value:.6g}") if isinstance(value, float) else value

    return {
        "method": (
            "grid convergence index (Roache; ASME V&V 20's u_num): the chosen effects "
            "refitted on the same fit events through the reduced model on coarser meshes; "
            "per mesh gci = safety_factor |coarse - fine| / (ratio^order - 1), the largest "
            "added in quadrature to the statistical half-width"
        ),
        "refinement": n.refinement,
        "order": n.order,
        "safety_factor": n.safety_factor,
        "grids": [g(grid) for grid in n.grids],
        "half_width": g(n.half_width),
    }


def _input_json(term: InputTerm) -> dict[str, Any]:
    return {
        "method": (
            "sensitivity to the input's systematic error (ASME V&V 20's u_input): the "
            "chosen parameters' residual on the same fit events with the speed read as "
            "sqrt(max(v^2 - noise^2, 0)) (a GPS speed is a magnitude: at standstill it "
            "reads its noise), the noise from the logged speed's second differences where "
            "the wagon moves, and the parameters' shift where the changed residual meets "
            "the fit's normal equations, by quasi-Newton steps from the fit's Jacobian "
            "(Broyden-updated); the shift added in quadrature to the statistical half-width"
        ),
        "speed_noise_kmh": float(f"{term.speed_noise_kmh:.6g}"),
        "debiased": _g6(term.debiased),
        "shift": _g6(term.shift),
        "evaluations": term.evaluations,
        "half_width": _g6(term.half_width),
    }


def _adequacy_json(a: AdequacyReport) -> dict[str, Any]:
    out: dict[str, Any] = {
        "rmse_k": a.rmse_k,
        "ratio": a.ratio,
        "whiteness": a.whiteness,
        "explained_fraction": a.explained_fraction,
        "correlations": a.correlations,
    }
    if a.judged_on is not None:  # judged again on the report's own fit events
        out.update(
            {
                "rmse_choice_k": a.rmse_choice_k,
                "rmse_judged_k": a.rmse_judged_k,
                "rmse_fit_k": a.rmse_fit_k,
                "max_ratio": a.max_ratio,
                "judged_on": a.judged_on,
            }
        )
    return out


def _methods_json(m: IntervalMethods) -> dict[str, Any]:
    out: dict[str, Any] = {
        "blocks": m.blocks,
        "widest": m.widest,
        "jacobian": m.jacobian,
        "sandwich": m.sandwich,
        "jackknife": m.jackknife,
        "statistical": m.statistical,
    }
    if m.numerical is not None:
        out["numerical"] = _numerical_json(m.numerical)
    if m.inputs is not None:
        out["input"] = _input_json(m.inputs)
    return out


# ---------------------------------------------------------------------------- building
def _selection_text(evidence: Evidence, config: CloseLoopConfig) -> str:
    n_eff = evidence.n_eff["fit"]
    return (
        f"Bayesian information criterion on the fit events on an effective sample size of "
        f"{n_eff:.0f} independent residuals (of {int(evidence.ok.sum())} seconds: the "
        f"baseline residual's autocorrelation within wagon-days); score = improvement over "
        f"the baseline. Every addition (the first effect over the baseline, a pair over "
        f"its single, empirical over what it corrects) must score {config.bic_margin:g} "
        f"above what it adds to, cut the fit RMSE by "
        f"{100 * config.min_improvement:.0f} %, cut the held-out RMSE of whole wagon-days "
        f"({config.folds} folds, each fit moved one Gauss-Newton step off its fold) by the "
        f"practical margin of {100 * config.held_out_margin:.0f} % and on most folds, and "
        f"have each added law's parameters distinguishable from their nulls (95 % "
        f"intervals, the widest of Jacobian on n_eff, cluster-robust and delete-one-"
        f"wagon-day jackknife); a candidate's 'refused' says why it did not enter. Pairs "
        f"are tried when the single leaves the fit RMSE above "
        f"{config.pair_above_noise:g}x the noise. The holdout is never used to choose."
    )


def _exclusion_text(config: CloseLoopConfig) -> str:
    return (
        "events whose window overlaps a dragging_brake, weak_brake or "
        "sensor_fault flag of their wagon or the window of one of its events cut by a data gap "
        f"(incomplete), or starts less than {config.settle_after_flag_s:.0f} s after one ends, "
        "are left out of fit and holdout, and so are brakings over a frozen GPS speed (their "
        "heat input is unknown: unknown_heat); events_all and rmse_*_all_k count every event "
        "of the "
        "set; fit events whose residual RMS under the best screened effect is far above the "
        "bulk (outliers) are left out of the parameter fit and the adequacy verdict"
    )


def _candidate_report(c: Candidate, current: Candidate, families: Families) -> CandidateReport:
    return CandidateReport(
        effect=c.label,
        label=families.label(c),
        parameters={e.name: e.parameters for e in families.added(c.effects)},
        rmse_fit_k=round(c.rmse_fit_k, 5),
        rmse_holdout_k=None if c.rmse_holdout_k is None else round(c.rmse_holdout_k, 5),
        score=round(current.bic - c.bic, 3),
        fitted_on=c.fitted_on,
        held_out=c.held_out,
        refused=c.refused,
    )


def _figures(
    wh: Warehouse,
    ids: list[str],
    every: list[str],
    before: str,
    after: str,
    rmse: tuple[float | None, float | None],
) -> EventSetFigures:
    """An event set's figures: ``rmse`` (before, after) on its ``ids``, and both revisions'
    RMSE over ``every`` event of the set, flagged ones included."""
    return EventSetFigures(
        events=len(ids),
        rmse_before_k=rmse[0],
        rmse_after_k=rmse[1],
        events_all=len(every),
        rmse_before_all_k=rmse_from_predictions(wh, before, every) if every else None,
        rmse_after_all_k=rmse_from_predictions(wh, after, every) if every else None,
    )


def _adequacy_report(verdict: Verdict) -> AdequacyReport:
    a = verdict.adequacy
    return AdequacyReport(
        rmse_k=round(a.rmse_k, 5),
        ratio=round(a.ratio, 3),
        whiteness=round(a.whiteness, 3),
        explained_fraction=None if a.explained_fraction is None else round(a.explained_fraction, 4),
        correlations={k: round(v, 3) for k, v in a.correlations.items()},
    )


def _interval_methods(verdict: Verdict) -> IntervalMethods | None:
    iv = verdict.intervals
    if iv is None:
        return None
    return IntervalMethods(
        blocks=iv.blocks,
        widest=iv.method,
        jacobian=intervals_for_json(iv.jacobian),
        sandwich=intervals_for_json(iv.sandwich),
        jackknife=intervals_for_json(iv.jackknife),
        statistical=intervals_for_json(iv.intervals),
        numerical=verdict.numerical,
        inputs=verdict.inputs,
    )


def build_report(
    wh: Warehouse,
    evidence: Evidence,
    families: Families,
    fitted: Fitted,
    selection: Selection,
    verdict: Verdict,
    new: NewRevision | None,
    config: CloseLoopConfig,
) -> CloseLoopReport:
    """The close loop's last phase: the report of what the phases found (``new``: the new
    revision, None when nothing was added), the RMSE of every event of each set read from
    ``v_predictions``."""
    base = evidence.base.name
    every = evidence.events.every
    sentence = evidence.summary.sentence(evidence.noise_k)
    if new is None:
        sentence += "; no candidate effect explains a significant part of it: nothing was added"
        after, flags_with, added, parameters = base, base, None, {}
        ids = {
            "fit": evidence.events.fit["event_id"].to_list(),
            "holdout": evidence.events.holdout["event_id"].to_list(),
        }
        rmse: dict[str, tuple[float | None, float | None]] = {}
        for key, idset in ids.items():
            value = rmse_from_predictions(wh, base, idset) if idset else None
            rmse[key] = (value, value)
    else:
        after, flags_with, added = new.name, new.flags_judged_with, new.added
        parameters = report_parameters(new.added)
        ids = {"fit": new.fit_ids, "holdout": new.hold_ids}
        rmse = {key: (new.rmse[(key, base)], new.rmse[(key, new.name)]) for key in ids}
    figures = {key: _figures(wh, ids[key], every[key], base, after, rmse[key]) for key in ids}
    return CloseLoopReport(
        baseline_revision=base,
        new_revision=None if new is None else new.name,
        effect=None if new is None else new.chosen.label,
        parameters=parameters,
        evidence=sentence,
        fit=figures["fit"],
        holdout=figures["holdout"],
        candidates=[_candidate_report(c, fitted.current, families) for c in selection.candidates],
        noise_k=round(evidence.noise_k, 5),
        flags_judged_with=flags_with,
        solver=evidence.base.solver,
        residual=evidence.summary,
        n_eff=round(evidence.n_eff["fit"], 1),
        selection=_selection_text(evidence, config),
        exclusion=_exclusion_text(config),
        outliers=fitted.outliers,
        unknown_heat=UnknownHeat(len(evidence.unknown_heat), sorted(evidence.unknown_heat)),
        effects=added,
        interval_methods=_interval_methods(verdict),
        parameter_intervals=intervals_for_json(verdict.reported_intervals(parameters)),
        adequate=verdict.adequacy.adequate,
        unexplained=verdict.adequacy.unexplained,
        adequacy=_adequacy_report(verdict),
        drift=verdict.drift,
    )


def judged_on_report(
    wh: Warehouse, report: CloseLoopReport, config: CloseLoopConfig
) -> CloseLoopReport:
    """The verdict judged on the figure the report shows: the fit RMSE of the revision the
    report ends with, from ``v_predictions`` over the fit events as they stand after the
    re-flagging, less only the outlier events the report names (the fit's verdict was judged
    on the events of the choice, before the re-flagging; they differ when the flags moved).
    ``adequacy`` gives both figures: ``rmse_fit_k`` (every unflagged fit event, the report's
    ``fit.rmse_after_k``) and ``rmse_judged_k`` (less the outliers: what ``adequate`` is
    judged on), with ``ratio`` = ``rmse_judged_k / noise_k``."""
    noise = report.noise_k
    if not noise:
        return report
    revision = report.new_revision or report.baseline_revision
    unknown_heat = report.unknown_heat.event_ids
    fit_ids = event_sets(wh, report.baseline_revision, config, unknown_heat).fit
    fit_ids_list = fit_ids["event_id"].to_list()
    outliers = set(report.outliers.event_ids)
    kept = [e for e in fit_ids_list if e not in outliers]
    judged = rmse_from_predictions(wh, revision, kept) if kept else float("nan")
    if not math.isfinite(judged):
        return report
    ratio = judged / noise
    adequate = bool(ratio <= MAX_NOISE_RATIO)
    ad = dataclasses.replace(
        report.adequacy,
        rmse_choice_k=report.adequacy.rmse_k,
        rmse_k=round(judged, 5),
        rmse_judged_k=round(judged, 5),
        rmse_fit_k=report.fit.rmse_after_k,
        ratio=round(ratio, 3),
        max_ratio=MAX_NOISE_RATIO,
        judged_on=(
            f"v_predictions of {revision} over the {len(kept)} fit events of the report "
            f"less the {len(fit_ids_list) - len(kept)} outlier events (fit.rmse_after_k counts "
            "them too)"
        ),
    )
    unexplained = report.unexplained
    if adequate != report.adequate:
        unexplained = None if adequate else _unexplained(report, judged, noise, ad)
    return dataclasses.replace(report, adequacy=ad, adequate=adequate, unexplained=unexplained)


def _unexplained(report: CloseLoopReport, judged: float, noise: float, ad: AdequacyReport) -> str:
    """What is left when the verdict judged on the report's figure is inadequate."""
    before = report.fit.rmse_before_k
    rest = (
        f"{judged:.2g} K remains against {noise:.2g} K of sensor noise, "
        f"{describe_drivers(ad.correlations)}"
    )
    if report.new_revision:
        share = (
            f" explains {100 * max(1.0 - (judged / before) ** 2, 0.0):.0f} % of the residual"
            if before
            else " was added"
        )
        return f"partly explained: {report.effect}{share}; {rest}"
    return f"not explained: {rest}"


BOUND_REL_TOL = 1e-6
"""A fitted value within this share of a limit's size (at least of 1) is on it."""


def parameters_on_bound(
    effects: list[Effect] | None,
    parameters: Mapping[str, float],
    intervals: Mapping[str, Any],
) -> list[OnBound]:
    """The added ``effects``' parameters (keyed as the report's ``parameters``) whose value or
    interval (``[low, high]``, None: unbounded) reaches a limit of the effect's ``LIMITS``."""
    if not effects:
        return []
    qualified = len(effects) > 1
    out = []
    for effect in effects:
        for name, (low, high) in effect.LIMITS.items():
            key = f"{effect.name}.{name}" if qualified else name
            if key not in parameters:
                continue
            value = float(parameters[key])
            lo, hi = intervals.get(key, (value, value))
            for side, limit, reach in (("lower", low, lo), ("upper", high, hi)):
                if limit is None:
                    continue
                tol = BOUND_REL_TOL * max(1.0, abs(limit))
                beyond = reach is None or (
                    reach <= limit + tol if side == "lower" else reach >= limit - tol
                )
                if abs(value - limit) <= tol or beyond:
                    out.append(OnBound(key, effect.name, side, float(limit), value))
    return out


def bounds_verdict(report: CloseLoopReport) -> CloseLoopReport:
    """The verdict with the parameters on a bound: a fitted value or interval that reaches a
    limit of its family says the law in the data lies outside the family as implemented (its
    form, constants or units differ), so the revision is not adequate, and ``unexplained``
    names the parameter and the limit."""
    found = parameters_on_bound(report.effects, report.parameters, report.parameter_intervals)
    if not found:
        return report
    named = "; ".join(
        f"{b.effect}: {b.parameter} = {b.value:.4g} reaches its {b.side} limit {b.limit:.4g}"
        for b in found
    )
    sentence = (
        f"{named} (the law in the data lies outside the family as implemented: its form, "
        "constants or units differ)"
    )
    unexplained = sentence if report.adequate else f"{report.unexplained}; {sentence}"
    return dataclasses.replace(report, adequate=False, unexplained=unexplained, on_bound=found)


def _drift_json(drift: DriftReport) -> dict[str, Any]:
    return {
        "period": drift.period,
        "parameters": {
            k: {
                "rate_per_day": _finite(d.rate_per_day),
                "rate_interval": [_finite(v) for v in d.rate_interval],
                "changes": d.changes,
            }
            for k, d in drift.parameters.items()
        },
        "periods": [
            {
                "start": p.start,
                "seconds": p.seconds,
                "values": p.values,
                "intervals": {k: [_finite(a), _finite(b)] for k, (a, b) in p.intervals.items()},
            }
            for p in drift.periods
        ],
    }


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def drift_verdict(report: CloseLoopReport) -> CloseLoopReport:
    """The verdict with the parameters that change over the fit days: a constant effect does
    not explain them, so the revision is not adequate, and ``unexplained`` says which changes
    and at what rate."""
    if report.drift is None:
        return report
    changing = {k: d for k, d in report.drift.parameters.items() if d.changes}
    if not changing:
        return report
    named = "; ".join(
        f"{k} changes over the period: {d.rate_per_day:+.3g} per day "
        f"[{d.rate_interval[0]:.3g}, {d.rate_interval[1]:.3g}]"
        for k, d in changing.items()
    )
    sentence = f"{report.effect}: {named} (fitted as a constant)"
    unexplained = sentence if report.adequate else f"{report.unexplained}; {sentence}"
    return dataclasses.replace(report, adequate=False, unexplained=unexplained)
