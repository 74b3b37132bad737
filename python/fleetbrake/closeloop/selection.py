"""The close loop's fourth phase, selection (never looks at the holdout): every addition -- the
first effect over the current revision (singles fitted on every fit event, best criterion
first), a pair over its single, ``empirical`` over what it corrects -- must (a) beat what it
adds to by ``bic_margin`` on the Bayesian information criterion on the effective sample size
of the baseline residual and cut the fit RMSE by ``min_improvement``, (b) cut the held-out
RMSE of whole wagon-days (``folds``, each fit moved one Gauss-Newton step off its fold:
nothing re-simulated) by ``held_out_margin`` and on most folds, and (c) have its laws'
parameters distinguishable from their nulls
(:data:`~fleetbrake.closeloop.stats.EFFECT_NULLS`) by 95 % intervals; a candidate's
``refused`` says which failed. Pairs are tried when the chosen single leaves the fit RMSE
above ``pair_above_noise`` times the noise. A physical answer that leaves the fit inadequate
and explains less than ``min_explained_share`` of the baseline's systematic residual is a
proxy for something outside the vocabulary and is refused; then only ``empirical`` may enter
(:func:`select` -> :class:`Selection`). The fitted candidates' holdout RMSE is computed here
for the report, never to choose."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from fleetbrake.closeloop.candidates import (
    Candidate,
    Families,
    HeldOut,
    HeldOutFailed,
    adequacy_of,
    law,
    scored,
)
from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.evidence import Evidence
from fleetbrake.closeloop.fit import Fitted
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.leastsquares import fit_intervals
from fleetbrake.closeloop.stats import (
    EFFECT_NULLS,
    Comparison,
    SelectionError,
    block_folds,
    distinguishable_from_null,
    improves_held_out,
    root_mean_square,
    systematic_share,
)
from fleetbrake.closeloop.workers import Workers

__all__ = ["Selection", "held_out_comparison", "select"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Selection:
    """What the choice ended with: the chosen candidate (None: nothing enters) and every
    candidate judged, those fitted on every fit event first, best criterion first."""

    chosen: Candidate | None
    candidates: list[Candidate]


class _Rule:
    """The rule every addition must pass (see the module), on the fit events less the
    outliers: ``admit`` says whether a candidate enters over what it adds to, and records
    why not (``Candidate.refused``) and its held-out comparison (``Candidate.held_out``)."""

    def __init__(
        self, evidence: Evidence, families: Families, fitted: Fitted, config: CloseLoopConfig
    ) -> None:
        self.evidence, self.families, self.fitted, self.config = evidence, families, fitted, config

    def significant_over(self, c: Candidate | None, than: Candidate) -> bool:
        config = self.config
        return (
            c is not None
            and c.bic < than.bic - config.bic_margin
            and c.rmse_fit_k < (1.0 - config.min_improvement) * than.rmse_fit_k
        )

    def admit(self, c: Candidate, over: Candidate) -> bool:
        """Whether ``c`` enters over ``over`` (the baseline, or the model it adds to): the
        criterion by its margin, the held-out wagon-days by the stated margin, and the added
        laws' parameters distinguishable from their nulls. Says why not in ``c.refused``."""
        config, label = self.config, self.families.label
        if not self.significant_over(c, over):
            c.refused = (
                f"criterion: score {over.bic - c.bic:.1f} over {label(over)} "
                f"(needs {config.bic_margin:g}) and fit RMSE {c.rmse_fit_k:.4f} K against "
                f"{over.rmse_fit_k:.4f} K (needs a {100 * config.min_improvement:.0f} % cut)"
            )
            return False
        reasons = []
        data = self.evidence.fit_data
        try:
            comparison = held_out_comparison(c, over, data, self.fitted.base_kept, config)
        except SelectionError as exc:
            c.held_out = HeldOutFailed(str(exc))
            logger.warning("held-out comparison of %s not possible: %s", c.label, exc)
        else:
            c.held_out = HeldOut(
                over=label(over),
                rmse_over_k=round(comparison.rmse_a_k, 5),
                rmse_k=round(comparison.rmse_b_k, 5),
                gain=round(comparison.gain, 4),
                margin=comparison.margin,
                folds_improved=comparison.folds_improved,
                folds=comparison.folds,
            )
            if not comparison.improves:
                reasons.append(comparison.describe())
        if c.fitted is not None:
            reasons += self._null_reasons(c, over, fit_intervals(c.fitted, data).intervals)
        c.refused = "; ".join(reasons) or None
        if c.refused:
            logger.info("%s does not enter: %s", label(c), c.refused)
        return c.refused is None

    def _null_reasons(
        self, c: Candidate, over: Candidate, iv: Mapping[str, tuple[float, float]]
    ) -> list[str]:
        """Why ``c``'s laws added over ``over`` are not distinguishable from their nulls."""
        before = {type(e) for e in over.effects}
        reasons = []
        for e in c.effects:
            if type(e) in before or type(e) in self.families.present:
                continue
            nulls = {f"{e.name}.{k}": v for k, v in EFFECT_NULLS.get(law(e), {}).items()}
            any_of = e.name == "empirical"
            if not distinguishable_from_null(iv, nulls, any_of=any_of):
                inside = ", ".join(
                    f"{k.split('.', 1)[1]} = {v:g} within "
                    f"[{iv.get(k, (-math.inf, math.inf))[0]:.4g}, "
                    f"{iv.get(k, (-math.inf, math.inf))[1]:.4g}]"
                    for k, v in nulls.items()
                )
                reasons.append(f"{law(e)} not distinguishable from its null: {inside}")
        return reasons


