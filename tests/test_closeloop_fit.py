"""The close loop's parameter fit (``fleetbrake.closeloop.leastsquares.fit_parameters``) on
event sets small enough to reason about: each evaluation is scored second by second against
the seconds of the starting point, whatever predictions a candidate drops (NaN in its
residual: the start's residual there)."""

from __future__ import annotations

import dataclasses
import datetime as dt

import numpy as np
import pytest

from fleetbrake.closeloop.candidates import Candidate
from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.errors import CloseLoopConfigError, CloseLoopError
from fleetbrake.closeloop.leastsquares import fit_parameters, forward_steps
from fleetbrake.closeloop.revision import refit_moved
from fleetbrake.model.effects import EFFECT_ORDER, EffectSet, HeatPartition

ALPHA_DECLARED = 0.7455
"""The reference block's declared heat partition (eqs. 9-12)."""

AMBIENT_C = 10.0


def _rise_k() -> np.ndarray:
    """A braking's temperature rise at the sensor: 120 s of heating, 480 s of cooling."""
    t = np.arange(600, dtype=np.float64)
    heating = 60.0 * (1.0 - np.exp(-np.minimum(t, 120.0) / 40.0))
    return np.where(t < 120.0, heating, heating * np.exp(-(t - 120.0) / 300.0))


class ThreeBrakings:
    """Three brakings of blocks whose heat partitions differ (``alphas``: a fleet the
    declared model with one :class:`HeatPartition` cannot fit exactly), measured with 0.05 K
    of noise. A candidate predicts ``AMBIENT_C`` + its flux factor x the declared rise. A
    candidate with ``alpha`` above ``drop_above`` cannot simulate the first braking: its
    predictions there are NaN. Seconds in event order, as the fit data's."""

    def __init__(self, alphas: tuple[float, ...], drop_above: float) -> None:
        rng = np.random.default_rng(5)
        self.drop_above = drop_above
        self.rise_k = _rise_k()
        t0 = dt.datetime(2024, 3, 4, 6)
        self.times = [
            [t0 + dt.timedelta(hours=k, seconds=s) for s in range(self.rise_k.size)]
            for k in range(len(alphas))
        ]
        self.measured = [
            AMBIENT_C
            + HeatPartition(alpha=alpha).flux_factor(ALPHA_DECLARED) * self.rise_k
            + rng.normal(0.0, 0.05, self.rise_k.size)
            for alpha in alphas
        ]

    def predicted(self, effects: EffectSet) -> np.ndarray:
        partition = effects.get("heat_partition")
        assert isinstance(partition, HeatPartition)
        one = AMBIENT_C + partition.flux_factor(ALPHA_DECLARED) * self.rise_k
        parts = [one.copy() for _ in self.measured]
        if partition.alpha > self.drop_above:
            parts[0][:] = np.nan
        return np.concatenate(parts)

    def residuals(self, effect_sets: list[EffectSet]) -> list[np.ndarray]:
        measured = np.concatenate(self.measured)
        return [measured - self.predicted(e) for e in effect_sets]

    def residual(self, effects: EffectSet) -> np.ndarray:
        r = self.residuals([effects])[0]
        return r[np.isfinite(r)]


def test_steps_are_scipys_forward_differences_turned_round_at_a_bound():
    from scipy.optimize._numdiff import approx_derivative

    x = np.array([0.5, -2.0, 0.99, 3.0])
    lo = np.array([0.0, -10.0, 0.0, 2.9])
    hi = np.array([1.0, 10.0, 1.0, 3.05])
    h = forward_steps(x, lo, hi, 0.05)
    np.testing.assert_allclose(h, [0.025, -0.1, -0.0495, -0.1], rtol=1e-12)
    # the same Jacobian as scipy's own 2-point scheme with these bounds
    a = np.array([[1.0, 2.0, 3.0, 4.0], [0.5, -1.0, 2.0, 0.0]])

    def f(v: np.ndarray) -> np.ndarray:
        return a @ v + 0.3 * v**2 @ np.ones((4, 2))

    mine = np.column_stack([(f(x + np.eye(4)[j] * h[j]) - f(x)) / h[j] for j in range(4)])
    theirs = approx_derivative(f, x, method="2-point", rel_step=0.05, bounds=(lo, hi))
    np.testing.assert_allclose(mine, theirs, rtol=1e-9)


