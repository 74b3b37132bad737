"""The close loop's second phase, candidate families: what a candidate is
(:class:`Candidate`: effects added over the baseline, fitted and scored), which are tried
(:class:`Families`: singles, pairs seeded from the chosen single, the ``empirical`` fallback
last), how a candidate's fit is asked for (:class:`FitRequests`), and whether a candidate
leaves a residual consistent with the sensor noise (:func:`adequacy_of`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.fitdata import FitData
from fleetbrake.closeloop.leastsquares import FitResult, FitTask, report_key
from fleetbrake.closeloop.stats import (
    Adequacy,
    adequacy,
    information_criterion,
    root_mean_square,
)
from fleetbrake.model.effects import EFFECT_ORDER, Effect, EffectSet

__all__ = [
    "DRIVER_PERIODS",
    "Candidate",
    "Families",
    "FitRequests",
    "HeldOut",
    "HeldOutFailed",
    "adequacy_of",
    "candidate_families",
    "drivers_at",
    "law",
    "law_label",
    "report_parameters",
    "scored",
]


@dataclass
class Candidate:
    effects: EffectSet
    rmse_fit_k: float
    bic: float
    n_parameters: int
    rmse_holdout_k: float | None = None
    fitted: FitResult | None = None
    fitted_on: str = "fit"
    """``fit``: every fit event; ``screen``: the screening events only."""
    held_out: HeldOut | HeldOutFailed | None = None
    """The held-out comparison with what it would be added to (when judged)."""
    refused: str | None = None
    """Why it did not enter (None: it entered, or was not judged)."""

    @property
    def label(self) -> str:
        return "+".join(e.name for e in self.effects) or "none"


@dataclass(frozen=True)
class HeldOut:
    """A candidate's held-out comparison with what it would be added to (whole wagon-days per
    fold, :func:`~fleetbrake.closeloop.stats.improves_held_out`), as the report gives it."""

    over: str
    """The law label of what it adds to."""
    rmse_over_k: float
    rmse_k: float
    gain: float
    """Relative cut of the held-out RMSE."""
    margin: float
    folds_improved: int
    folds: int


@dataclass(frozen=True)
class HeldOutFailed:
    """A held-out comparison that could not be made, and why."""

    error: str


@dataclass(frozen=True)
class Families:
    """The candidate families over the baseline: single effects (every effect of the
    configuration the baseline lacks), pairs seeded from a chosen single
    (:meth:`partners`), and the ``fallback`` laws (``empirical``), tried last."""

    present: frozenset[type[Effect]]
    """The effect classes the baseline revision already has."""
    singles: tuple[type[Effect], ...]
    fallbacks: tuple[type[Effect], ...]

    def added(self, effects: EffectSet) -> list[Effect]:
        """The effects of ``effects`` the baseline lacks."""
        return [e for e in effects if type(e) not in self.present]

    def partners(self, first: Sequence[Effect]) -> list[type[Effect]]:
        """The second effects of the pairs seeded from ``first`` (the chosen single)."""
        names = {e.name for e in first}
        return [cls for cls in self.singles if cls.name not in names]

    def label(self, c: Candidate) -> str:
        """The candidate's added laws (:func:`law_label`)."""
        return law_label(c, set(self.present))


def candidate_families(present: frozenset[type[Effect]], config: CloseLoopConfig) -> Families:
    """The close loop's second phase: which effects are tried, over a baseline with the
    effects ``present`` (the singles in :data:`~fleetbrake.model.effects.EFFECT_ORDER`; a
    fallback only when no candidates are named)."""
    return Families(
        present=present,
        singles=tuple(cls for cls in config.candidate_classes() if cls not in present),
        fallbacks=tuple(
            cls
            for cls in EFFECT_ORDER
            if getattr(cls, "fallback", False) and cls not in present and config.candidates is None
        ),
    )


