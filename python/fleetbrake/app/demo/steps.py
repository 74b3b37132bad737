"""``fleetbrake demo``: the whole of fleetbrake on a synthetic fleet, in a few minutes.

::

    from fleetbrake.app.demo import DemoConfig, run_demo

    result = run_demo("demo-out", DemoConfig(wagons=4, days=2))
    print(result.summary)

Steps (each timed):

1. **Reduced thermal model**: built once per block geometry and cached on disk
   (``$FLEETBRAKE_CACHE_DIR`` or ``~/.cache/fleetbrake``); the first demo on a machine pays
   for the build (about a minute at the default mesh on 2 cores), later ones load it.
2. **Fleet**: :func:`fleetbrake.synth.generator.generate_fleet` writes ``wagons`` wagons over ``days``
   UTC days with ONE undeclared effect acting on every wagon (by default
   ``convection_speed``: the convection coefficient grows with train speed, which the
   declared model does not know), anomalies (dragging brake, weak brake, sensor faults) and
   the ordinary imperfections of real logs (bad files, a wagon missing from the registry,
   ...), and its truth beside it (``fleet/truth``).
3. **Run**: :func:`fleetbrake.app.run.run_fleet`, as ``fleetbrake run``: ingestion (bad
   files quarantined), events, simulation with the declared model, flags.
4. **Closed loop**: :func:`fleetbrake.closeloop.loop.run_close_loop`, as ``fleetbrake
   close-loop``, fitting on every day but the last and holding the last day out; then the
   effect it found is compared with the truth.
5. **Flags again**: when the closed loop added an effect, ``run_fleet`` once more (as the
   next scheduled ``fleetbrake run`` would): nothing new to ingest or simulate, the flags
   are judged again with the new revision.
6. **Recordings** (``fleetbrake record``): the timeline of one wagon and one of its events
   (the worst flagged one, else the one with the largest residual), with the block's field.
7. **Report**: :func:`fleetbrake.app.report.write_report` (Markdown and PNGs).

Each step is a method of :class:`DemoSteps`, taking what the steps before it handed over;
:func:`run_demo` calls them in order. The output directory holds only this demo's results
(:func:`~fleetbrake.app.demo.outdir.prepare_out_dir`).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import rich
from rich.console import Console
from rich.markup import escape

from fleetbrake.app.demo.config import DemoConfig, DemoError
from fleetbrake.app.demo.outdir import prepare_out_dir
from fleetbrake.app.demo.result import DemoResult
from fleetbrake.app.demo.summary import flag_counts, loop_line, plural, seconds_text, summary
from fleetbrake.app.progress import generation_bar, spinner
from fleetbrake.errors import FleetbrakeError

if TYPE_CHECKING:
    from fleetbrake.app.run import RunReport

__all__ = ["DemoSteps", "LoopOutcome", "ModelOutcome", "Recordings", "pick_event", "run_demo"]

_SEVERITY_RANK = {"alarm": 0, "warning": 1, "info": 2}
_KIND_RANK = {"dragging_brake": 0, "overheating": 1, "weak_brake": 2, "sensor_fault": 3}


@dataclass(frozen=True)
class ModelOutcome:
    """Step 1: how long the reduced model took, and whether it was built (not loaded)."""

    seconds: float
    built: bool


@dataclass(frozen=True)
class LoopOutcome:
    """Step 4: the close-loop report (empty if the loop could not run) and why it could not."""

    report: dict[str, Any]
    error: str | None = None


@dataclass(frozen=True)
class Recordings:
    """Step 6: the recordings written, and the wagon and event they show (None: none)."""

    paths: list[Path] = field(default_factory=list)
    wagon_id: str | None = None
    event_id: str | None = None
    reason: str | None = None
    """Why the event was picked (:func:`pick_event`)."""


class DemoSteps:
    """The demo's steps into one output directory, each timed into :attr:`timings`."""

    def __init__(self, out: Path, config: DemoConfig, console: Console, show: bool) -> None:
        from fleetbrake.simulation.config import SimulationConfig

        self.out = out
        self.config = config
        self.console = console
        self.show = show
        self.fleet_dir = out / "fleet"
        self.db_path = out / "fleet.duckdb"
        self.close_json = out / "close-loop.json"
        self.simulation = SimulationConfig(refinement=config.refinement)
        """Every step runs on the same model."""
        self.timings: dict[str, float] = {}

    def _announce(self, number: int, text: str) -> None:
        self.console.print(
            f"[bold]\\[{number}/7][/bold] {escape(text)}", highlight=False, soft_wrap=True
        )

    def _say(self, text: str) -> None:
        self.console.print(f"    {text}", highlight=False, soft_wrap=True)

    def _clock(self, name: str, t0: float) -> None:
        self.timings[name] = round(time.perf_counter() - t0, 2)

    def model(self) -> ModelOutcome:
        """1. Load (or build and cache) the reduced model of the synthetic fleet's block: the
        generator's wagons all have the reference block and sensor seat."""
        from fleetbrake.fleet.registry import WagonConfig
        from fleetbrake.model.rom import ReducedModel, default_cache_dir

        refinement = self.config.refinement
        self._announce(1, f"reduced thermal model of the block (refinement {refinement:g})")
        began = time.perf_counter()
        text = (
            f"reduced thermal model (refinement {refinement:g}): loading from "
            f"{default_cache_dir()}, or building it once (about a minute at the default mesh)"
        )
        with spinner(text, self.show, self.console):
            ReducedModel.for_wagon(WagonConfig(wagon_id="SGG-0001"), refinement=refinement)
        seconds = time.perf_counter() - began
        outcome = ModelOutcome(seconds, built=seconds > 3.0)
        self.timings["model"] = round(seconds, 2)
        self._say(
            f"{'built and cached' if outcome.built else 'loaded from the cache'} "
            f"in {seconds_text(seconds)}"
        )
        return outcome

    def generate(self) -> Any:
        """2. The synthetic fleet and its truth (the generator's ``FleetTruth``)."""
        from fleetbrake.model.effects import EffectSet, parse_effect
        from fleetbrake.synth.generator import SynthConfig, generate_fleet

        config = self.config
        self._announce(
            2,
            f"generating {plural(config.wagons, 'wagon')} x {config.days} days "
            f"(seed {config.seed}) "
            f"with an undeclared effect and anomalies into {self.fleet_dir}",
        )
        t0 = time.perf_counter()
        synth = SynthConfig(
            wagons=config.wagons,
            days=config.days,
            seed=config.seed,
            start=config.start,
            effects=EffectSet((parse_effect(config.effect),)),
            anomalies=config.anomalies,
            refinement=config.refinement,
        )
        total = synth.wagons + int(synth.unregistered_wagon) + int(synth.bad_registry_entry)
        with generation_bar(total, self.show, self.console) as step:
            truth = generate_fleet(self.fleet_dir, synth, progress=step)
        self._clock("generate", t0)
        return truth

    def run(self) -> RunReport:
        """3. ``fleetbrake run``: ingest, detect events, simulate them, raise flags."""
        from fleetbrake.app.run import run_fleet

        self._announce(3, "fleetbrake run: ingest, detect events, simulate them, raise flags")
        t0 = time.perf_counter()
        run = run_fleet(
            self.fleet_dir, self.db_path, simulation=self.simulation, progress=self.show
        )
        self._clock("run", t0)
        self._say(
            f"{len(run.ingest.ingested)} files ingested, "
            f"{len(run.ingest.quarantined)} quarantined, "
            f"{run.simulation.events_simulated} events simulated, "
            f"flags: {flag_counts(run.flags)}"
        )
        return run

    def close_loop(self) -> LoopOutcome:
        """4. ``fleetbrake close-loop``, fitting on every day but the last, holding it out."""
        from fleetbrake.closeloop.config import CloseLoopConfig
        from fleetbrake.closeloop.errors import CloseLoopError
        from fleetbrake.closeloop.loop import run_close_loop

        holdout_from = self.config.holdout_from
        self._announce(
            4,
            f"fleetbrake close-loop: fit before {holdout_from}, hold that day out "
            "(the longest step)",
        )
        t0 = time.perf_counter()
        try:
            with spinner("finding the effect the model lacks", self.show, self.console):
                outcome = LoopOutcome(
                    run_close_loop(
                        self.db_path,
                        holdout_from,
                        self.close_json,
                        config=CloseLoopConfig(holdout_from, simulation=self.simulation),
                    )
                )
        except CloseLoopError as error:  # e.g. every fit event flagged: say so, go on
            outcome = LoopOutcome({}, str(error))
        self._clock("close_loop", t0)
        self._say(
            loop_line(outcome.report)
            if outcome.error is None
            else f"could not run: {outcome.error}"
        )
        return outcome

    def flags_again(self, loop: LoopOutcome) -> RunReport | None:
        """5. When the closed loop added an effect, ``run_fleet`` once more (as the next
        scheduled ``fleetbrake run`` would): the flags judged again with the new revision."""
        from fleetbrake.app.run import run_fleet

        if not loop.report.get("new_revision"):
            self._announce(5, "no effect added: the flags stand")
            return None
        self._announce(5, f"flags judged again with revision {loop.report['new_revision']}")
        t0 = time.perf_counter()
        rerun = run_fleet(
            self.fleet_dir, self.db_path, simulation=self.simulation, progress=self.show
        )
        self._clock("flags_again", t0)
        self._say(f"flags: {flag_counts(rerun.flags)}")
        return rerun

    def recordings(self) -> Recordings:
        """6. The rerun recordings of one wagon's timeline and of one of its events
        (:func:`pick_event`), with the block's field."""
        from fleetbrake.viz.record import record

        picked = pick_event(self.db_path)
        if not self.config.recordings or picked is None:
            self._announce(6, "no recordings")
            return Recordings()
        event_id, wagon_id, reason = picked
        self._announce(6, f"rerun recordings of wagon {wagon_id} and of event {event_id}")
        t0 = time.perf_counter()
        rec_dir = self.out / "recordings"
        with spinner("writing recordings", self.show, self.console):
            paths = [
                record(self.db_path, wagon_id, rec_dir / f"{wagon_id}-timeline.rrd").out,
                record(self.db_path, wagon_id, rec_dir / f"{event_id}.rrd", event_id=event_id).out,
            ]
        self._clock("record", t0)
        return Recordings(paths, wagon_id, event_id, reason)

    def report(self, result: DemoResult, recordings: Recordings) -> list[Path]:
        """7. The report (Markdown and PNGs) of everything the steps before wrote and found;
        returns its pictures."""
        from fleetbrake.app.report import write_report

        self._announce(7, "the report")
        t0 = time.perf_counter()
        config, truth = self.config, result.truth
        notes = [
            f"Synthetic fleet of the demo: {plural(config.wagons, 'wagon')} x {config.days} "
            f"days, seed {config.seed}, undeclared effect `{truth.effects}`"
            + (", with anomalies" if config.anomalies else "")
            + f"; reduced model at refinement {config.refinement:g}. "
            f"Closed loop fitted before {config.holdout_from}, that day held out."
        ]
        if recordings.event_id is not None:
            notes.append(
                f"Recordings: wagon {recordings.wagon_id} and event "
                f"`{recordings.event_id}` ({recordings.reason}); open them with `rerun FILE.rrd`."
            )
        if result.close_loop_error is not None:
            notes.append(f"The closed loop could not run: {result.close_loop_error}.")
        written = write_report(
            self.db_path,
            self.out,
            close_loop=result.close_loop or None,
            truth=truth,
            artefacts=[(w, p.relative_to(self.out)) for w, p in result.artefacts()],
            title="fleetbrake demo report",
            notes=notes,
        )
        self._clock("report", t0)
        return written.pictures