def test_a_fit_whose_candidates_drop_a_braking_scores_them_on_the_right_seconds():
    """Brakings of alpha 0.70, 0.75 and 0.80; the fit starts at 0.75 (the middle of the
    effect's range), where every braking is simulated; above 0.76 the first one is dropped.
    Scored second by second against the start, a candidate above 0.76 keeps the start's
    residual on the dropped braking and is judged on the other two: the best is their least-
    squares alpha (0.775). Scored by position, the second and third brakings' residuals land
    on the first and second's seconds and the second's again on the third's (np.resize wraps
    round): the second counts twice, and the fit stops near 0.767."""
    brakings = ThreeBrakings(alphas=(0.70, 0.75, 0.80), drop_above=0.76)
    assert brakings.residual(EffectSet((HeatPartition(alpha=0.75),))).size == 1800
    assert brakings.residual(EffectSet((HeatPartition(alpha=0.77),))).size == 1200
    # least squares over the second and third brakings: the flux factor, then alpha
    rise = np.concatenate([brakings.rise_k] * 2)
    excess = np.concatenate(brakings.measured[1:]) - AMBIENT_C
    factor = float(excess @ rise / (rise @ rise))
    expected = 1.0 - factor * (1.0 - ALPHA_DECLARED)
    assert expected == pytest.approx(0.775, abs=0.002)

    fit = fit_parameters(brakings, EffectSet(), [HeatPartition], None, max_nfev=14)

    fitted = fit.effects.get("heat_partition")
    assert isinstance(fitted, HeatPartition)
    assert fitted.alpha == pytest.approx(expected, abs=1e-3)
    assert fit.residual.size == 1200  # the candidate's own residual: the brakings it simulates
    assert fit.aligned.size == 1800  # scored on the start's seconds
    assert fit.jacobian.shape == (1800, 1) and fit.names == ("heat_partition.alpha",)


def test_candidates_are_effects_of_the_vocabulary():
    holdout = dt.date(2024, 3, 6)
    chosen = CloseLoopConfig(holdout, candidates=("sensor_lag", "heat_partition"))
    assert [cls.name for cls in chosen.candidate_classes()] == ["heat_partition", "sensor_lag"]
    physical = [cls for cls in EFFECT_ORDER if not cls.fallback]
    assert len(CloseLoopConfig(holdout).candidate_classes()) == len(physical)
    with pytest.raises(CloseLoopConfigError, match=r"candidates: unknown effect.*heat_partitio\b"):
        CloseLoopConfig(holdout, candidates=("heat_partitio",))


class CountingBrakings(ThreeBrakings):
    """:class:`ThreeBrakings` that records the parameter of every simulation it is asked for."""

    def __init__(self, alphas: tuple[float, ...], drop_above: float) -> None:
        super().__init__(alphas, drop_above)
        self.simulated: list[float] = []

    def predicted(self, effects: EffectSet) -> np.ndarray:
        partition = effects.get("heat_partition")
        assert isinstance(partition, HeatPartition)
        self.simulated.append(partition.alpha)
        return super().predicted(effects)


def test_a_fit_simulates_each_parameter_vector_once():
    """The optimiser's first call (the starting point, already simulated for the reference
    seconds) and the fit's residual (its last accepted point) reuse what was simulated: every
    simulation of a fit is of a new parameter vector, and the residual returned is the one of
    the fitted effects."""
    brakings = CountingBrakings(alphas=(0.70, 0.75, 0.80), drop_above=0.76)

    fit = fit_parameters(brakings, EffectSet(), [HeatPartition], None, max_nfev=14)

    assert len(brakings.simulated) >= 3
    assert len(set(brakings.simulated)) == len(brakings.simulated), brakings.simulated
    assert fit.evaluations == len(brakings.simulated)
    np.testing.assert_array_equal(fit.residual, ThreeBrakings.residual(brakings, fit.effects))