@dataclass(frozen=True)
class FitRequests:
    """How a candidate's fit is asked for: over the baseline's effects, the configuration's
    Jacobian step and refit stopping rule, the outlier events left out (``excluded``, set
    once the outliers are known)."""

    base: EffectSet
    diff_step: float
    refit_step_tolerance: float
    excluded: frozenset[str] = frozenset()

    def task(
        self,
        data: FitData,
        classes: Sequence[type[Effect]],
        start: Sequence[Effect] | None,
        nfev: int,
        refit: bool = False,
    ) -> FitTask:
        """A fit of ``classes`` from ``start``; ``refit``: every parameter starts fitted (the
        refits' stopping rule applies, ``CloseLoopConfig.refit_step_tolerance``)."""
        return FitTask(
            data,
            self.base,
            tuple(classes),
            None if start is None else tuple(start),
            nfev,
            self.diff_step,
            self.excluded,
            self.refit_step_tolerance if refit else 0.0,
        )


def scored(fitted: FitResult, k: int, on: str, n_eff: Mapping[str, float]) -> Candidate:
    """The candidate of a fit of ``k`` parameters on the ``on`` data set (``fit`` or
    ``screen``), scored on that set's effective sample size."""
    r = fitted.residual
    bic = information_criterion(r, k, n_eff[on])
    return Candidate(fitted.effects, root_mean_square(r), bic, k, fitted=fitted, fitted_on=on)


def law(effect: Effect) -> str:
    """``name[law]``: the vocabulary name and the law (``convection_speed[flat_plate]``)."""
    return f"{effect.name}[{effect.law}]"


def law_label(c: Candidate, present: set[type[Effect]]) -> str:
    """The candidate's added laws, ``+``-joined (the report's candidate ``label``; its
    ``effect`` stays the vocabulary names)."""
    return "+".join(law(e) for e in c.effects if type(e) not in present) or "none"


def report_parameters(added: Sequence[Effect]) -> dict[str, float]:
    """The report's flat ``parameters`` map (interface.md: parameter -> value) of the added
    effects, keyed as :func:`~fleetbrake.closeloop.leastsquares.report_key` does."""
    qualified = len(added) > 1
    return {
        report_key(f"{e.name}.{k}", qualified): v for e in added for k, v in e.parameters.items()
    }


DRIVER_PERIODS: dict[str, float] = {"hour of day": 24.0}
"""Drivers that are phases (hours on a 24 h clock), correlated with a leftover residual by
the circular-linear correlation: sunshine peaking at noon has next to no Pearson correlation
with the hour counted from midnight."""


def drivers_at(data: FitData, scored: np.ndarray) -> dict[str, np.ndarray]:
    """What a residual may still correlate with, at the ``scored`` seconds of ``data``."""
    time_s = data.time_utc.astype("datetime64[us]").astype(np.int64) / 1e6
    first = np.full(len(data.event_ids), np.inf)
    np.minimum.at(first, data.event, time_s)
    named = {
        "speed": data.drivers["speed_kmh"],
        "pressure": data.drivers["brake_pressure_bar"],
        "heat input": data.drivers["flux_w_m2"],
        "ambient": data.drivers["ambient_c"],
        "time since activation": time_s - first[data.event],
        "heating phase": data.heating.astype(np.float64),
        "hour of day": (time_s % 86400.0) / 3600.0,
    }
    return {name: values[scored] for name, values in named.items()}


def adequacy_of(
    chosen: Candidate | None,
    data: FitData,
    base: tuple[np.ndarray, np.ndarray],
    noise_k: float,
    current: Candidate,
) -> Adequacy:
    """Whether ``chosen`` (None: the baseline, ``base``: its residual and the seconds it is
    of) leaves a fit residual consistent with the sensor noise
    (:func:`~fleetbrake.closeloop.stats.adequacy`; ``current``: the baseline as a candidate,
    for the share explained)."""
    if chosen is None or chosen.fitted is None:
        residual, scored = base
        effect = None
    else:
        residual, scored, effect = chosen.fitted.aligned, chosen.fitted.scored, chosen.label
    return adequacy(
        residual,
        data.blocks[scored],
        noise_k,
        drivers_at(data, scored),
        before_rmse_k=current.rmse_fit_k if effect is not None else None,
        effect=effect,
        periods=DRIVER_PERIODS,
    )
