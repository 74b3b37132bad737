"""``fleetbrake close-loop``: find the residual, trace it to the effect the model lacks, add
it, and report the error before and after (contract: ``shared/spec/interface.md``).

:func:`close_loop` runs the phases in order, each a module of this package handing the next a
typed result, none calling back up (an import-linter contract holds it):

1. **Residual and evidence** (:mod:`~fleetbrake.closeloop.evidence`). Fit events start before
   the holdout date, holdout events on or after it; an event whose window overlaps a flag of
   its wagon (dragging or weak brake, sensor fault) or an event cut by a data gap, or starts
   less than ``settle_after_flag_s`` after one ends, is left out of both, and so is a braking
   over a frozen GPS speed (its heat input is unknown). The residual (measured - predicted)
   of the current revision on the fit events is the evidence: how it relates to speed,
   pressure, heating, ambient, time since activation and the phase; the sensor noise is
   estimated from its second differences within each event window (model errors are smooth,
   the thermistor's noise is white).
2. **Candidate families** (:mod:`~fleetbrake.closeloop.candidates`): every effect of
   :mod:`fleetbrake.model.effects` (or those of ``CloseLoopConfig.candidates``) the baseline
   lacks, pairs seeded from a chosen single, and a ``fallback`` law such as ``empirical``
   last, when nothing physical is adequate.
3. **Fit** (:mod:`~fleetbrake.closeloop.fit`): each candidate's parameters by bounded least
   squares on the per-second residual (:mod:`~fleetbrake.closeloop.leastsquares`, on the
   events cached as arrays, :mod:`~fleetbrake.closeloop.fitdata`), in parallel on the
   engine's workers (:mod:`~fleetbrake.closeloop.workers`): first on the screening events,
   the best then on every fit event; fit events far off under the best are left out as
   outliers.
4. **Selection** (:mod:`~fleetbrake.closeloop.selection`, never looks at the holdout): every
   addition must beat what it adds to on the information criterion on the effective sample
   size, cut the held-out RMSE of whole wagon-days, and have its parameters distinguishable
   from their nulls; a proxy for something outside the vocabulary is refused.
5. **Verdict** (:mod:`~fleetbrake.closeloop.verdict`): the chosen model's residual against the
   noise (``adequate``, ``unexplained``) and its parameters' 95 % intervals, widened by a
   numerical term (coarser meshes, Roache's grid convergence index) and an input term (the
   speed's magnitude bias) (:mod:`~fleetbrake.closeloop.terms`).
6. **New revision** (:mod:`~fleetbrake.closeloop.revision`): the chosen effects become a new
   model revision, every event is re-simulated with it, the flags are judged again with it
   and the effect is refitted on the events usable then; the verdict is given on the fit it
   ends with.
7. **Report** (:mod:`~fleetbrake.closeloop.report`): the typed report, the RMSE before and
   after on the fit and holdout events computed from ``v_predictions`` exactly as an analyst
   would, serialised to the JSON report, and the Markdown report with plots beside it
   (:mod:`~fleetbrake.closeloop.markdown`).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from fleetbrake.closeloop import fitdata
from fleetbrake.closeloop.candidates import candidate_families
from fleetbrake.closeloop.config import CloseLoopConfig
from fleetbrake.closeloop.evidence import gather_evidence
from fleetbrake.closeloop.fit import fit_candidates
from fleetbrake.closeloop.markdown import MarkdownReport, read_markdown_report
from fleetbrake.closeloop.report import (
    CloseLoopReport,
    Cost,
    bounds_verdict,
    build_report,
    drift_verdict,
    judged_on_report,
)
from fleetbrake.closeloop.revision import new_revision
from fleetbrake.closeloop.selection import select
from fleetbrake.closeloop.verdict import baseline_verdict, start_terms
from fleetbrake.closeloop.workers import Workers
from fleetbrake.engine import Engine, InlineEngine, LocalEngine, make_engine
from fleetbrake.warehouse.connection import Warehouse, open_warehouse

__all__ = ["CLOSE_LOOP_ENGINES", "close_loop", "close_loop_report", "run_close_loop"]


def close_loop(
    wh: Warehouse, config: CloseLoopConfig, engine: Engine | None = None
) -> dict[str, Any]:
    """The closed loop on an open (writable) warehouse; returns the report as JSON values
    (:func:`close_loop_report`)."""
    return close_loop_report(wh, config, engine).to_dict()


def close_loop_report(
    wh: Warehouse, config: CloseLoopConfig, engine: Engine | None = None
) -> CloseLoopReport:
    """The closed loop on an open (writable) warehouse; returns the report (see module).
    ``engine``: where the candidates are fitted (and the new revision simulated and judged),
    in this process when None. The report's ``cost`` says what it took: candidates fitted,
    chain-kernel calls, seconds per phase."""
    clock = time.perf_counter()
    calls = fitdata.kernel_calls()
    workers = Workers(engine)
    # the evaluations made in this process (a single fit, the outliers, the holdout, the
    # input term) split their spans across as many threads as the engine has workers, which
    # are idle then (but for the coarse fits beside the re-flag refit); the same results
    threads = engine.workers if isinstance(engine, LocalEngine) else 1
    try:
        with fitdata.parallel(threads):
            report = _phases(wh, config, engine, workers)
    finally:
        workers.close()
    report = drift_verdict(bounds_verdict(judged_on_report(wh, report, config)))
    workers.timing["total_s"] = time.perf_counter() - clock
    cost = Cost(
        candidates_fitted=workers.fits,
        kernel_calls=fitdata.kernel_calls() - calls + workers.kernel_calls,
        evaluations=dict(workers.evaluations),
        seconds={k: round(v, 3) for k, v in workers.timing.items()},
    )
    return dataclasses.replace(report, cost=cost)


def _phases(
    wh: Warehouse, config: CloseLoopConfig, engine: Engine | None, workers: Workers
) -> CloseLoopReport:
    """The phases in order (see the module), each handed what the earlier ones found."""
    evidence = gather_evidence(wh, config, workers)
    families = candidate_families(evidence.present, config)
    fitted = fit_candidates(evidence, families, config, workers)
    selection = select(evidence, families, fitted, config, workers)
    if selection.chosen is None:
        verdict, new = baseline_verdict(evidence, fitted), None
    else:
        ahead = start_terms(selection.chosen, evidence, families, fitted, config, workers)
        new = new_revision(
            wh, selection.chosen, ahead, evidence, families, fitted, config, engine, workers
        )
        verdict = new.verdict
    return build_report(wh, evidence, families, fitted, selection, verdict, new, config)


CLOSE_LOOP_ENGINES = ("inline", "local", "ray")
"""Names ``close-loop --engine`` accepts: ``inline`` runs everything in this process."""


def _make_engine(name: str, workers: int | None, address: str | None) -> Engine:
    from fleetbrake.engine import EngineConfigError

    if name not in CLOSE_LOOP_ENGINES:
        raise EngineConfigError(
            f"--engine must be one of {', '.join(CLOSE_LOOP_ENGINES)}, got {name!r}"
        )
    if name == "inline":
        if address is not None:
            raise EngineConfigError("--address needs --engine ray")
        if workers is not None and workers < 1:
            raise EngineConfigError(f"--workers must be >= 1, got {workers}")
        return InlineEngine()
    # the workers import what a fit runs (least_squares is imported when a fit starts)
    preload = ("fleetbrake.closeloop.loop", "scipy.optimize")
    return make_engine(name, workers, address=address, preload=preload)


def run_close_loop(
    db_path: str | Path,
    holdout_from: dt.date,
    json_out: str | Path,
    *,
    wait_s: float = 0.0,
    config: CloseLoopConfig | None = None,
    engine: str = "inline",
    workers: int | None = None,
    address: str | None = None,
) -> dict[str, Any]:
    """``fleetbrake close-loop``: run, write the JSON report and the Markdown report.
    ``engine``: where candidates are fitted and the new revision simulated and judged:
    ``inline`` (this process), ``local`` (``workers`` processes, default the cores) or
    ``ray`` (at ``address``, or a local instance of ``workers`` CPUs)."""
    config = config or CloseLoopConfig(holdout_from=holdout_from)
    pool = _make_engine(engine, workers, address)  # refused before the database is opened
    with pool, ThreadPoolExecutor(max_workers=1, thread_name_prefix="closeloop-report") as side:
        with open_warehouse(db_path, wait_s=wait_s) as wh:
            # the workers start and import the close loop while the wagons are loaded, not at
            # the screening's first fit (about a processor-second each)
            pool.start()
            report = close_loop_report(wh, config, None if isinstance(pool, InlineEngine) else pool)
            data = report.to_dict()
            json_out = Path(json_out)
            json_out.parent.mkdir(parents=True, exist_ok=True)
            text = json.dumps(data, indent=2, default=str) + "\n"
            json_out.write_text(text, encoding="utf-8")
            markdown = read_markdown_report(wh, report, json_out.with_suffix(".md"))
            # the Markdown report's plots are drawn on a worker, and the workers stopped,
            # while the warehouse closes (DuckDB's checkpoint merges the new revision's row
            # groups: about 1.5 processor-s of its own)
            written = side.submit(_write_and_stop, markdown, pool)
        written.result()
    return data


def _write_and_stop(markdown: MarkdownReport, engine: Engine) -> None:
    """Write the Markdown report (its plots drawn on one of ``engine``'s workers), then stop
    the engine's workers: it has no more work."""
    try:
        markdown.write(engine)
    finally:
        engine.close()
