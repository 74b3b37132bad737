"""The close loop's statistics (``fleetbrake.closeloop.stats``) on synthetic arrays whose
answers are known: white and AR(1) noise, a linear model with correlated noise, a smooth
leftover driven by a known input; and the typed report (``fleetbrake.closeloop.report``): its
JSON and the Markdown report's verdict line (``fleetbrake.closeloop.markdown``)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pytest

from fleetbrake.closeloop.candidates import HeldOut
from fleetbrake.closeloop.evidence import ResidualSummary
from fleetbrake.closeloop.fit import Outliers
from fleetbrake.closeloop.markdown import (
    MarkdownReport,
    ResidualPlots,
    plot_residual_by_phase,
    plot_residual_by_wagon,
    render_markdown,
    verdict_line,
)
from fleetbrake.closeloop.report import (
    AdequacyReport,
    CandidateReport,
    CloseLoopReport,
    EventSetFigures,
    IntervalMethods,
    UnknownHeat,
)
from fleetbrake.closeloop.stats import (
    EFFECT_NULLS,
    SelectionError,
    adequacy,
    block_folds,
    blocked_cv_rmse,
    blocked_intervals,
    circular_linear_correlation,
    combined_half_width,
    distinguishable_from_null,
    effective_sample_size,
    grid_convergence_index,
    held_out_residual,
    improves_held_out,
    information_criterion,
    intervals_for_json,
    noise_from_residual,
    parameter_intervals,
    refusal,
    systematic_share,
    with_numerical_term,
)
from fleetbrake.closeloop.terms import InputTerm, Numerical


def ar1(n: int, rho: float, rng: np.random.Generator, sigma: float = 1.0) -> np.ndarray:
    """A stationary AR(1) series with innovation scale ``sigma``."""
    e = rng.normal(scale=sigma, size=n)
    x = np.empty(n)
    x[0] = e[0] / np.sqrt(1.0 - rho * rho)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + e[i]
    return x


def blocked_ar1(n_blocks: int, length: int, rho: float, rng, sigma: float = 1.0) -> np.ndarray:
    return np.concatenate([ar1(length, rho, rng, sigma) for _ in range(n_blocks)])


# ---------------------------------------------------------------------------- n_eff
def test_white_noise_is_worth_every_second():
    rng = np.random.default_rng(0)
    blocks = np.repeat(np.arange(20), 2000)
    n_eff = effective_sample_size(rng.normal(size=blocks.size), blocks)
    assert n_eff == pytest.approx(blocks.size, rel=0.05)


@pytest.mark.parametrize("rho", [0.5, 0.95])
def test_ar1_is_worth_n_one_minus_rho_over_one_plus_rho(rho):
    rng = np.random.default_rng(1)
    blocks = np.repeat(np.arange(20), 3000)
    r = blocked_ar1(20, 3000, rho, rng)
    expected = blocks.size * (1 - rho) / (1 + rho)
    assert effective_sample_size(r, blocks) == pytest.approx(expected, rel=0.2)


def test_correlation_is_never_taken_across_blocks():
    """Blocks in any order, interleaved: the same n_eff as the blocks laid end to end; and a
    per-block offset (perfect correlation within a block) leaves about one sample per block."""
    rng = np.random.default_rng(2)
    blocks = np.repeat(np.arange(10), 1000)
    r = blocked_ar1(10, 1000, 0.9, rng)
    shuffled = rng.permutation(10)[blocks]
    interleaved = np.argsort(np.tile(np.arange(1000), 10), kind="stable")
    ordered = effective_sample_size(r, blocks)
    assert effective_sample_size(r, shuffled) == pytest.approx(ordered, rel=1e-9)
    assert effective_sample_size(r[interleaved], blocks[interleaved]) == pytest.approx(
        ordered, rel=1e-9
    )
    labels = np.array([f"SGG-{b:04d}/2026-11-0{b % 3}" for b in blocks], dtype=object)
    assert effective_sample_size(r, labels) == pytest.approx(ordered, rel=1e-9)
    offsets = np.repeat(rng.normal(size=10), 1000) + 1e-3 * rng.normal(size=10_000)
    assert 10 <= effective_sample_size(offsets, blocks) < 30


def test_criterion_on_fewer_samples_refuses_a_small_gain():
    """A 2 % cut of the mean square buys a parameter on 300 000 seconds, not on their n_eff."""
    rng = np.random.default_rng(3)
    r_a = rng.normal(size=300_000)
    r_b = r_a * np.sqrt(0.98)
    n = r_a.size
    assert information_criterion(r_b, 1, n) < information_criterion(r_a, 0, n)
    assert information_criterion(r_b, 1, 200.0) > information_criterion(r_a, 0, 200.0)


# ---------------------------------------------------------------------------- folds
def test_folds_hold_whole_blocks_and_cover_every_second_once():
    rng = np.random.default_rng(4)
    blocks = rng.permutation(np.repeat(np.arange(23), rng.integers(50, 400, size=23)))
    folds = block_folds(blocks, 5, seed=7)
    assert len(folds) == 5
    stacked = np.vstack(folds)
    assert (stacked.sum(axis=0) == 1).all()
    for mask in folds:
        assert mask.any()
        inside = set(blocks[mask].tolist())
        assert not inside & set(blocks[~mask].tolist())
    sizes = stacked.sum(axis=1)
    assert sizes.max() < 1.5 * sizes.min()
    again = block_folds(blocks, 5, seed=7)
    assert all((a == b).all() for a, b in zip(folds, again, strict=True))
    assert len(block_folds(blocks, 50)) == 23
    with pytest.raises(SelectionError, match="2 blocks"):
        block_folds(np.zeros(100, dtype=int), 5)


def linear_case(rng, n_blocks=12, length=400, rho=0.9, sigma=0.05):
    """y = 1 + 0.3 x1 + correlated noise; x1 a slow driver, x2 an unrelated slow input."""
    blocks = np.repeat(np.arange(n_blocks), length)
    t = np.tile(np.arange(length), n_blocks)
    phase = np.repeat(rng.uniform(0, 2 * np.pi, size=n_blocks), length)
    x1 = np.sin(2 * np.pi * t / length + phase)
    x2 = np.cos(2 * np.pi * t / (0.7 * length) + 2 * phase)
    y = 1.0 + 0.3 * x1 + blocked_ar1(n_blocks, length, rho, rng, sigma)
    return blocks, x1, x2, y


def ls_fit(design: np.ndarray, y: np.ndarray, train: np.ndarray | None = None):
    """Residual y - X b (every second) and its Jacobian -X, b fitted on ``train``."""
    use = np.ones(y.size, dtype=bool) if train is None else train
    b = np.linalg.lstsq(design[use], y[use], rcond=None)[0]
    return y - design @ b, -design, b


def test_held_out_residual_is_exact_for_a_linear_model():
    rng = np.random.default_rng(5)
    blocks, x1, _, y = linear_case(rng)
    design = np.column_stack([np.ones_like(x1), x1])
    folds = block_folds(blocks, 4, seed=1)
    r, jac, _ = ls_fit(design, y)
    held = held_out_residual(r, jac, folds)
    refit = blocked_cv_rmse(lambda train: ls_fit(design, y, train)[0], folds)
    assert np.sqrt(np.mean(held**2)) == pytest.approx(refit, rel=1e-9)
    for mask in folds:
        assert held[mask] == pytest.approx(ls_fit(design, y, ~mask)[0][mask], abs=1e-10)
    # held out, a fit does worse than on the seconds it saw
    assert np.mean(held**2) > np.mean(r**2)


def test_a_real_driver_improves_the_held_out_blocks_a_spurious_one_does_not():
    rng = np.random.default_rng(6)
    blocks, x1, x2, y = linear_case(rng)
    ones = np.ones_like(x1)
    folds = block_folds(blocks, 5)
    r_a, j_a, _ = ls_fit(ones[:, None], y)
    r_b, j_b, _ = ls_fit(np.column_stack([ones, x1]), y)
    r_c, j_c, _ = ls_fit(np.column_stack([ones, x1, x2]), y)
    real = improves_held_out(r_a, j_a, r_b, j_b, folds, margin=0.05)
    assert real.improves and real.gain > 0.5 and real.folds_improved == 5
    spurious = improves_held_out(r_b, j_b, r_c, j_c, folds, margin=0.05)
    assert not spurious.improves, spurious.describe()
    assert spurious.gain < 0.05
    # the fit RMSE alone would always prefer the richer model
    assert np.mean(r_c**2) < np.mean(r_b**2)


# ---------------------------------------------------------------------------- intervals
def test_intervals_cover_the_truth_with_correlated_noise_and_ols_would_not():
    rng = np.random.default_rng(7)
    n_blocks, length, rho = 10, 600, 0.95
    blocks = np.repeat(np.arange(n_blocks), length)
    t = np.tile(np.arange(length), n_blocks)
    design = np.column_stack(
        [
            np.ones(blocks.size),
            np.sin(2 * np.pi * t / length) + 0.3 * np.repeat(rng.normal(size=n_blocks), length),
        ]
    )
    beta = np.array([1.0, 0.5])
    draws = 200
    covered = np.zeros(2)
    covered_ols = np.zeros(2)
    for _ in range(draws):
        y = design @ beta + blocked_ar1(n_blocks, length, rho, rng, 0.1)
        r, jac, b = ls_fit(design, y)
        n_eff = effective_sample_size(r, blocks)
        ours = parameter_intervals(jac, r, b, ["a", "b"], n_eff)
        ols = parameter_intervals(jac, r, b, ["a", "b"], float(r.size))
        covered += [ours[k][0] <= v <= ours[k][1] for k, v in zip("ab", beta, strict=True)]
        covered_ols += [ols[k][0] <= v <= ols[k][1] for k, v in zip("ab", beta, strict=True)]
    assert ((covered / draws > 0.88) & (covered / draws < 0.995)).all(), covered / draws
    assert (covered_ols / draws < 0.5).all(), covered_ols / draws


def test_distinguishable_from_null():
    intervals = {"scale": (0.2, 0.6), "exponent": (-0.1, 0.4)}
    assert distinguishable_from_null(intervals, {"scale": 0.0})
    assert not distinguishable_from_null(intervals, {"scale": 0.0, "exponent": 0.0})
    assert not distinguishable_from_null(intervals, {"lag_s": 0.0})
    assert distinguishable_from_null(intervals, {})


def perturbed_blocks(rng, n_blocks=12, length=2000, rho=0.5, sigma=0.1, spread=0.0075):
    """A linear model whose parameters move from block to block (``truth`` + N(0, spread)
    per block: the best parameters of a reduced model differ from one wagon-day to the next)
    with AR(1) noise: (J, residual at the least-squares fit, x, blocks, truth)."""
    from scipy.signal import lfilter

    truth = np.array([1.0, 2.0])
    t = np.linspace(0.0, 1.0, length)
    xs, ys = [], []
    for _ in range(n_blocks):
        x = np.column_stack(
            [
                np.sin(2 * np.pi * t * rng.uniform(0.5, 1.5) + rng.uniform(0, 6)) + 1.5,
                t * rng.uniform(0.5, 2.0),
            ]
        )
        innovations = rng.normal(scale=sigma * np.sqrt(1 - rho * rho), size=length)
        noise = lfilter([1.0], [1.0, -rho], innovations)
        xs.append(x)
        ys.append(x @ (truth + rng.normal(scale=spread, size=2)) + noise)
    jac, y = np.vstack(xs), np.concatenate(ys)
    fitted = np.linalg.lstsq(jac, y, rcond=None)[0]
    blocks = np.repeat(np.arange(n_blocks), length)
    return jac, jac @ fitted - y, fitted, blocks, truth


def test_blocked_intervals_cover_block_wise_parameters_the_jacobian_misses():
    # the parameters move a little from block to block (less than the noise shows): the
    # n_eff Jacobian interval sees only the noise and misses the mean; the reported interval
    # (widest of Jacobian, cluster-robust, delete-one-block jackknife, t on blocks - 1)
    # covers it
    rng = np.random.default_rng(7)
    draws, reported, jacobian = 80, 0, 0
    for _ in range(draws):
        jac, r, x, blocks, truth = perturbed_blocks(rng)
        out = blocked_intervals(jac, r, x, ["a", "b"], blocks)
        assert out.blocks == 12
        for i, name in enumerate(("a", "b")):
            lo, hi = out.intervals[name]
            reported += lo <= truth[i] <= hi
            lo, hi = out.jacobian[name]
            jacobian += lo <= truth[i] <= hi
            # the reported interval is the widest of the three
            widths = [hi - lo for lo, hi in (out.jacobian[name], out.sandwich[name])]
            widths.append(out.jackknife[name][1] - out.jackknife[name][0])
            assert out.intervals[name][1] - out.intervals[name][0] == pytest.approx(max(widths))
    assert 0.88 <= reported / (2 * draws) <= 1.0
    assert jacobian / (2 * draws) < 0.8


def test_blocked_intervals_jackknife_step_is_the_refit_without_the_block():
    # for a linear model one Gauss-Newton step from the optimum is the refit without a block:
    # the jackknife's spread equals the one of refitting G times
    from scipy.stats import t as student_t

    rng = np.random.default_rng(3)
    jac, r, x, blocks, _ = perturbed_blocks(rng, n_blocks=6, length=300, spread=0.05)
    y = jac @ x - r
    refits = np.array(
        [np.linalg.lstsq(jac[blocks != g], y[blocks != g], rcond=None)[0] for g in range(6)]
    )
    var = 5 / 6 * ((refits - refits.mean(axis=0)) ** 2).sum(axis=0)
    half = float(student_t.ppf(0.975, 5)) * np.sqrt(var)
    out = blocked_intervals(jac, r, x, ["a", "b"], blocks)
    for i, name in enumerate(("a", "b")):
        assert out.jackknife[name] == pytest.approx((x[i] - half[i], x[i] + half[i]), rel=1e-9)


def test_blocked_intervals_with_two_blocks_are_the_jacobian_ones():
    rng = np.random.default_rng(4)
    jac, r, x, blocks, _ = perturbed_blocks(rng, n_blocks=2, length=300)
    out = blocked_intervals(jac, r, x, ["a", "b"], blocks)
    assert out.sandwich == {} and out.jackknife == {}
    assert out.intervals == out.jacobian
    assert set(out.method.values()) == {"jacobian"}


def fitted_time_constant(step_s: float, data_t: np.ndarray, data_y: np.ndarray) -> float:
    """tau fitted to a decay through the trapezoidal (Crank-Nicolson) rule with time step
    ``step_s`` (a second-order scheme; the data's times are on its grid)."""
    from scipy.optimize import least_squares

    steps = np.rint(data_t / step_s)

    def model(tau: float) -> np.ndarray:
        growth = (1.0 - step_s / (2.0 * tau)) / (1.0 + step_s / (2.0 * tau))
        return np.asarray(growth**steps)

    fit = least_squares(lambda x: model(float(x[0])) - data_y, [50.0], xtol=1e-14, ftol=1e-14)
    return float(fit.x[0])


def test_grid_convergence_index_bounds_a_discretisation_bias_and_is_not_useless():
    # a decay written exactly (the world), its time constant fitted through a second-order
    # scheme: biased by the scheme. The GCI of the fits with steps h and 2h (order 2, safety
    # factor 3) covers the bias at h, and is not more than a few times it
    for tau, fine_step in ((40.0, 8.0), (90.0, 12.0), (25.0, 5.0)):
        t = np.arange(0.0, 6.0 * tau, 2.0 * fine_step)
        y = np.exp(-t / tau)
        fine = fitted_time_constant(fine_step, t, y)
        coarse = fitted_time_constant(2.0 * fine_step, t, y)
        (gci,) = grid_convergence_index(np.array([fine]), np.array([coarse]), 2.0)
        error = abs(fine - tau)
        assert error > 1e-3 * tau, (tau, fine)  # a real bias to bound
        assert error <= gci <= 5.0 * error, (tau, fine, coarse, gci)


def test_grid_convergence_index_is_roaches_formula():
    got = grid_convergence_index(np.array([1.0, 2.0]), np.array([1.1, 1.5]), 1.5, 2.0, 3.0)
    assert got == pytest.approx([3.0 * 0.1 / 1.25, 3.0 * 0.5 / 1.25])
    with pytest.raises(SelectionError, match="ratio"):
        grid_convergence_index(np.array([1.0]), np.array([1.1]), 1.0)
    with pytest.raises(SelectionError, match="coarse"):
        grid_convergence_index(np.array([1.0]), np.array([1.1, 1.2]), 2.0)


def test_numerical_term_is_added_in_quadrature_about_the_estimate():
    intervals = {"a": (0.7, 1.3), "b": (1.0, 3.0), "c": (-np.inf, np.inf), "d": (4.0, 6.0)}
    x = {"a": 1.0, "b": 2.0, "c": 0.0, "d": 5.0}
    out = with_numerical_term(intervals, x, {"a": 0.4, "b": 0.0, "c": 1.0})
    assert out["a"] == pytest.approx((0.5, 1.5))  # hypot(0.3, 0.4) = 0.5
    assert out["b"] == (1.0, 3.0)  # no term: unchanged
    assert out["c"] == (-np.inf, np.inf)  # unbounded stays so
    assert out["d"] == (4.0, 6.0)  # not given: unchanged


def test_numerical_and_input_terms_combine_in_quadrature():
    out = combined_half_width([{"a": 0.3, "b": 0.0}, {"a": 0.4, "c": 2.0}])
    assert out == pytest.approx({"a": 0.5, "b": 0.0, "c": 2.0})
    assert list(out) == ["a", "b", "c"]  # in the order first named
    assert combined_half_width([]) == {}


def test_effect_nulls_name_real_laws_and_parameters():
    from fleetbrake.model.effects import EFFECT_ORDER

    laws = {f"{cls.name}[{cls.law}]": cls for cls in EFFECT_ORDER}
    for label, nulls in EFFECT_NULLS.items():
        assert label in laws, label
        assert set(nulls) <= set(laws[label].PARAMETER_RANGES), label
        for name, null in nulls.items():
            lo, hi = laws[label].LIMITS.get(name, (None, None))
            assert (lo is None or lo <= null) and (hi is None or null <= hi), (label, name)


def test_distinguishable_from_null_any_of():
    intervals = {"a": (-0.1, 0.1), "b": (0.2, 0.3)}
    nulls = {"a": 0.0, "b": 0.0}
    assert not distinguishable_from_null(intervals, nulls)
    assert distinguishable_from_null(intervals, nulls, any_of=True)
    assert not distinguishable_from_null({"a": (-0.1, 0.1)}, {"a": 0.0}, any_of=True)


def test_an_undetermined_parameter_has_an_unbounded_interval():
    rng = np.random.default_rng(8)
    r = rng.normal(size=200)
    jac = np.column_stack([np.ones(200), np.ones(200)])
    out = parameter_intervals(jac, r, np.array([1.0, 2.0]), ["a", "b"], 200.0)
    assert not distinguishable_from_null(out, {"a": 0.0})
    assert intervals_for_json(out) == {"a": [None, None], "b": [None, None]}
    assert intervals_for_json({"a": (0.123456789, 2.0)}) == {"a": [0.123457, 2.0]}


def test_refusal_says_why_a_candidate_does_not_enter():
    rng = np.random.default_rng(12)
    blocks, x1, x2, y = linear_case(rng)
    ones = np.ones_like(x1)
    folds = block_folds(blocks, 5)
    r_b, j_b, b_b = ls_fit(np.column_stack([ones, x1]), y)
    r_c, j_c, b_c = ls_fit(np.column_stack([ones, x1, x2]), y)
    n_eff = effective_sample_size(r_c, blocks)
    names = ["level", "gain", "spurious"]
    intervals = parameter_intervals(j_c, r_c, b_c, names, n_eff)
    why = refusal(improves_held_out(r_b, j_b, r_c, j_c, folds), intervals, {"spurious": 0.0})
    assert why is not None
    assert "held-out RMSE" in why and "spurious = 0 within" in why
    r_a, j_a, _ = ls_fit(ones[:, None], y)
    good = parameter_intervals(j_b, r_b, b_b, names[:2], effective_sample_size(r_b, blocks))
    assert refusal(improves_held_out(r_a, j_a, r_b, j_b, folds), good, {"gain": 0.0}) is None


# ---------------------------------------------------------------------------- noise
def test_noise_from_residual_ignores_a_smooth_model_error_and_its_turns():
    rng = np.random.default_rng(9)
    blocks = np.repeat(np.arange(30), 1200)
    t = np.tile(np.arange(1200.0), 30)
    smooth = 1.5 * np.sin(t / 80.0) + np.where(t > 300, 0.02 * (t - 300), 0.0)  # a kink
    r = 0.1 * rng.normal(size=t.size) + smooth
    assert noise_from_residual(r, blocks) == pytest.approx(0.1, rel=0.05)
    # a gap in time is not a step: with the times given, the jump across it is not counted
    jumpy = r.copy()
    jumpy[t >= 600] += 5.0
    t_gap = np.where(t >= 600, t + 3600.0, t)
    assert noise_from_residual(jumpy, blocks, t_gap) == pytest.approx(0.1, rel=0.05)
    # today's estimate, std(diff) / sqrt(2), is pulled up by the model error's slope
    assert np.std(np.diff(r)) / np.sqrt(2) > 0.11


# ---------------------------------------------------------------------------- adequacy
def test_white_noise_at_the_noise_level_is_adequate():
    rng = np.random.default_rng(10)
    blocks = np.repeat(np.arange(20), 1500)
    r = 0.1 * rng.normal(size=blocks.size)
    speed = np.abs(np.tile(np.sin(np.arange(1500) / 200.0), 20)) * 100
    noise = noise_from_residual(r, blocks)
    out = adequacy(r, blocks, noise, {"speed": speed}, before_rmse_k=0.8, effect="sensor_lag")
    assert out.adequate and out.unexplained is None
    assert out.ratio == pytest.approx(1.0, abs=0.1)
    assert out.whiteness > 0.8
    assert out.explained_fraction == pytest.approx(1 - (out.rmse_k / 0.8) ** 2)
    assert abs(out.correlations["speed"]) < 0.05


def test_a_smooth_leftover_is_not_adequate_and_names_its_driver():
    rng = np.random.default_rng(11)
    blocks = np.repeat(np.arange(20), 1500)
    t = np.tile(np.arange(1500.0), 20)
    speed = 60 + 50 * np.sin(t / 150.0 + np.repeat(rng.uniform(0, 6, 20), 1500))
    hour = (t / 3600.0 + np.repeat(rng.uniform(0, 24, 20), 1500)) % 24
    r = 0.1 * rng.normal(size=t.size) + 0.02 * (speed - 60)  # ~0.7 K rms leftover
    noise = noise_from_residual(r, blocks)
    assert noise == pytest.approx(0.1, rel=0.1)
    out = adequacy(
        r,
        blocks,
        noise,
        {"speed": speed, "hour of day": hour},
        before_rmse_k=2.0,
        effect="friction_speed",
    )
    assert not out.adequate
    assert out.ratio > 1.5
    assert out.whiteness < 0.2
    assert out.correlations["speed"] > 0.9
    assert out.unexplained is not None
    assert out.unexplained.startswith("partly explained: friction_speed explains 8")
    assert "correlated with speed (r = +0.99)" in out.unexplained
    assert "hour of day" not in out.unexplained
    nothing = adequacy(r, blocks, noise, {"speed": speed})
    assert nothing.unexplained is not None and nothing.unexplained.startswith("not explained")


def test_a_noon_bump_correlates_with_the_hour_of_day_on_its_circle_not_on_a_line():
    """Sunshine peaking at noon: next to no Pearson correlation with the hour counted from
    midnight, a strong circular-linear one; the verdict names the hour of day."""
    rng = np.random.default_rng(12)
    blocks = np.repeat(np.arange(20), 3000)
    hour = (
        np.tile(np.arange(3000.0), 20) * 8.0 / 3600.0 + np.repeat(np.arange(20) * 7.0, 3000)
    ) % 24
    sun = np.maximum(np.cos(2 * np.pi * (hour - 12.0) / 24.0), 0.0)
    r = 0.1 * rng.normal(size=hour.size) + 0.5 * sun
    assert abs(np.corrcoef(r, hour)[0, 1]) < 0.1
    circular = circular_linear_correlation(r, hour, 24.0)
    assert circular is not None and circular > 0.8
    # the same bump shifted to any hour correlates as strongly; noise alone does not
    shifted = circular_linear_correlation(r, (hour + 5.0) % 24, 24.0)
    assert shifted == pytest.approx(circular, abs=1e-9)
    noise_only = circular_linear_correlation(0.1 * rng.normal(size=hour.size), hour, 24.0)
    assert noise_only is not None and noise_only < 0.05
    ambient = 10 + 0.2 * rng.normal(size=hour.size)
    out = adequacy(
        r,
        blocks,
        0.1,
        {"ambient": ambient, "hour of day": hour},
        periods={"hour of day": 24.0},
    )
    assert not out.adequate
    assert out.correlations["hour of day"] == pytest.approx(circular)
    assert out.unexplained is not None and "correlated with hour of day" in out.unexplained
    linear = adequacy(r, blocks, 0.1, {"ambient": ambient, "hour of day": hour})
    assert linear.unexplained is not None and "hour of day" not in linear.unexplained


def test_systematic_share_does_not_count_the_noise_as_left():
    # 2 K of misfit over 0.1 K of noise cut to the noise: all of it explained
    assert systematic_share(2.0, 0.1, 0.1) == pytest.approx(1.0)
    assert systematic_share(2.0, 0.09, 0.1) == pytest.approx(1.0)
    # the hour-of-day fleet's proxy: 0.297 -> 0.239 K over 0.101 K of noise explains 40 %,
    # less than the plain explained fraction (35 % of the mean square would read the same)
    share = systematic_share(0.297, 0.239, 0.101)
    assert share == pytest.approx(1 - (0.239**2 - 0.101**2) / (0.297**2 - 0.101**2))
    assert 0.35 < share < 0.45
    # an effect that explains most of a large misfit but leaves 1.2 K: dominant
    assert systematic_share(7.5, 1.2, 0.1) > 0.9
    assert systematic_share(0.1, 0.1, 0.1) == 1.0  # nothing systematic before
    assert systematic_share(0.3, 0.4, 0.1) < 0.0  # made worse


# ---------------------------------------------------------------------------- report
def typed_report(**changes: Any) -> CloseLoopReport:
    """A report of an added convection, adequate, with ``changes``."""
    report = CloseLoopReport(
        baseline_revision="declared",
        new_revision="r1-convection_speed",
        effect="convection_speed",
        parameters={"h_speed": 1.2},
        evidence="residual correlates with speed",
        fit=EventSetFigures(40, 1.31, 0.118, 44, 1.5, 0.5),
        holdout=EventSetFigures(10, 1.40, 0.121, 12, 1.6, 0.6),
        candidates=[
            CandidateReport(
                effect="convection_speed",
                label="convection_speed",
                parameters={"convection_speed": {"h_speed": 1.2}},
                rmse_fit_k=0.118,
                rmse_holdout_k=0.121,
                score=310.5,
                fitted_on="fit",
                held_out=None,
                refused=None,
            )
        ],
        noise_k=0.1,
        flags_judged_with="r1-convection_speed",
        solver="rom",
        residual=ResidualSummary(100),
        n_eff=30.0,
        selection="blocked cross-validation",
        exclusion="flagged events",
        outliers=Outliers(events=0),
        unknown_heat=UnknownHeat(0, []),
        effects=None,
        interval_methods=None,
        parameter_intervals={"h_speed": [1.1, 1.3]},
        adequate=True,
        unexplained=None,
        adequacy=AdequacyReport(0.118, 1.18, 0.9, 0.99, {}),
    )
    return dataclasses.replace(report, **changes)


def methods(numerical: float | None = None, inputs: float | None = None) -> IntervalMethods:
    """Interval methods naming the jackknife as the widest, with the terms' half-widths."""
    return IntervalMethods(
        blocks=4,
        widest={"h_speed": "jackknife"},
        jacobian={},
        sandwich={},
        jackknife={},
        statistical={},
        numerical=None
        if numerical is None
        else Numerical(0.6, [], 2.0, 3.0, {"h_speed": numerical}),
        inputs=None if inputs is None else InputTerm(0.3, {"h_speed": 1.2}, {"h_speed": inputs}, 2),
    )


def test_report_first_line_is_the_verdict():
    found = render_markdown(typed_report()).splitlines()
    assert found[0].startswith("found: convection_speed")
    assert "| h_speed | 1.2 | 1.1 | 1.3 | - | - | - |" in found
    # the statistical method and the numerical term beside the reported interval
    with_term = render_markdown(typed_report(interval_methods=methods(0.05))).splitlines()
    assert "| h_speed | 1.2 | 1.1 | 1.3 | jackknife | 0.05 | - |" in with_term
    assert any("adequate" in line and "yes" in line for line in found)
    partly = (
        "partly explained: friction_speed explains 76 % of the residual; 1.2 K remains "
        "against 0.1 K of sensor noise, correlated with speed (r = +0.41)"
    )
    text = render_markdown(
        typed_report(adequate=False, unexplained=partly, effect="friction_speed")
    )
    assert text.splitlines()[0] == partly
    assert "| adequate | no |" in text
    nothing = typed_report(new_revision=None, effect=None, parameters={}, parameter_intervals={})
    assert verdict_line(nothing).startswith("nothing added")
    assert verdict_line(nothing).endswith("the baseline revision is adequate")
    assert render_markdown(nothing).splitlines()[0].startswith("nothing added")


def test_the_report_serialises_to_the_contracts_keys():
    """``to_dict`` gives interface.md's keys in its order, the optional sections only when
    there is something in them, and a JSON round trip of it."""
    data = typed_report().to_dict()
    contract = [
        "baseline_revision",
        "new_revision",
        "effect",
        "parameters",
        "evidence",
        "fit",
        "holdout",
        "candidates",
    ]
    assert list(data)[: len(contract)] == contract
    for key in ("parameter_intervals", "noise_k", "adequate", "unexplained"):
        assert key in data
    assert list(data["fit"]) == [
        "events",
        "rmse_before_k",
        "rmse_after_k",
        "events_all",
        "rmse_before_all_k",
        "rmse_after_all_k",
    ]
    assert list(data["candidates"][0])[:2] == ["effect", "label"]
    assert "effects" not in data and "interval_methods" not in data and "cost" not in data
    assert data["outliers"] == {"events": 0} and data["residual"] == {"seconds": 100}
    with_terms = typed_report(interval_methods=methods(0.05, -0.04)).to_dict()
    terms = with_terms["interval_methods"]
    assert terms["numerical"]["half_width"] == {"h_speed": 0.05}
    assert terms["input"]["half_width"] == {"h_speed": 0.04}
    assert json.loads(json.dumps(with_terms)) == with_terms


def test_the_residual_plots_drawn_on_a_worker_are_those_drawn_here(tmp_path: Path) -> None:
    """``close-loop`` draws the report's plots on one of its engine's workers (while the
    warehouse closes): the residuals cross to it as an Arrow table (one large enough to be
    shipped as a file) and the images are the bytes drawn in this process; the report's
    text is written, and links them."""
    from fleetbrake.engine import LocalEngine
    from fleetbrake.engine.local import SHIPPED_MIN_BYTES

    rng = np.random.default_rng(11)
    n = 60_000
    frame = pl.DataFrame(
        {
            "wagon_id": rng.choice(["W-3", "W-1", "W-2"], n),
            "model_revision": np.repeat(["declared", "r1-convection_speed"], n // 2),
            "phase": rng.choice(["heating", "cooling"], n),
            "residual_k": rng.normal(-1.0, 2.0, n),
        }
    )
    assert frame.to_arrow().nbytes >= SHIPPED_MIN_BYTES

    def plots(name: str) -> ResidualPlots:
        return ResidualPlots(
            frame.to_arrow(), tmp_path / f"{name}-by-wagon.png", tmp_path / f"{name}-by-phase.png"
        )

    here, there = plots("here"), plots("there")
    plot_residual_by_wagon(frame, here.by_wagon)
    plot_residual_by_phase(frame, here.by_phase)
    text = render_markdown(typed_report(), there)
    with LocalEngine(1) as engine:
        MarkdownReport(tmp_path / "there.md", text, there).write(engine)
    for drawn, reference in ((there.by_wagon, here.by_wagon), (there.by_phase, here.by_phase)):
        assert drawn.read_bytes() == reference.read_bytes(), drawn.name
    written = (tmp_path / "there.md").read_text(encoding="utf-8")
    assert written == text
    assert "](there-by-wagon.png)" in written and "](there-by-phase.png)" in written
    assert "png" not in render_markdown(typed_report())


def test_report_names_the_law_the_refusals_and_the_figure_judged():
    flat = CandidateReport(
        effect="convection_speed",
        label="convection_speed[flat_plate]",
        parameters={"convection_speed": {"multiplier": 0.4}},
        rmse_fit_k=0.5,
        rmse_holdout_k=0.6,
        score=12.0,
        fitted_on="fit",
        held_out=HeldOut("none", 0.5, 0.495, 0.01, 0.05, 2, 5),
        refused="held-out RMSE 0.5 -> 0.495 K (+1.0 %, margin 5 %), better on 2 of 5 folds",
    )
    report = typed_report(
        candidates=[*typed_report().candidates, flat],
        outliers=Outliers(events=2),
        adequacy=AdequacyReport(
            0.105,
            1.05,
            0.9,
            0.99,
            {},
            rmse_judged_k=0.105,
            judged_on="v_predictions less 2 outlier events",
            max_ratio=1.5,
        ),
        parameter_intervals={"h_speed": [1.1, 1.3]},
        interval_methods=methods(0.03, 0.04),
    )
    text = render_markdown(report)
    first = text.splitlines()[0]
    # the verdict shows the figure it was judged on beside the report's fit RMSE
    assert first.startswith("found: convection_speed (fit RMSE 1.31 -> 0.118 K, 0.105 K without 2")
    assert "| convection_speed[flat_plate] | 12.0 |" in text
    assert "+1.0 % | held-out RMSE 0.5 -> 0.495 K" in text
    assert "| h_speed | 1.2 | 1.1 | 1.3 | jackknife | 0.03 | 0.04 |" in text
    assert "ratio 1.05 (adequate at most 1.5)" in text
