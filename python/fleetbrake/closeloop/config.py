"""The close loop's configuration (:class:`CloseLoopConfig`)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field

from fleetbrake.closeloop.errors import CloseLoopConfigError
from fleetbrake.closeloop.stats import (
    GCI_ORDER,
    GCI_SAFETY_FACTOR,
    MAX_NOISE_RATIO,
    MIN_EXPLAINED_SHARE,
)
from fleetbrake.model.effects import EFFECT_ORDER, EFFECTS, Effect
from fleetbrake.simulation.config import SimulationConfig

__all__ = ["CloseLoopConfig"]


@dataclass(frozen=True)
class CloseLoopConfig:
    """How the close loop chooses, fits and judges the effect the model lacks (the method:
    :mod:`fleetbrake.closeloop.loop`; the reasons: ``docs/closeloop.md``).

    Read by: ``fleetbrake close-loop``, ``fleetbrake demo``."""

    holdout_from: dt.date
    """Events starting on or after this date are the holdout: never used to fit or to
    choose, only to report the error before and after."""
    max_effects: int = 2
    """At most this many effects are added over the current revision (a pair at most)."""
    bic_margin: float = 10.0
    """How much lower the criterion of a candidate must be than the current revision's."""
    min_improvement: float = 0.05
    """Relative cut of the fit RMSE a candidate must bring."""
    pair_above_noise: float = MAX_NOISE_RATIO
    """Try pairs of effects when the chosen single leaves the fit RMSE above this many times
    the estimated sensor noise: the adequacy bar (a model adequate on its own is not made
    richer)."""
    held_out_margin: float = 0.05
    """Every addition (the first effect over the baseline, a pair over its single, the
    ``empirical`` correction over what it corrects) must cut the held-out RMSE of the fit
    period's blocks (wagon-days) by at least this share, on most folds, and its parameters
    must be distinguishable from their nulls
    (:func:`~fleetbrake.closeloop.stats.improves_held_out`)."""
    folds: int = 5
    """Folds of whole wagon-days for the held-out comparison (one per block when fewer)."""
    max_nfev: int = 14
    """Model evaluations per parameter fit (each re-simulates the fit events; the Jacobian's
    perturbed vectors not counted)."""
    diff_step: float = 0.05
    """Relative forward-difference step of the Jacobian (above ``H_QUANTUM_W_M2K``'s rounding
    of a varying convection)."""
    screen_events: int = 60
    """Candidates are first fitted on at most this many fit events (the earliest of each
    wagon in turn: their chains are short); the best ones are then refitted on all of them."""
    refit: int = 2
    """How many of the screened candidates are refitted on every fit event."""
    reflag: bool = True
    """After adding an effect, judge the flags again with the new revision and refit on the
    events that are usable then (flags judged with a model that lacks the effect mistake a
    fleet-wide misfit for anomalies)."""
    settle_after_flag_s: float = 3600.0
    """Events starting less than this after the end of a brake or sensor-fault flag of their
    wagon are left out: the state carried out of the anomaly is still off (a weak braking
    leaves the simulated block ~0.8 K too warm at the sensor 25 min later)."""
    outlier_noise_factor: float = 5.0
    """Events whose residual RMS under the best screened single effect is above this many
    times the sensor noise ..."""
    outlier_z: float = 5.0
    """... and this many robust standard deviations above the events' median are left out of
    the fit as outliers (:func:`~fleetbrake.closeloop.stats.outlier_events`)."""
    max_outlier_fraction: float = 0.05
    """At most this share of the fit events is left out as outliers (0: none)."""
    refit_changed_fraction: float = 0.02
    """After re-flagging, the effect is refitted only when the fit set changed by at least
    this share of its events."""
    refit_step_tolerance: float = 0.1
    """A refit from fitted parameters (the chosen effect on every fit event from its screened
    parameters, the re-flag refit, the numerical term's coarse-mesh refits) ends at the first
    trial step below this many standard errors in every parameter (its Jacobian's at the
    start, on the effective sample size), without evaluating it
    (:func:`~fleetbrake.closeloop.leastsquares.fit_parameters`; 0: scipy's
    default relative tolerance only). Such a step moves no parameter by more than a fifth of
    ``refit_tolerance`` (at least 0.49 standard errors) (docs/closeloop.md, "3. Fit": "Refits
    stop at the fit's resolution")."""
    refit_tolerance: float = 0.25
    """A re-flag refit whose every parameter moved by less than this share of its 95 %
    interval's half-width (:func:`~fleetbrake.closeloop.revision.refit_moved`) keeps the
    revision as it was simulated, estimated and flagged: the new revision is re-simulated only
    when the refit changes the answer beyond the fit's own uncertainty."""
    min_explained_share: float = MIN_EXPLAINED_SHARE
    """A physical answer that leaves the fit inadequate is named only when it explains at
    least this share of the baseline's systematic residual
    (:func:`~fleetbrake.closeloop.stats.systematic_share`); otherwise it is a proxy for
    something outside the vocabulary and only the ``empirical`` correction may enter (0: no
    such rule). An adequate answer is never affected."""
    numerical_grid_ratios: tuple[float, ...] = (1.5, 2.0)
    """The reported intervals' numerical (model-form) term: the chosen effects refitted once
    per ratio, on the same fit events from the chosen parameters, through the reduced model on
    a coarser mesh (the revision's refinement divided by the ratio, cells per direction); the
    parameters' shift between each coarse mesh and the revision's as Roache's grid
    convergence index (two grids: ``gci_safety_factor`` 3, the formal order ``gci_order``),
    the largest over the coarse meshes added in quadrature to the statistical half-width
    (:func:`~fleetbrake.closeloop.stats.with_numerical_term`). Empty: no such term. Entry
    (distinguishable from the nulls) is judged on the statistical intervals alone."""
    gci_safety_factor: float = GCI_SAFETY_FACTOR
    """Roache's safety factor of the grid convergence index (two grids: 3)."""
    gci_order: float = GCI_ORDER
    """The formal order of convergence the grid convergence index assumes."""
    speed_input_term: bool = True
    """The reported intervals' input term (ASME V&V 20's u_input by its sensitivity method:
    the parameters' response to the input's systematic error taken out): the residual of the
    chosen parameters evaluated on the same fit events with the speed read as
    ``sqrt(max(v^2 - noise^2, 0))`` (:func:`~fleetbrake.closeloop.terms.with_speed_debiased`,
    the noise estimated from the logged speed by
    :func:`~fleetbrake.closeloop.terms.speed_noise_kmh`), and the parameters moved by
    quasi-Newton steps from the Jacobian the fit already has (Broyden-updated), one
    evaluation each (:func:`~fleetbrake.closeloop.terms.input_shift`, a few evaluations
    where a refit from the chosen parameters takes about 20); the shift per parameter added
    in quadrature to the statistical half-width with the numerical term. Why: a GPS speed is
    a magnitude, so where the wagon stands it reads about its noise, not 0, and a convection
    law steep at low speed turns that into a bias of its exponent the same on every
    wagon-day, which no resampling sees (docs/closeloop.md, "6. New revision"). False: no
    such term."""
    input_step_tolerance: float = 0.05
    """The input term's steps stop when a step is at most this share of the
    shift in every parameter (:func:`~fleetbrake.closeloop.terms.input_shift`)."""
    overlap: bool = True
    """With an engine of worker processes: the interval terms (numerical and input), which
    depend only on the chosen fit and its fit events, have their data built while the
    revision is made and re-flagged and are computed while the chosen effect is refitted
    (the numerical term's coarse fits on the workers, the input term's evaluations and the
    refit in this process), and computed again after it only when the refit moved the
    answer (``refit_moved``): the same report and stored values as one after another
    (False), in less time (the report's ``cost`` gives each phase's seconds)."""
    candidates: tuple[str, ...] | None = None
    """The effects to try, by vocabulary name (None: every effect of
    :data:`fleetbrake.model.effects.EFFECT_ORDER`)."""
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    """How the events are simulated (mesh, solver, chains) for the fit and the new
    revision; the baseline keeps the solver and mesh it was made with."""

    def __post_init__(self) -> None:
        unknown = sorted(set(self.candidates or ()) - set(EFFECTS))
        if unknown:
            raise CloseLoopConfigError(
                f"candidates: unknown effect(s) {', '.join(unknown)}; the vocabulary is "
                f"{', '.join(EFFECTS)}"
            )
        if not all(r > 1.0 for r in self.numerical_grid_ratios):
            raise CloseLoopConfigError(
                f"numerical_grid_ratios must each be > 1 (fine over coarse cells per "
                f"direction), got {self.numerical_grid_ratios}"
            )
        if not self.refit_step_tolerance >= 0.0:
            raise CloseLoopConfigError(
                f"refit_step_tolerance must be >= 0, got {self.refit_step_tolerance}"
            )
        if not self.refit_tolerance >= 0.0:
            raise CloseLoopConfigError(f"refit_tolerance must be >= 0, got {self.refit_tolerance}")

    def candidate_classes(self) -> tuple[type[Effect], ...]:
        """The effect classes to try, in :data:`EFFECT_ORDER`."""
        wanted = set(EFFECTS) if self.candidates is None else set(self.candidates)
        # a fallback (``empirical``) only when named: the method tries it last
        return tuple(
            cls
            for cls in EFFECT_ORDER
            if cls.name in wanted and (self.candidates is not None or not cls.fallback)
        )