def run_demo(
    out_dir: str | Path = "demo-out",
    config: DemoConfig | None = None,
    *,
    force: bool = False,
    console: Console | None = None,
    progress: bool | None = None,
) -> DemoResult:
    """Run the demo into ``out_dir`` (see the module); returns what it wrote and found,
    with a summary for people in ``result.summary``. ``progress``: show spinners and bars
    (None: when the console is a terminal). Raises :class:`DemoError` (or
    :class:`DemoExistsError`) with a message that says what to do."""
    config = config or DemoConfig()
    console = console or rich.get_console()
    show = console.is_terminal if progress is None else progress
    began = time.perf_counter()
    out = prepare_out_dir(out_dir, force=force)
    steps = DemoSteps(out, config, console, show)
    try:
        model = steps.model()
        truth = steps.generate()
        run = steps.run()
        loop = steps.close_loop()
        rerun = steps.flags_again(loop)
        recordings = steps.recordings()
        result = DemoResult(
            out_dir=out,
            config=config,
            fleet_dir=steps.fleet_dir,
            db_path=steps.db_path,
            close_loop_json=steps.close_json,
            close_loop_md=steps.close_json.with_suffix(".md"),
            report=out / "report.md",
            pictures=[],
            recordings=recordings.paths,
            truth=truth,
            run=run,
            close_loop=loop.report,
            rerun=rerun,
            close_loop_error=loop.error,
            event_id=recordings.event_id,
            event_reason=recordings.reason,
            refinement=config.refinement,
            rom_seconds=model.seconds,
            rom_built=model.built,
            timings=steps.timings,
        )
        result.pictures = steps.report(result, recordings)
    except DemoError:
        raise
    except (FleetbrakeError, OSError) as error:  # a step could not do its job: say which demo
        raise DemoError(f"demo in {out}: {error}") from error
    steps.timings["total"] = round(time.perf_counter() - began, 2)
    result.summary = summary(result)
    (out / "summary.txt").write_text(result.summary + "\n", encoding="utf-8")
    (out / "timings.json").write_text(json.dumps(steps.timings, indent=2) + "\n", encoding="utf-8")
    return result