def test_two_wild_events_are_left_out_and_change_neither_verdict_nor_parameter():
    """Forty brakings of one heat partition (0.72) measured with 0.05 K of noise; two of them
    carry data the flags did not catch (the reading 15 % of the rise too high). Fitted on
    everything, the wild pair biases alpha and leaves the fit far above the noise; the outlier
    rule picks exactly those two events from their residual RMS, and the fit on the kept
    events finds the truth and is judged adequate."""
    from fleetbrake.closeloop.stats import adequacy, event_rms, outlier_events

    brakings = ThreeBrakings(alphas=(0.72,) * 40, drop_above=1.0)
    for wild in (3, 11):
        brakings.measured[wild] = brakings.measured[wild] + 0.15 * brakings.rise_k
    event = np.repeat(np.arange(40), brakings.rise_k.size)
    noise_k = 0.05

    everything = fit_parameters(brakings, EffectSet(), [HeatPartition], None, max_nfev=14)
    rms = event_rms(brakings.residuals([everything.effects])[0], event, 40)
    outliers, threshold = outlier_events(rms, noise_k)
    assert sorted(outliers.tolist()) == [3, 11] and threshold >= 5 * noise_k
    kept = ~np.isin(event, outliers)
    robust = fit_parameters(brakings, EffectSet(), [HeatPartition], None, max_nfev=14, keep=kept)

    def alpha(fit) -> float:  # type: ignore[no-untyped-def]
        effect = fit.effects.get("heat_partition")
        assert isinstance(effect, HeatPartition)
        return float(effect.alpha)

    assert alpha(robust) == pytest.approx(0.72, abs=5e-4)
    assert abs(alpha(everything) - 0.72) > 5 * abs(alpha(robust) - 0.72)
    assert robust.aligned.size == kept.sum() == 38 * brakings.rise_k.size
    blocks = event  # one block per braking
    verdict = adequacy(robust.aligned, blocks[robust.scored], noise_k, {})
    assert verdict.adequate
    assert not adequacy(everything.aligned, blocks, noise_k, {}).adequate


def test_outlier_rule_leaves_nothing_out_of_a_uniform_misfit():
    """A model that misfits every event alike has no outlier: the bulk moves with it; and at
    most the worst ``max_fraction`` of the events are ever left out."""
    from fleetbrake.closeloop.stats import outlier_events

    rng = np.random.default_rng(3)
    misfit = 2.0 + 0.2 * rng.random(100)  # every event ~2 K off, noise 0.1 K
    assert outlier_events(misfit, 0.1)[0].size == 0
    bulk = 0.1 + 0.005 * rng.random(100)
    bulk[[7, 40, 41, 42, 43, 44, 45]] = [9.0, 3.0, 3.1, 3.2, 3.3, 3.4, 3.5]
    worst, _ = outlier_events(bulk, 0.1, max_fraction=0.05)
    assert worst.tolist() == [7, 45, 44, 43, 42]


def _chosen(fit) -> Candidate:  # type: ignore[no-untyped-def]
    return Candidate(fit.effects, float(np.sqrt(np.mean(fit.residual**2))), 0.0, 1, fitted=fit)


def test_a_refit_inside_the_fits_uncertainty_keeps_the_revision():
    """After re-flagging, the close loop refits the chosen effect on the events usable then and
    makes the revision again only when a parameter moved by more than ``refit_tolerance``
    times its 95 % interval's half-width. Forty brakings of alpha 0.72 (0.05 K of noise), two
    of them with data the flags missed (15 % of the rise too high): chosen on every event, the
    wild pair biases alpha, and the refit on the 38 clean events moves it far beyond its
    interval (made again); chosen on the 38 clean events, a refit on 36 of them (two good
    events more judged unusable) moves it by a fraction of its interval (kept)."""
    from fleetbrake.closeloop.stats import blocked_intervals

    brakings = ThreeBrakings(alphas=(0.72,) * 40, drop_above=1.0)
    for wild in (3, 11):
        brakings.measured[wild] = brakings.measured[wild] + 0.15 * brakings.rise_k
    event = np.repeat(np.arange(40), brakings.rise_k.size)

    def fit_without(*gone: int):  # type: ignore[no-untyped-def]
        keep = ~np.isin(event, gone)
        return fit_parameters(brakings, EffectSet(), [HeatPartition], None, max_nfev=14, keep=keep)

    def intervals(fit):  # type: ignore[no-untyped-def]
        return blocked_intervals(fit.jacobian, fit.aligned, fit.x, fit.names, event[fit.scored])

    everything, clean, fewer = fit_without(), fit_without(3, 11), fit_without(3, 11, 20, 30)
    lo, hi = intervals(clean).intervals["heat_partition.alpha"]
    half = 0.5 * (hi - lo)
    assert abs(everything.x[0] - clean.x[0]) > 2 * half
    assert refit_moved(_chosen(everything), clean, intervals(clean), 0.25) == [
        "heat_partition.alpha"
    ]
    assert 0 < abs(fewer.x[0] - clean.x[0]) < 0.25 * half
    assert refit_moved(_chosen(clean), fewer, intervals(fewer), 0.25) == []
    # the tolerance is a share of the interval: none at all makes every move count
    assert refit_moved(_chosen(clean), fewer, intervals(fewer), 0.0) == ["heat_partition.alpha"]


