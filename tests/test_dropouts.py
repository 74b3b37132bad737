"""The speed across a GPS dropout: both ends and the logged distance."""

from __future__ import annotations

import numpy as np
import pytest

from fleetbrake.simulation.dropouts import dropout_runs, speed_across_dropouts, speed_profile


def _covered_m(v0_kmh: float, inside_kmh: np.ndarray, v1_kmh: float) -> float:
    """The distance of a 1 Hz profile by the trapezoidal rule (km/h in, m out)."""
    v = np.concatenate([[v0_kmh], inside_kmh, [v1_kmh]]) / 3.6
    return float(np.sum((v[1:] + v[:-1]) / 2.0))


def test_a_stop_inside_the_dropout_is_found_from_the_distance():
    # truth: 60 km/h braking at constant deceleration to rest 40 s into a 150 s dropout
    t_s = np.arange(151.0)
    truth = np.maximum(60.0 * (1.0 - t_s / 40.0), 0.0)
    covered_m = _covered_m(truth[0], truth[1:-1], truth[-1])
    assert covered_m == pytest.approx(333.33, abs=0.5)
    filled = speed_profile(60.0, 0.0, covered_m, 150.0)
    assert filled.shape == (149,)
    assert np.all(filled >= 0)
    np.testing.assert_allclose(filled, truth[1:-1], atol=1e-9)
    # a straight line would have covered 1,250 m: almost four times the work of the brakes
    assert _covered_m(60.0, np.linspace(60.0, 0.0, 151)[1:-1], 0.0) == pytest.approx(1250.0)


def test_the_smooth_profile_meets_both_ends_and_the_distance():
    for v0, v1, covered_m in [(40.0, 20.0, 1200.0), (0.0, 0.0, 300.0), (50.0, 50.0, 1600.0)]:
        filled = speed_profile(v0, v1, covered_m, 90.0)
        assert np.all(filled >= 0)
        assert _covered_m(v0, filled, v1) == pytest.approx(covered_m, rel=2e-3)
        # continuous at the ends: the first and last seconds are near the end speeds
        assert abs(filled[0] - v0) < 0.1 * max(v0, v1, 10.0)
        assert abs(filled[-1] - v1) < 0.1 * max(v0, v1, 10.0)


def test_a_stop_then_a_start_inside_the_dropout():
    filled = speed_profile(36.0, 18.0, 150.0, 120.0)  # 10 m/s and 5 m/s ends, only 150 m
    assert np.all(filled >= 0)
    assert np.min(filled) == 0.0  # it stood still
    assert _covered_m(36.0, filled, 18.0) == pytest.approx(150.0, rel=0.02)


def test_runs_are_filled_only_where_the_distance_can_say():
    t_s = np.arange(20.0)
    speed = np.full(20, 30.0)
    speed[3:8] = np.nan  # a dropout with a usable distance
    speed[12:15] = np.nan  # a dropout across a new session: the distance went back
    speed[18:] = np.nan  # trailing: no end
    distance = np.cumsum(np.full(20, 30.0 / 3.6))
    distance[3:8] = distance[2]  # held while there is no fix
    distance[15:] -= 1000.0
    assert dropout_runs(speed) == [(2, 8), (11, 15)]
    filled = speed_across_dropouts(t_s, speed, distance)
    np.testing.assert_allclose(filled[3:8], 30.0, atol=1e-9)
    assert np.all(np.isnan(filled[12:15]))
    assert np.all(np.isnan(filled[18:]))
    np.testing.assert_array_equal(filled[:3], speed[:3])


def test_the_synthetic_dropout_holds_the_distance_inside_a_braking():
    import polars as pl

    from fleetbrake.synth.corrupt import gps_dropout

    n = 300
    speed = np.full(n, 50.0)
    frame = pl.DataFrame(
        {
            "speed_kmh": speed,
            "distance_m": np.cumsum(speed / 3.6),
            "brake_pressure_bar": np.where(np.arange(n) >= 100, 3.0, 0.0),
        }
    )
    out = gps_dropout(frame, np.random.default_rng(0), 60, start=105)
    assert out["speed_kmh"].null_count() == 60
    assert out["speed_kmh"][104] == 50.0 and out["speed_kmh"][165] == 50.0
    held = out["distance_m"].to_numpy()
    assert np.all(held[105:165] == held[104])
    assert held[165] == frame["distance_m"][165]  # the jump when the fix returns
    filled = speed_across_dropouts(
        np.arange(n, dtype=np.float64),
        out["speed_kmh"].to_numpy().astype(np.float64),
        held,
    )
    np.testing.assert_allclose(filled, speed, atol=1e-9)
