"""The close loop's parameter fit (``fleetbrake.closeloop.loop._fit``) on event sets small
enough to reason about: each evaluation is scored second by second against the seconds of the
starting point, matched by (event, second), whatever predictions a candidate drops."""

from __future__ import annotations

import datetime as dt

import numpy as np
import polars as pl
import pytest

from fleetbrake.closeloop.loop import (
    CloseLoopConfig,
    CloseLoopConfigError,
    _aligned,
    _fit,
    _keyed_residual,
)
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
    predictions there are dropped. Rows come out in event order, as the evaluator's do."""

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

    def frames(self, effects: EffectSet) -> pl.DataFrame:
        partition = effects.get("heat_partition")
        assert isinstance(partition, HeatPartition)
        predicted = AMBIENT_C + partition.flux_factor(ALPHA_DECLARED) * self.rise_k
        parts = [
            pl.DataFrame(
                {
                    "event_id": f"E{k}",
                    "time_utc": pl.Series(times, dtype=pl.Datetime("us")),
                    "measured_sensor_c": measured,
                    "predicted_sensor_c": predicted,
                }
            )
            for k, (times, measured) in enumerate(zip(self.times, self.measured, strict=True))
            if not (k == 0 and partition.alpha > self.drop_above)
        ]
        return pl.concat(parts)

    def residual(self, effects: EffectSet) -> np.ndarray:
        return np.asarray(_keyed_residual(self.frames(effects))["residual_k"], dtype=np.float64)


def test_aligned_matches_seconds_by_key_and_keeps_the_reference_where_one_is_dropped():
    keys = {"event_id": ["A", "A", "B"], "time_utc": [1, 2, 1]}
    reference = pl.DataFrame({**keys, "residual_k": [0.1, 0.2, 0.3]})
    # the candidate lost ("A", 2), gained ("B", 2), and lists its seconds in another order
    candidate = pl.DataFrame(
        {"event_id": ["B", "B", "A"], "time_utc": [2, 1, 1], "residual_k": [9.0, -0.3, -0.1]}
    )
    np.testing.assert_array_equal(_aligned(reference, candidate), [-0.1, 0.2, -0.3])


def test_a_fit_whose_candidates_drop_a_braking_scores_them_on_the_right_seconds():
    """Brakings of alpha 0.70, 0.75 and 0.80; the fit starts at 0.75 (the middle of the
    effect's range), where every braking is simulated; above 0.76 the first one is dropped.
    Scored second by second against the start, a candidate above 0.76 keeps the start's
    residual on the dropped braking and is judged on the other two: the best is their least-
    squares alpha (0.775). Scored by position, the second and third brakings' residuals land
    on the first and second's seconds and the second's again on the third's (np.resize wraps
    round): the second counts twice, and the fit stops near 0.767."""
    brakings = ThreeBrakings(alphas=(0.70, 0.75, 0.80), drop_above=0.76)
    assert brakings.frames(EffectSet((HeatPartition(alpha=0.75),))).height == 1800
    assert brakings.frames(EffectSet((HeatPartition(alpha=0.77),))).height == 1200
    # least squares over the second and third brakings: the flux factor, then alpha
    rise = np.concatenate([brakings.rise_k] * 2)
    excess = np.concatenate(brakings.measured[1:]) - AMBIENT_C
    factor = float(excess @ rise / (rise @ rise))
    expected = 1.0 - factor * (1.0 - ALPHA_DECLARED)
    assert expected == pytest.approx(0.775, abs=0.002)

    effects, residual = _fit(
        brakings,  # type: ignore[arg-type]  # the evaluator's frames/residual, in miniature
        EffectSet(),
        [HeatPartition],
        None,
        max_nfev=14,
    )

    fitted = effects.get("heat_partition")
    assert isinstance(fitted, HeatPartition)
    assert fitted.alpha == pytest.approx(expected, abs=1e-3)
    assert residual.size == 1200  # the candidate's own residual: the brakings it simulates


def test_candidates_are_effects_of_the_vocabulary():
    holdout = dt.date(2024, 3, 6)
    chosen = CloseLoopConfig(holdout, candidates=("sensor_lag", "heat_partition"))
    assert [cls.name for cls in chosen.candidate_classes()] == ["heat_partition", "sensor_lag"]
    assert len(CloseLoopConfig(holdout).candidate_classes()) == len(EFFECT_ORDER)
    with pytest.raises(CloseLoopConfigError, match=r"candidates: unknown effect.*heat_partitio\b"):
        CloseLoopConfig(holdout, candidates=("heat_partitio",))


class CountingBrakings(ThreeBrakings):
    """:class:`ThreeBrakings` that records the parameter of every simulation it is asked for."""

    def __init__(self, alphas: tuple[float, ...], drop_above: float) -> None:
        super().__init__(alphas, drop_above)
        self.simulated: list[float] = []

    def frames(self, effects: EffectSet) -> pl.DataFrame:
        partition = effects.get("heat_partition")
        assert isinstance(partition, HeatPartition)
        self.simulated.append(partition.alpha)
        return super().frames(effects)


def test_a_fit_simulates_each_parameter_vector_once():
    """The optimiser's first call (the starting point, already simulated for the reference
    seconds) and the fit's residual (its last accepted point) reuse what was simulated: every
    simulation of a fit is of a new parameter vector, and the residual returned is the one of
    the fitted effects."""
    brakings = CountingBrakings(alphas=(0.70, 0.75, 0.80), drop_above=0.76)

    effects, residual = _fit(
        brakings,  # type: ignore[arg-type]  # the evaluator's frames/residual, in miniature
        EffectSet(),
        [HeatPartition],
        None,
        max_nfev=14,
    )

    assert len(brakings.simulated) >= 3
    assert len(set(brakings.simulated)) == len(brakings.simulated), brakings.simulated
    np.testing.assert_array_equal(residual, ThreeBrakings.residual(brakings, effects))