def test_a_refit_move_of_an_undetermined_parameter_or_a_new_one():
    """A parameter whose interval is unbounded (the data do not determine it) never counts
    as moved; one the chosen candidate lacks always does."""
    from fleetbrake.closeloop.stats import BlockedIntervals

    chosen = Candidate(EffectSet((HeatPartition(alpha=0.70),)), 0.1, 0.0, 1)
    refit = fit_parameters(ThreeBrakings((0.72,) * 3, 1.0), EffectSet(), [HeatPartition], None, 14)
    assert refit.x[0] != pytest.approx(0.70, abs=1e-3)
    unbounded = BlockedIntervals({"heat_partition.alpha": (-np.inf, np.inf)}, {}, {}, {}, 3, {})
    assert refit_moved(chosen, refit, unbounded, 0.25) == []
    assert refit_moved(Candidate(EffectSet(), 0.1, 0.0, 0), refit, unbounded, 0.25) == [
        "heat_partition.alpha"
    ]
    with pytest.raises(CloseLoopConfigError, match="refit_tolerance must be >= 0"):
        CloseLoopConfig(dt.date(2024, 3, 6), refit_tolerance=-0.1)
    with pytest.raises(CloseLoopConfigError, match="numerical_grid_ratios must each be > 1"):
        CloseLoopConfig(dt.date(2024, 3, 6), numerical_grid_ratios=(1.5, 0.5))
    assert (
        CloseLoopConfig(dt.date(2024, 3, 6), numerical_grid_ratios=()).numerical_grid_ratios == ()
    )


def test_a_refit_from_the_optimum_stops_at_the_fits_resolution_and_one_far_off_does_not():
    """The refits' stopping rule (``step_tolerance``): a refit started at the fitted
    parameters ends at its first trial step, before evaluating it, when that step is below
    0.1 standard errors (the Jacobian's at the start, on the effective sample size over the
    events as blocks): the start and the Jacobian's one vector, 2 evaluations, the start
    returned bit for bit. scipy's own stopping (``xtol`` 1e-8 relative) evaluates more steps
    of the same refit and moves the parameter by less than that tolerance. Started 10 standard
    errors away, the rule does not stop the refit: it goes to the optimum."""
    from fleetbrake.closeloop.stats import effective_sample_size, standard_errors

    brakings = ThreeBrakings(alphas=(0.70, 0.72, 0.74) * 8, drop_above=1.0)
    event = np.repeat(np.arange(24), brakings.rise_k.size)
    fitted = fit_parameters(brakings, EffectSet(), [HeatPartition], None, max_nfev=14)
    n_eff = effective_sample_size(fitted.aligned, event)
    sigma = float(standard_errors(fitted.jacobian, fitted.aligned, n_eff)[0])
    assert 0.0 < sigma < 0.01

    def refit_from(alpha: float, tolerance: float):  # type: ignore[no-untyped-def]
        start = (HeatPartition(alpha=alpha),)
        return fit_parameters(
            brakings, EffectSet(), [HeatPartition], start, 7, 0.05, None, tolerance, event
        )

    at_optimum = refit_from(fitted.x[0], 0.1)
    assert at_optimum.evaluations <= 2
    assert at_optimum.x[0] == fitted.x[0]
    np.testing.assert_array_equal(at_optimum.jacobian, refit_from(fitted.x[0], 0.0).jacobian)
    without_rule = refit_from(fitted.x[0], 0.0)
    assert without_rule.evaluations > 2
    assert abs(without_rule.x[0] - fitted.x[0]) < 0.1 * sigma

    far_off = refit_from(fitted.x[0] + 10.0 * sigma, 0.1)
    assert far_off.evaluations > 2
    assert abs(far_off.x[0] - fitted.x[0]) < 0.1 * sigma
    with pytest.raises(CloseLoopConfigError, match="refit_step_tolerance must be >= 0"):
        CloseLoopConfig(dt.date(2024, 3, 6), refit_step_tolerance=-0.1)


