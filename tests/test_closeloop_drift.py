"""A parameter that changes over the calendar: found per day, reported, and not adequate."""

from __future__ import annotations

import json

import numpy as np

from fleetbrake.closeloop.report import drift_verdict
from fleetbrake.closeloop.stats import parameter_drift
from test_selection import typed_report

DAYS = 3
WAGONS = 8
SECONDS = 1500


def _fleet(rate_per_day: float, seed: int, spread: float = 0.02):
    """A model linear in one parameter (``predicted = p g``), measured with the parameter
    ``1 + rate t`` on day t plus a wagon-day spread and white noise: the residual and
    Jacobian at the pooled fit, the wagon-day blocks and the times."""
    rng = np.random.default_rng(seed)
    g, measured, blocks, times = [], [], [], []
    start = np.datetime64("2024-03-01T06:00:00", "us")
    for day in range(DAYS):
        for wagon in range(WAGONS):
            gk = np.abs(rng.normal(5.0, 2.0, SECONDS))
            p_true = 1.0 + rate_per_day * day + rng.normal(0.0, spread)
            g.append(gk)
            measured.append(p_true * gk + rng.normal(0.0, 0.1, SECONDS))
            blocks.append(np.full(SECONDS, day * WAGONS + wagon))
            seconds = np.arange(SECONDS) * 10 + wagon * 3
            times.append(start + np.timedelta64(day, "D") + seconds * np.timedelta64(1, "s"))
    g_all, m_all = np.concatenate(g), np.concatenate(measured)
    p_hat = float(np.dot(g_all, m_all) / np.dot(g_all, g_all))
    residual = p_hat * g_all - m_all
    return (
        g_all[:, None],
        residual,
        np.array([p_hat]),
        np.concatenate(blocks),
        np.concatenate(times),
    )


def test_a_constant_parameter_seldom_changes():
    found = 0
    for seed in range(40):
        jacobian, residual, x, blocks, times = _fleet(0.0, seed)
        drift = parameter_drift(jacobian, residual, x, ["gain"], blocks, times)
        assert drift is not None and len(drift.periods) == DAYS
        found += drift.parameters["gain"].changes
    assert found <= 6  # about 5 % expected of 40


def test_a_drifting_parameter_changes_at_its_rate():
    jacobian, residual, x, blocks, times = _fleet(0.08, seed=3)
    drift = parameter_drift(jacobian, residual, x, ["gain"], blocks, times)
    assert drift is not None
    gain = drift.parameters["gain"]
    assert gain.changes
    low, high = gain.rate_interval
    assert low < 0.08 < high
    assert abs(gain.rate_per_day - 0.08) < 0.03
    values = [p.values["gain"] for p in drift.periods]
    assert values == sorted(values)
    assert [p.start for p in drift.periods] == ["2024-03-01", "2024-03-02", "2024-03-03"]
    # one day only: no drift to speak of
    one = times < np.datetime64("2024-03-02", "us")
    assert (
        parameter_drift(jacobian[one], residual[one], x, ["gain"], blocks[one], times[one]) is None
    )


def test_the_verdict_says_what_changes():
    jacobian, residual, x, blocks, times = _fleet(0.08, seed=3)
    drift = parameter_drift(jacobian, residual, x, ["h_speed"], blocks, times)
    report = typed_report(drift=drift)
    judged = drift_verdict(report)
    assert report.adequate and not judged.adequate
    assert judged.unexplained is not None
    assert "h_speed changes over the period" in judged.unexplained
    assert "per day" in judged.unexplained
    data = json.loads(json.dumps(judged.to_dict()))
    assert data["drift"]["parameters"]["h_speed"]["changes"] is True
    assert len(data["drift"]["periods"]) == DAYS
    j0, r0, x0, b0, t0 = _fleet(0.0, seed=1)
    steady = typed_report(drift=parameter_drift(j0, r0, x0, ["h_speed"], b0, t0))
    assert steady.drift is not None and not steady.drift.parameters["h_speed"].changes
    assert drift_verdict(steady) is steady
    assert typed_report().to_dict()["drift"] is None