def _pair(
    best: Candidate,
    rule: _Rule,
    candidates: list[Candidate],
    workers: Workers,
) -> Candidate:
    """Pairs seeded from the chosen single ``best``: its fitted effect, the second from its
    range, screened; the best pair refitted on every fit event and entering over its single
    by the same rule as the single over the baseline. Returns what is chosen then."""
    evidence, families, config = rule.evidence, rule.families, rule.config
    requests, n_eff, screened_on = rule.fitted.requests, evidence.n_eff, evidence.screened_on
    first = families.added(best.effects)
    others = families.partners(first)
    pair_results = workers.fit(
        [
            requests.task(evidence.screen_data, [type(first[0]), cls], first, config.max_nfev)
            for cls in others
        ],
        "pairs",
    )
    pairs = [
        scored(res, best.n_parameters + len(cls.PARAMETER_RANGES), screened_on, n_eff)
        for cls, res in zip(others, pair_results, strict=True)
    ]
    for c in pairs:
        logger.debug("screened pair %s: rmse %.4f K", c.label, c.rmse_fit_k)
    if not pairs:
        return best
    top_pair = min(pairs, key=lambda c: c.bic)
    added = families.added(top_pair.effects)
    if screened_on == "fit":  # screened on every fit event already
        refitted = top_pair
    else:
        (res,) = workers.fit(
            [
                requests.task(
                    evidence.fit_data,
                    [type(e) for e in added],
                    added,
                    max(4, config.max_nfev // 2),
                    refit=True,
                )
            ],
            "pairs",
        )
        refitted = scored(res, top_pair.n_parameters, "fit", n_eff)
    logger.debug("refitted pair %s: rmse %.4f K", refitted.label, refitted.rmse_fit_k)
    candidates.append(refitted)
    # a pair enters over its single by the same rule as the single over the baseline
    return refitted if rule.admit(refitted, best) else best


def _not_a_proxy(best: Candidate | None, rule: _Rule) -> Candidate | None:
    """``best``, unless it is a proxy: an inadequate physical answer is named only when it is
    the dominant cause of the misfit. With the truth outside the vocabulary, an effect
    correlated with it passes the criterion and the held-out folds against a baseline that
    is itself wrong, and its parameter then describes the missing term, not its own law; such
    a proxy gives way to the empirical correction alone (or nothing)."""
    config, evidence, current = rule.config, rule.evidence, rule.fitted.current
    if best is None or config.min_explained_share <= 0:
        return best
    noise_k = evidence.noise_k
    verdict = adequacy_of(best, evidence.fit_data, rule.fitted.base_kept, noise_k, current)
    share = systematic_share(current.rmse_fit_k, best.rmse_fit_k, noise_k)
    if verdict.adequate or share >= config.min_explained_share:
        return best
    best.refused = (
        f"proxy: leaves the fit inadequate ({verdict.ratio:.2f}x the noise) and "
        f"explains {100 * max(share, 0.0):.0f} % of the systematic residual (needs "
        f"{100 * config.min_explained_share:.0f} %): not the cause of the misfit"
    )
    logger.info("%s is not named: %s", rule.families.label(best), best.refused)
    return None


def _fallback(
    chosen: Candidate | None, rule: _Rule, candidates: list[Candidate], workers: Workers
) -> Candidate | None:
    """Nothing physical adequate: the empirical correction, last (on the chosen physical
    effect when one entered), entering over what it corrects by the same rule. Returns what
    is chosen then."""
    evidence, families, config, fitted = rule.evidence, rule.families, rule.config, rule.fitted
    current, base_kept = fitted.current, fitted.base_kept
    if (
        not families.fallbacks
        or adequacy_of(chosen, evidence.fit_data, base_kept, evidence.noise_k, current).adequate
    ):
        return chosen
    t = time.perf_counter()
    seed = families.added(chosen.effects) if chosen is not None else []
    if len(seed) < config.max_effects:
        classes = [type(e) for e in seed] + list(families.fallbacks[:1])
        (res,) = workers.fit(
            [fitted.requests.task(evidence.fit_data, classes, seed, max(4, config.max_nfev // 2))],
            "empirical",
        )
        k = sum(len(cls.PARAMETER_RANGES) for cls in classes)
        empirical = scored(res, k, "fit", evidence.n_eff)
        logger.debug("fitted %s: rmse %.4f K", empirical.label, empirical.rmse_fit_k)
        candidates.append(empirical)
        if rule.admit(empirical, chosen or current):
            chosen = empirical
    workers.timing["empirical_s"] = time.perf_counter() - t
    return chosen


def select(
    evidence: Evidence,
    families: Families,
    fitted: Fitted,
    config: CloseLoopConfig,
    workers: Workers,
) -> Selection:
    """The close loop's fourth phase (see the module)."""
    rule = _Rule(evidence, families, fitted, config)
    candidates = list(fitted.candidates)
    # the first effect over the baseline: the singles fitted on every fit event, best
    # criterion first, the first that enters
    best: Candidate | None = None
    for c in fitted.comparable:
        if c.fitted_on == "fit" and rule.admit(c, fitted.current):
            best = c
            break
    t = time.perf_counter()
    if (
        best is not None
        and config.max_effects >= 2
        and best.rmse_fit_k > config.pair_above_noise * evidence.noise_k
    ):
        best = _pair(best, rule, candidates, workers)
    workers.timing["pairs_s"] = time.perf_counter() - t
    t = time.perf_counter()
    if evidence.hold_data is not None:
        fitted_all = [c for c in candidates if c.fitted_on == "fit"]
        for c, r in zip(
            fitted_all,
            workers.evaluate(evidence.hold_data, [c.effects for c in fitted_all], "holdout"),
            strict=True,
        ):
            c.rmse_holdout_k = root_mean_square(r[np.isfinite(r)])
    workers.timing["holdout_s"] = time.perf_counter() - t
    chosen = _fallback(_not_a_proxy(best, rule), rule, candidates, workers)
    candidates.sort(key=lambda c: (c.fitted_on != "fit", c.bic))
    return Selection(chosen, candidates)


def _on_seconds(
    c: Candidate, n: int, base: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(residual, mask, Jacobian) of a candidate over every second of the fit data (NaN and
    zero rows where it is not scored); the baseline (nothing fitted) from ``base``."""
    r = np.full(n, np.nan)
    if c.fitted is None:
        residual, mask = base
        r[mask] = residual
        return r, np.asarray(mask, dtype=bool), None
    mask = np.asarray(c.fitted.scored, dtype=bool)
    r[mask] = c.fitted.aligned
    j = np.zeros((n, c.fitted.jacobian.shape[1]))
    j[mask] = c.fitted.jacobian
    return r, mask, j


def held_out_comparison(
    c: Candidate,
    over: Candidate,
    data: FitData,
    base: tuple[np.ndarray, np.ndarray],
    config: CloseLoopConfig,
) -> Comparison:
    """Blocked cross-validation of ``c`` against ``over`` on the seconds both are scored on:
    whole wagon-days per fold, each fit moved one Gauss-Newton step off the fold
    (:func:`~fleetbrake.closeloop.stats.improves_held_out`)."""
    n = data.measured_c.size
    ra, ma, ja = _on_seconds(over, n, base)
    rb, mb, jb = _on_seconds(c, n, base)
    common = ma & mb & np.isfinite(ra) & np.isfinite(rb)
    folds = block_folds(data.blocks[common], config.folds)
    return improves_held_out(
        ra[common],
        None if ja is None else ja[common],
        rb[common],
        None if jb is None else jb[common],
        folds,
        config.held_out_margin,
    )