def test_brakings_over_a_frozen_gps_speed_are_left_out_of_thefit_parameters() -> None:
    """An event braking while the logged speed repeats one value to the last digit (a GPS
    that froze) has an unknown heat input: the close loop leaves it out of fit and holdout.
    A braking whose speed jitters as a live GPS does is kept, and so is a frozen speed with
    the brake released."""
    from types import SimpleNamespace

    from fleetbrake.closeloop.evidence import unknown_heat_events
    from fleetbrake.simulation.series import WagonSeries

    n = 600
    rng = np.random.default_rng(3)
    speed = 60.0 + rng.normal(0.0, 0.3, n)
    pressure = np.zeros(n)
    pressure[100:160] = 2.0  # event A: speed frozen over it
    speed[95:170] = 52.28
    pressure[300:360] = 2.0  # event B: live speed
    speed[450:520] = 41.0  # frozen speed, brake released: no event there
    pressure[530:560] = 1.5  # event C: after the frozen stretch ended
    series = WagonSeries(
        wagon_id="SGG-0001",
        t0=dt.datetime(2024, 3, 1),
        present=np.ones(n, dtype=bool),
        speed_kmh=speed,
        pressure_bar=pressure,
        ambient_c=np.full(n, 10.0),
        measured_c=np.full(n, 20.0),
        fault=np.zeros(n, dtype=bool),
        raw_c=np.full(n, np.nan),
        speed_raw_kmh=speed.copy(),
        events=[("A", 100, 160, True), ("B", 300, 360, True), ("C", 530, 560, True)],
    )
    loaded = {"SGG-0001": SimpleNamespace(spans=[series])}
    assert unknown_heat_events(loaded) == frozenset({"A"})  # type: ignore[arg-type]


class ThreeBrakingsMisread(ThreeBrakings):
    """:class:`ThreeBrakings` with the model driven by an input read ``misread`` times too
    large (the rise each candidate predicts scaled by it): an input's systematic error."""

    def __init__(self, alphas: tuple[float, ...], drop_above: float, misread: float) -> None:
        super().__init__(alphas, drop_above)
        self.misread = misread

    def predicted(self, effects: EffectSet) -> np.ndarray:
        return AMBIENT_C + self.misread * (super().predicted(effects) - AMBIENT_C)


