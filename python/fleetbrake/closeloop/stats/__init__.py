"""The close loop's statistics: how many independent residuals there are, whether a candidate
improves what it was not fitted on, how sure its parameters are, and whether the chosen model
is adequate (the method and its reasons: ``docs/closeloop.md``).

Pure numpy on arrays (no database, no simulation): a residual is one value per second, in time
order within each *block* (``blocks``: an id per second, integers or any sortable labels
such as event ids, for a wagon-day or an event chain). Nothing here looks across a block
boundary: the seconds of one block are correlated, blocks are taken as independent of each
other.

* :func:`effective_sample_size` -- ``n / tau`` with ``tau = 1 + 2 sum rho_k`` from the
  residual's autocorrelation pooled over blocks, truncated by Geyer's initial monotone
  positive sequence; bounded by ``[n_blocks, n]``.
* :func:`information_criterion` -- BIC on that effective sample size.
* :func:`block_folds`, :func:`held_out_residual`, :func:`blocked_cv_rmse`,
  :func:`improves_held_out` -- blocked cross-validation: whole blocks per fold; a fitted
  candidate's held-out residual from its Jacobian (one Gauss-Newton step from the fit on all
  blocks to the fit without the fold: exact for a model linear in its parameters), so that
  the comparison costs no re-simulation.
* :func:`parameter_intervals`, :func:`distinguishable_from_null` -- Gauss-Newton covariance
  ``s^2 (J^T J)^-1`` inflated by ``n / n_eff``, Student-t intervals on ``n_eff - p`` degrees
  of freedom; :func:`refusal` says why a candidate does not enter (not by the margin on the
  held-out blocks, or a parameter not distinguishable from its null).
* :func:`blocked_intervals` -- the intervals the close loop reports: the wider of the
  ``n_eff`` Jacobian interval, a cluster-robust (sandwich) interval with the blocks as
  clusters and a delete-one-block jackknife (one Gauss-Newton step per block from the
  optimum with the fit's Jacobian), the last two with Student-t quantiles on ``blocks - 1``
  degrees of freedom; :data:`EFFECT_NULLS` the values at which each law's part vanishes.
* :func:`grid_convergence_index`, :func:`with_numerical_term` -- the numerical (model-form)
  term the resampling cannot see: Roache's GCI of the parameters refitted through coarser
  meshes, added in quadrature to the statistical half-width (ASME V&V 20's combination).
* :func:`noise_from_residual` -- white sensor noise from the residual's second differences
  within blocks (median absolute deviation).
* :func:`parameter_drift` -- the fitted parameters per day (one Gauss-Newton step on the
  day's rows) and the weighted slope of each over the days: whether it changes over the
  period.
* :func:`adequacy` -- the chosen model's residual against the noise: RMSE ratio, whiteness,
  what it still correlates with, and the sentence the report gives when it is not adequate.
"""

from __future__ import annotations

from fleetbrake.closeloop.stats.adequacy import (
    MAX_NOISE_RATIO,
    MIN_CORRELATION,
    MIN_EXPLAINED_SHARE,
    Adequacy,
    adequacy,
    circular_linear_correlation,
    describe_drivers,
    ljung_box_white_fraction,
    systematic_share,
)
from fleetbrake.closeloop.stats.blocks import (
    MAX_OUTLIER_FRACTION,
    OUTLIER_NOISE_FACTOR,
    OUTLIER_Z,
    SelectionError,
    as_arrays,
    autocorrelation,
    block_slices,
    effective_sample_size,
    event_rms,
    information_criterion,
    noise_from_residual,
    outlier_events,
    root_mean_square,
)
from fleetbrake.closeloop.stats.drift import (
    DriftReport,
    ParameterDrift,
    PeriodFit,
    parameter_drift,
)
from fleetbrake.closeloop.stats.heldout import (
    HELD_OUT_MARGIN,
    Comparison,
    block_folds,
    blocked_cv_rmse,
    held_out_residual,
    improves_held_out,
)
from fleetbrake.closeloop.stats.intervals import (
    EFFECT_NULLS,
    GCI_ORDER,
    GCI_SAFETY_FACTOR,
    BlockedIntervals,
    blocked_intervals,
    combined_half_width,
    distinguishable_from_null,
    grid_convergence_index,
    intervals_for_json,
    parameter_covariance,
    parameter_intervals,
    refusal,
    standard_errors,
    with_numerical_term,
)

__all__ = [
    "EFFECT_NULLS",
    "GCI_ORDER",
    "GCI_SAFETY_FACTOR",
    "HELD_OUT_MARGIN",
    "MAX_NOISE_RATIO",
    "MAX_OUTLIER_FRACTION",
    "MIN_CORRELATION",
    "MIN_EXPLAINED_SHARE",
    "OUTLIER_NOISE_FACTOR",
    "OUTLIER_Z",
    "Adequacy",
    "BlockedIntervals",
    "Comparison",
    "DriftReport",
    "ParameterDrift",
    "PeriodFit",
    "SelectionError",
    "adequacy",
    "as_arrays",
    "autocorrelation",
    "block_folds",
    "block_slices",
    "blocked_cv_rmse",
    "blocked_intervals",
    "circular_linear_correlation",
    "combined_half_width",
    "describe_drivers",
    "distinguishable_from_null",
    "effective_sample_size",
    "event_rms",
    "grid_convergence_index",
    "held_out_residual",
    "improves_held_out",
    "information_criterion",
    "intervals_for_json",
    "ljung_box_white_fraction",
    "noise_from_residual",
    "outlier_events",
    "parameter_covariance",
    "parameter_drift",
    "parameter_intervals",
    "refusal",
    "root_mean_square",
    "standard_errors",
    "systematic_share",
    "with_numerical_term",
]
