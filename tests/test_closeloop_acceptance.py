"""The close loop's acceptance tests on fleets the pipeline did not make easy.

One small fleet per effect of the vocabulary, a clean one and one with an effect outside the
vocabulary (sunshine by the hour of day), each written by the full finite-element model on
the identifying reduced model's own mesh (``acceptance_fleets.FE_REFINEMENT``, 0.6) with its
law and parameters drawn at random, anomalies and file faults on
(:mod:`acceptance_fleets`). Each fleet is generated, run and closed once per module; every
test below is parametrised by the fleet, so one fleet runs alone with ``-k NAME``
(``-k convection_speed``, ``-k clean``, ``-k hour_of_day``)::

    RAYON_NUM_THREADS=1 .venv/bin/python -m pytest -p no:cacheprovider -q -s \\
        tests/test_closeloop_acceptance.py -k convection_speed

(``-s`` prints each fleet's row of the acceptance table: what was named, the parameters
against the truth with their intervals, the holdout RMSE against the noise-free truth before
and after, the noise, the verdict, the flags' precision and recall, and the seconds spent.)

What must hold: on a vocabulary fleet the effect in the data
is named **alone**, in its law, and nothing is added on the clean fleet; every fitted
parameter's 95 % interval (``parameter_intervals``) contains the true value; on the holdout
day the new revision's RMSE against the noise-free truth is at most 40 % of the declared
model's and at most 1.5x the sensor noise; the flags judged after the loop have precision and
recall of at least 0.9 against the injected anomalies. On the fleet outside the vocabulary the
report says ``adequate: false``, ``unexplained`` names the hour of day, and nothing but the
``empirical`` correction is added. On every fleet the report's before/after numbers are what
``v_predictions`` gives.

Every case takes half an hour or more on a shared 2-core machine, most of it the full model
at refinement 0.6 writing the fleet (26 min for ambient_offset under load 7-10; 54 s at
refinement 0.2), then ``run`` and the close loop: the module is
``slow``; run one case at a time.

A written fleet is kept: under ``$FLEETBRAKE_ACCEPTANCE_CACHE`` (default
``~/.cache/fleetbrake/acceptance``; ``off`` for none), keyed by the case, its seed and the
writer's version (``acceptance_fleets.writer_version``: a hash of ``FE_REFINEMENT``, the
SynthConfig with its drawn effect, the source of ``fleetbrake.synth`` and of the full-model
modules it runs, Python and Rust, and the writing part of ``acceptance_fleets``), written
into a temporary directory and renamed into place when complete. A case whose fleet is
cached copies it into its own directory (the ``from_cache`` seconds instead of
``generate``) and pays only for ``run`` and the close loop; a changed writer has another
version and writes the fleet again (``test_closeloop_fleet_cache``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest

from acceptance_fleets import (
    CASES,
    NOISE_K,
    Case,
    Outcome,
    draw_case_effect,
    fitted_effects,
    flag_score,
    holdout_rmse_against_truth,
    interval_misses,
    make_outcome,
    report_vs_predictions,
    summary_row,
)

pytestmark = pytest.mark.slow

VOCABULARY_CASES = [c for c in CASES if c.effect is not None]
EXPLAINABLE_CASES = [c for c in CASES if not c.outside_vocabulary]
OUTSIDE_CASES = [c for c in CASES if c.outside_vocabulary]


def cases(chosen: list[Case], xfail: Mapping[str, str] | None = None) -> list[Any]:
    """The cases as parameters; those named in ``xfail`` marked ``xfail(strict=True)`` with
    the reason given (a bar the pipeline cannot meet today, with its measured figures)."""
    return [
        pytest.param(
            c,
            id=c.name,
            marks=[pytest.mark.xfail(strict=True, reason=xfail[c.name])]
            if xfail and c.name in xfail
            else [],
        )
        for c in chosen
    ]


@pytest.fixture(scope="module")
def outcome_of(
    tmp_path_factory: pytest.TempPathFactory,
    rom_cache_dir: Path,
    rom_refinement: float,
) -> Iterator[Callable[[Case], Outcome]]:
    """``outcome_of(case)``: the case generated, run and closed, once per module (a failure
    too is kept, and raised again by every test of the case, rather than paid for again)."""
    done: dict[str, Outcome | BaseException] = {}
    with pytest.MonkeyPatch.context() as mp:
        # the pipeline builds its reduced models where the test run keeps them
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))

        def get(case: Case) -> Outcome:
            if case.name not in done:
                try:
                    # written by the full model at acceptance_fleets.FE_REFINEMENT
                    out = make_outcome(case, tmp_path_factory.mktemp(case.name), rom_refinement)
                except Exception as exc:
                    done[case.name] = exc
                else:
                    done[case.name] = out
                    print(f"\nacceptance {case.name}: {json.dumps(summary_row(out), default=str)}")
            value = done[case.name]
            if isinstance(value, BaseException):
                raise value
            return value

        yield get


@pytest.mark.parametrize("case", cases(list(CASES)))
def test_the_effect_in_the_data_is_named_alone(
    outcome_of: Callable[[Case], Outcome], case: Case
) -> None:
    """A vocabulary fleet: exactly its effect, in the law that made it; the clean fleet:
    nothing; outside the vocabulary: nothing physical (at most ``empirical``)."""
    outcome = outcome_of(case)
    report = outcome.report
    added = fitted_effects(report)
    context = (report.get("effect"), report.get("candidates"), report.get("evidence"))
    if case.outside_vocabulary:
        assert [e.name for e in added] in ([], ["empirical"]), context
        return
    truth = draw_case_effect(case)
    if truth is None:
        assert report["new_revision"] is None, context
        assert added == [], context
        return
    assert report["effect"] == truth.name, context
    assert [(e.name, e.law) for e in added] == [(truth.name, truth.law)], (str(truth), context)


@pytest.mark.parametrize("case", cases(VOCABULARY_CASES))
def test_every_interval_contains_the_true_value(
    outcome_of: Callable[[Case], Outcome], case: Case
) -> None:
    outcome = outcome_of(case)
    truth = draw_case_effect(case)
    assert truth is not None
    report = outcome.report
    assert report.get("effect") == truth.name, (report.get("effect"), str(truth))
    intervals = report.get("parameter_intervals")
    assert isinstance(intervals, dict), "the report has no parameter_intervals (interface v2)"
    misses = interval_misses(truth, intervals)
    assert misses == {}, (str(truth), report["parameters"], intervals)


@pytest.mark.parametrize("case", cases(EXPLAINABLE_CASES))
def test_holdout_rmse_against_the_noise_free_truth(
    outcome_of: Callable[[Case], Outcome], case: Case
) -> None:
    """The new revision on the holdout day, against the generator's noise-free sensor: at
    most 40 % of the declared model's and 1.5x the sensor noise (the clean fleet: the
    declared model itself within 1.5x the noise, which is why nothing is to be added)."""
    outcome = outcome_of(case)
    report = outcome.report
    declared = holdout_rmse_against_truth(outcome, report["baseline_revision"])
    if case.effect is None:
        assert declared <= 1.5 * NOISE_K, declared
        return
    assert report["new_revision"] is not None, report.get("evidence")
    new = holdout_rmse_against_truth(outcome, report["new_revision"])
    assert new <= 0.4 * declared, (new, declared)
    assert new <= 1.5 * NOISE_K, (new, declared)


@pytest.mark.parametrize("case", cases(EXPLAINABLE_CASES))
def test_the_report_calls_the_result_adequate(
    outcome_of: Callable[[Case], Outcome], case: Case
) -> None:
    """With the effect in the data found (or none in it), the verdict is ``adequate`` with a
    noise estimate (interface v2)."""
    report = outcome_of(case).report
    assert isinstance(report.get("noise_k"), float), report.get("noise_k")
    assert report.get("adequate") is True, (report.get("noise_k"), report.get("unexplained"))


@pytest.mark.parametrize("case", cases(OUTSIDE_CASES))
def test_an_effect_outside_the_vocabulary_is_not_called_adequate(
    outcome_of: Callable[[Case], Outcome], case: Case
) -> None:
    """Sunshine by the hour of day: ``adequate`` false, and ``unexplained`` says the residual
    still correlates with the hour of day (what the effect depends on)."""
    report = outcome_of(case).report
    assert report.get("adequate") is False, (report.get("effect"), report.get("unexplained"))
    unexplained = report.get("unexplained") or ""
    assert "correlated with" in unexplained, unexplained
    assert "hour" in unexplained, unexplained


@pytest.mark.parametrize("case", cases(EXPLAINABLE_CASES))
def test_flags_after_the_loop_match_the_injected_anomalies(
    outcome_of: Callable[[Case], Outcome], case: Case
) -> None:
    """The flags as the loop leaves them (judged again with the new revision), against the
    generator's anomalies: precision and recall at least 0.9."""
    outcome = outcome_of(case)
    if outcome.report.get("new_revision") and "flags_judged_with" in outcome.report:
        assert outcome.report["flags_judged_with"] == outcome.report["new_revision"]
    score = flag_score(outcome)
    assert score.total.anomalies >= 3, score
    assert score.precision >= 0.9, (score.precision, score.by_kind, score.misses)
    assert score.recall >= 0.9, (score.recall, score.by_kind, score.misses)


@pytest.mark.parametrize("case", cases(list(CASES)))
def test_the_report_agrees_with_v_predictions(
    outcome_of: Callable[[Case], Outcome], case: Case
) -> None:
    outcome = outcome_of(case)
    assert report_vs_predictions(outcome) == []
    assert outcome.db.with_name("close-loop.md").exists()