def test_the_input_term_is_gauss_newton_steps_that_agree_with_the_refit():
    """The input term (``input_shift``): the chosen parameters' response to an input's
    systematic error by quasi-Newton steps from the fit's Jacobian, one evaluation of the
    residual with the input changed each, agrees with refitting with it changed. The heat
    partition's flux factor is nonlinear in alpha: an input read 1 % (5 %)
    wrong moves alpha by 0.0028 (0.0133), the first step (``gauss_newton_shift``, the linear
    sensitivity) is 1 % (5 %) off the refit's shift, the Broyden-updated steps (one
    parameter: the secant method) meet it to 1e-7 in 2 evaluations (the chord, ``J^T J`` every
    step: 0.01 % (0.25 %) in 2-3). A parameter on a bound the step would cross stays on it."""
    from fleetbrake.closeloop.leastsquares import effects_at, parameter_bounds
    from fleetbrake.closeloop.terms import gauss_newton_shift, input_shift

    brakings = ThreeBrakings((0.72, 0.70, 0.74), drop_above=1.0)
    fitted = fit_parameters(brakings, EffectSet(), [HeatPartition], None, max_nfev=14)
    lower, upper = parameter_bounds([HeatPartition])
    assert (lower, upper) == (pytest.approx([0.0]), pytest.approx([0.999]))
    for misread in (1.01, 0.99, 1.05, 0.95):
        moved = ThreeBrakingsMisread((0.72, 0.70, 0.74), 1.0, misread)
        refit = fit_parameters(
            moved, EffectSet(), [HeatPartition], list(fitted.effects), max_nfev=14
        )
        wanted = refit.x[0] - fitted.x[0]
        assert abs(wanted) > 2e-3
        first = gauss_newton_shift(fitted, moved.residuals([fitted.effects])[0], lower, upper)
        assert first[0] == pytest.approx(wanted, rel=1.5 * abs(misread - 1.0))
        shift, evaluations = input_shift(
            fitted,
            lambda x, moved=moved: moved.residuals(
                [effects_at(fitted.effects, [HeatPartition], x)]
            )[0],
            lower,
            upper,
        )
        assert shift[0] == pytest.approx(wanted, rel=1e-6) and evaluations <= 2
    # unchanged input, no shift
    same = gauss_newton_shift(fitted, brakings.residuals([fitted.effects])[0], lower, upper)
    assert same == pytest.approx([0.0], abs=1e-12)
    # the fitted alpha on its lower bound: a step down stays there, a step up is taken
    on_bound = dataclasses.replace(fitted, x=np.array([0.0]))

    def moved_along_jacobian(size: float) -> np.ndarray:  # a step of -size
        r = np.full(on_bound.scored.shape, np.nan)
        r[on_bound.scored] = on_bound.aligned + size * on_bound.jacobian[:, 0]
        return r

    assert gauss_newton_shift(on_bound, moved_along_jacobian(1e-3), lower, upper) == [0.0]
    up = gauss_newton_shift(on_bound, moved_along_jacobian(-1e-3), lower, upper)
    assert up == pytest.approx([1e-3], rel=1e-9)
    with pytest.raises(CloseLoopError, match="not the fit's events"):
        gauss_newton_shift(fitted, np.zeros(3), lower, upper)


def test_the_input_term_converges_where_the_fits_jacobian_overstates_the_response():
    """On the bench fleet the fit's Jacobian (a 5 % forward difference: a secant over a
    convection quantum) is 2-3 times the residual's response over the input term's small
    shift (a convection varying inside a piece is rounded, so on that scale the residual is a
    step function of the parameters), and the chord (``J^T J`` every step) contracts by only
    0.5-0.7 a step: 5 evaluations, 5 % short. Here a linear response ``S`` whose fit Jacobian
    is ``J = -S diag(2, 3.3)`` (the fit's normal equations hold for both): the shift the
    changed residual asks is known exactly, the chord's 5 steps miss it by 0.7^5 = 17 % in
    the second parameter, the Broyden-updated steps (:func:`input_shift`) meet it to 1e-6
    (exact after 2p updates on a linear response; 3 evaluations on the bench fleet)."""
    from fleetbrake.closeloop.leastsquares import FitResult
    from fleetbrake.closeloop.terms import input_shift

    rng = np.random.default_rng(11)
    t = np.linspace(0.0, 1.0, 600)
    response = np.column_stack([1.0 - np.exp(-t / 0.2), t * np.exp(-t / 0.5)])
    fit_residual = rng.normal(0.0, 0.05, t.size)
    fit_residual -= response @ np.linalg.lstsq(response, fit_residual, rcond=None)[0]
    x0 = np.array([2.0, 0.8])
    fitted = FitResult(
        effects=EffectSet(),
        residual=fit_residual,
        aligned=fit_residual,
        jacobian=-response * np.array([2.0, 3.3]),  # d residual / dx: measured - predicted
        x=x0,
        names=("law.a", "law.b"),
        evaluations=0,
        scored=np.ones(t.size, dtype=bool),
    )
    wanted = np.array([0.002, 0.005])

    def residual_at(x: np.ndarray) -> np.ndarray:  # the input changed: the optimum moves
        return fit_residual - response @ (x - x0 - wanted)

    lower, upper = np.array([0.0, 0.1]), np.array([50.0, 2.0])
    shift, evaluations = input_shift(fitted, residual_at, lower, upper)
    assert shift == pytest.approx(wanted, rel=1e-6) and evaluations <= 5
    # the chord: the fit's Jacobian every step
    x = x0.copy()
    jac = fitted.jacobian
    for _ in range(5):
        x -= np.linalg.solve(jac.T @ jac, jac.T @ (residual_at(x) - fit_residual))
    assert abs((x - x0)[1] / wanted[1] - 1.0) > 0.1