def pick_event(db_path: str | Path) -> tuple[str, str, str] | None:
    """The event worth a recording: ``(event_id, wagon_id, why)``.

    The event of the most severe flag tied to one event, else the event inside the most
    severe flag's span with the largest error of the current revision, else the event with
    the largest error overall (RMSE measured - predicted). None without events.
    """
    import duckdb

    from fleetbrake.warehouse.connection import sql

    con = duckdb.connect(str(db_path), read_only=True)
    try:
        errors = con.sql(sql("q_demo_event_errors")).pl()
        flagged = con.sql(sql("q_demo_flagged_events")).pl()
        any_event = con.sql(sql("q_demo_first_event")).fetchall()
    finally:
        con.close()
    rmse = dict(zip(errors["event_id"], errors["rmse_k"], strict=True))
    if flagged.height:
        best = min(
            flagged.iter_rows(named=True),
            key=lambda r: (
                _SEVERITY_RANK.get(r["severity"], 9),
                _KIND_RANK.get(r["kind"], 9),
                r["tied"] is None,
                -(rmse.get(r["event_id"]) or 0.0),
            ),
        )
        article = "an" if best["severity"][0] in "aeiou" else "a"
        return (
            best["event_id"],
            best["wagon_id"],
            f"in {article} {best['severity']} {best['kind']} flag",
        )
    if errors.height:
        top = errors.drop_nulls("rmse_k").sort("rmse_k", descending=True)
        if top.height:
            return (
                top["event_id"][0],
                top["wagon_id"][0],
                f"largest error of revision {top['model_revision'][0]} "
                f"({top['rmse_k'][0]:.2f} K RMSE)",
            )
    if any_event:
        return any_event[0][0], any_event[0][1], "the first event"
    return None
