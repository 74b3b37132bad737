"""A fitted parameter on a limit of its family makes the verdict not adequate, and says so."""

from __future__ import annotations

import json

from fleetbrake.closeloop.markdown import render_markdown
from fleetbrake.closeloop.report import bounds_verdict, parameters_on_bound
from fleetbrake.model.effects import ConvectionSpeed, FrictionSpeed, SensorLag
from test_selection import typed_report

KARWATZKI = FrictionSpeed()


def test_a_value_or_an_interval_on_a_limit_is_found():
    high = FrictionSpeed.LIMITS["force_scale_kn"][1]
    assert high is not None
    on = FrictionSpeed(level=1.1, speed_scale_kmh=90.0, force_scale_kn=high)
    parameters = dict(on.parameters)
    intervals = {k: [v * 0.95, min(v * 1.05, high)] for k, v in parameters.items()}
    found = parameters_on_bound([on], parameters, intervals)
    assert [(b.parameter, b.side, b.limit) for b in found] == [("force_scale_kn", "upper", high)]
    # inside: nothing; an interval reaching the lower limit (or unbounded below): found
    inside = dict(KARWATZKI.parameters)
    narrow = {k: [v * 0.99, v * 1.01] for k, v in inside.items()}
    assert parameters_on_bound([KARWATZKI], inside, narrow) == []
    low = FrictionSpeed.LIMITS["level"][0]
    wide = dict(narrow, level=[low, 1.2])
    assert [b.parameter for b in parameters_on_bound([KARWATZKI], inside, wide)] == ["level"]
    unbounded = dict(narrow, level=[None, 1.2])
    assert [b.side for b in parameters_on_bound([KARWATZKI], inside, unbounded)] == ["lower"]
    # two effects: keyed effect.parameter; a side without a limit is never reached
    lag = SensorLag(tau_s=60.0)
    keyed = {"friction_speed." + k: v for k, v in inside.items()} | {"sensor_lag.tau_s": 60.0}
    assert parameters_on_bound([KARWATZKI, lag], keyed, {}) == []
    assert ConvectionSpeed.LIMITS  # every family states its limits


def test_the_verdict_names_the_parameter_and_the_limit():
    high = FrictionSpeed.LIMITS["force_scale_kn"][1]
    on = FrictionSpeed(level=1.1, speed_scale_kmh=90.0, force_scale_kn=high)
    report = typed_report(
        effect="friction_speed",
        effects=[on],
        parameters=dict(on.parameters),
        parameter_intervals={k: [v * 0.9, v] for k, v in on.parameters.items()},
    )
    judged = bounds_verdict(report)
    assert report.adequate and not judged.adequate
    assert judged.unexplained is not None
    assert "force_scale_kn" in judged.unexplained and "upper limit" in judged.unexplained
    data = json.loads(json.dumps(judged.to_dict()))
    assert data["adequate"] is False
    assert data["on_bound"][0]["parameter"] == "force_scale_kn"
    assert data["on_bound"][0]["side"] == "upper"
    assert judged.unexplained in render_markdown(judged)
    # inside every limit: the verdict stands
    inside = typed_report(effects=[KARWATZKI], parameters=dict(KARWATZKI.parameters))
    assert bounds_verdict(inside) is inside
