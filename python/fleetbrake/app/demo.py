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

The output directory holds only this demo's results: an existing one is refused unless
``force``, which wipes it first, and only if it is empty or was made by a demo (it holds
the marker file ``.fleetbrake-demo``), so that results are never mixed and nothing else is
ever deleted.
"""

from __future__ import annotations

import datetime as dt
import json
import shutil
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import rich
from rich.console import Console
from rich.markup import escape

from fleetbrake.app.progress import generation_bar, spinner
from fleetbrake.errors import ConfigError, FleetbrakeError

if TYPE_CHECKING:
    from fleetbrake.app.run import RunReport
    from fleetbrake.flags import FlagReport

__all__ = [
    "DEMO_EFFECT",
    "MARKER",
    "DemoConfig",
    "DemoConfigError",
    "DemoError",
    "DemoExistsError",
    "DemoResult",
    "pick_event",
    "prepare_out_dir",
    "run_demo",
]

DEMO_EFFECT = "convection_speed:gain=2.0,exponent=0.8"
"""The undeclared effect of the demo's fleet: forced convection growing with train speed,
``h(v) = h0 (1 + 2.0 (v / 100 km/h)^0.8)`` on every surface but the friction face."""

MARKER = ".fleetbrake-demo"
"""File written first into the output directory: ``force`` wipes only a directory holding
it (or an empty one)."""

_SEVERITY_RANK = {"alarm": 0, "warning": 1, "info": 2}
_KIND_RANK = {"dragging_brake": 0, "overheating": 1, "weak_brake": 2, "sensor_fault": 3}


class DemoError(FleetbrakeError):
    """The demo cannot run (output directory unusable, a step failed); the message says why."""


class DemoExistsError(DemoError):
    """The output directory holds something already and ``force`` was not given."""


class DemoConfigError(DemoError, ConfigError):
    """A setting of :class:`DemoConfig` is not usable (exit 2); the message names it."""


@dataclass(frozen=True)
class DemoConfig:
    """What the demo generates and how."""

    wagons: int = 4
    """Registered, valid wagons (the generator adds one without a registry entry and one
    with a bad entry, whose files are quarantined)."""
    days: int = 2
    """UTC days of operation; the last is the closed loop's holdout (so at least 2)."""
    seed: int = 7
    effect: str = DEMO_EFFECT
    """The one undeclared effect, ``NAME[:key=value,...]`` as ``fleetbrake synth --effect``."""
    anomalies: bool = True
    start: dt.date = dt.date(2024, 3, 4)
    refinement: float = 1.0
    """Mesh refinement of the reduced model (1.0: the default mesh); every step (generation,
    run, closed loop) uses the model of this refinement."""
    recordings: bool = True

    def __post_init__(self) -> None:
        if self.wagons < 1:
            raise DemoConfigError(f"wagons must be >= 1, got {self.wagons}")
        if self.days < 2:
            raise DemoConfigError(
                f"days must be >= 2 (the last day is held out of the fit), got {self.days}"
            )
        if not self.refinement > 0:
            raise DemoConfigError(f"refinement must be > 0, got {self.refinement}")

    @property
    def holdout_from(self) -> dt.date:
        return self.start + dt.timedelta(days=self.days - 1)


@dataclass
class DemoResult:
    """Everything the demo wrote and found."""

    out_dir: Path
    config: DemoConfig
    fleet_dir: Path
    db_path: Path
    close_loop_json: Path
    close_loop_md: Path
    report: Path
    pictures: list[Path]
    recordings: list[Path]
    truth: Any
    """The generator's :class:`fleetbrake.synth.generator.FleetTruth`."""
    run: RunReport
    """The report of the first run."""
    close_loop: dict[str, Any]
    rerun: RunReport | None
    """The run after the closed loop (flags judged with the new revision), if one was made."""
    close_loop_error: str | None
    event_id: str | None
    event_reason: str | None
    refinement: float
    rom_seconds: float
    rom_built: bool
    timings: dict[str, float] = field(default_factory=dict)
    summary: str = ""

    @property
    def effect_matched(self) -> bool:
        found: str | None = self.close_loop.get("effect")
        return found is not None and set(found.split("+")) == set(self.truth.effects.names)

    def artefacts(self) -> list[tuple[str, Path]]:
        out = [
            ("generated fleet and its truth", self.fleet_dir),
            ("warehouse (DuckDB)", self.db_path),
            ("closed-loop report", self.close_loop_json),
            ("closed-loop report, Markdown", self.close_loop_md),
        ]
        out += [("rerun recording", p) for p in self.recordings]
        out += [("this report", self.report)]
        return [(what, path) for what, path in out if path.exists() or path == self.report]


# --------------------------------------------------------------------------------------------
# The output directory


def prepare_out_dir(out_dir: str | Path, *, force: bool = False) -> Path:
    """Make ``out_dir`` ready for a demo: created if missing; an empty one is used as it is;
    one holding anything is refused (:class:`DemoExistsError`) unless ``force``, and then
    wiped only if it holds the demo marker. Writes the marker."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DemoError(f"{out}: exists and is not a directory; give another --out")
    if out.is_dir() and any(out.iterdir()):
        marked = (out / MARKER).is_file()
        if not force and marked:
            raise DemoExistsError(
                f"{out}: already holds the results of an earlier demo, and results are never "
                "mixed: give --force to wipe it and run again, or another --out"
            )
        if not force:
            raise DemoExistsError(
                f"{out}: already holds files that are not a demo's; give an empty or new "
                "directory as --out"
            )
        if not marked:
            raise DemoExistsError(
                f"{out}: holds files but no {MARKER} marker, so it was not made by "
                "`fleetbrake demo`; --force wipes only a demo's directory: give an empty or "
                "new directory as --out"
            )
        resolved = out.resolve()
        if resolved == Path.cwd().resolve() or resolved in Path.cwd().resolve().parents:
            raise DemoError(f"{out}: is the current directory or holds it; not wiping it")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text(
        "Made by `fleetbrake demo`; `fleetbrake demo --force` may wipe this directory.\n",
        encoding="utf-8",
    )
    return out


# --------------------------------------------------------------------------------------------
# Helpers


def _seconds(value: float) -> str:
    if value < 90:
        return f"{value:.0f} s"
    return f"{int(value // 60)} min {value % 60:02.0f} s"


def _rom(refinement: float, console: Console, show: bool) -> tuple[float, bool]:
    """Load (or build and cache) the reduced model of the synthetic fleet's block: the
    generator's wagons all have the reference block and sensor seat."""
    from fleetbrake.fleet.registry import WagonConfig
    from fleetbrake.model.rom import ReducedModel, default_cache_dir

    began = time.perf_counter()
    text = (
        f"reduced thermal model (refinement {refinement:g}): loading from "
        f"{default_cache_dir()}, or building it once (about a minute at the default mesh)"
    )
    with spinner(text, show, console):
        ReducedModel.for_wagon(WagonConfig(wagon_id="SGG-0001"), refinement=refinement)
    seconds = time.perf_counter() - began
    return seconds, seconds > 3.0


def _generate(fleet_dir: Path, config: DemoConfig, console: Console, show: bool) -> Any:
    from fleetbrake.model.effects import EffectSet, parse_effect
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

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
    with generation_bar(total, show, console) as step:
        return generate_fleet(fleet_dir, synth, progress=step)


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


def _flag_counts(flag_report: FlagReport | None) -> str:
    if flag_report is None:
        return "not raised"
    counts = Counter(f.kind for f in flag_report.flags)
    if not counts:
        return "none"
    return (
        f"{sum(counts.values())} (" + ", ".join(f"{k} {n}" for k, n in sorted(counts.items())) + ")"
    )


def _found_anomalies(db_path: Path, truth: Any) -> tuple[int, list[str]]:
    """How many injected anomalies a flag of the same kind overlaps (15 min slack), and the
    missed ones described."""
    import duckdb

    from fleetbrake.warehouse.connection import sql

    con = duckdb.connect(str(db_path), read_only=True)
    try:
        flags = con.sql(sql("q_demo_flag_spans")).fetchall()
    finally:
        con.close()
    slack = dt.timedelta(minutes=15)
    found, missed = 0, []
    for a in truth.anomalies:
        if any(
            w == a.wagon_id and k == a.kind and s <= a.end_utc + slack and e >= a.start_utc - slack
            for w, k, s, e in flags
        ):
            found += 1
        else:
            kind = a.kind + (f" ({a.subtype})" if a.subtype else "")
            missed.append(f"{a.wagon_id} {kind} {a.start_utc:%m-%d %H:%M}")
    return found, missed


# --------------------------------------------------------------------------------------------
# The demo


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
    from fleetbrake.app.report import write_report
    from fleetbrake.app.run import run_fleet
    from fleetbrake.closeloop.loop import CloseLoopConfig, CloseLoopError, run_close_loop
    from fleetbrake.simulation.predictions import SimulationConfig
    from fleetbrake.viz.record import record

    config = config or DemoConfig()
    console = console or rich.get_console()
    show = console.is_terminal if progress is None else progress
    began = time.perf_counter()
    timings: dict[str, float] = {}
    out = prepare_out_dir(out_dir, force=force)
    fleet_dir, db_path = out / "fleet", out / "fleet.duckdb"
    close_json = out / "close-loop.json"

    def step(number: int, text: str) -> None:
        console.print(
            f"[bold]\\[{number}/7][/bold] {escape(text)}", highlight=False, soft_wrap=True
        )

    def clock(name: str, t0: float) -> None:
        timings[name] = round(time.perf_counter() - t0, 2)

    refinement = config.refinement
    simulation = SimulationConfig(refinement=refinement)  # every step on the same model
    try:
        step(1, f"reduced thermal model of the block (refinement {refinement:g})")
        rom_seconds, rom_built = _rom(refinement, console, show)
        timings["model"] = round(rom_seconds, 2)
        console.print(
            f"    {'built and cached' if rom_built else 'loaded from the cache'} "
            f"in {_seconds(rom_seconds)}",
            highlight=False,
            soft_wrap=True,
        )

        step(
            2,
            f"generating {_n(config.wagons, 'wagon')} x {config.days} days "
            f"(seed {config.seed}) "
            f"with an undeclared effect and anomalies into {fleet_dir}",
        )
        t0 = time.perf_counter()
        truth = _generate(fleet_dir, config, console, show)
        clock("generate", t0)

        step(3, "fleetbrake run: ingest, detect events, simulate them, raise flags")
        t0 = time.perf_counter()
        run = run_fleet(fleet_dir, db_path, simulation=simulation, progress=show)
        clock("run", t0)
        console.print(
            f"    {len(run.ingest.ingested)} files ingested, "
            f"{len(run.ingest.quarantined)} quarantined, "
            f"{run.simulation.events_simulated} events simulated, "
            f"flags: {_flag_counts(run.flags)}",
            highlight=False,
            soft_wrap=True,
        )

        step(
            4,
            f"fleetbrake close-loop: fit before {config.holdout_from}, hold that day out "
            "(the longest step)",
        )
        t0 = time.perf_counter()
        loop_error = None
        try:
            with spinner("finding the effect the model lacks", show, console):
                loop = run_close_loop(
                    db_path,
                    config.holdout_from,
                    close_json,
                    config=CloseLoopConfig(config.holdout_from, simulation=simulation),
                )
        except CloseLoopError as error:  # e.g. every fit event flagged: say so, go on
            loop, loop_error = {}, str(error)
        clock("close_loop", t0)
        said = _loop_line(loop) if loop_error is None else f"could not run: {loop_error}"
        console.print(f"    {said}", highlight=False, soft_wrap=True)

        rerun = None
        if loop.get("new_revision"):
            step(5, f"flags judged again with revision {loop['new_revision']}")
            t0 = time.perf_counter()
            rerun = run_fleet(fleet_dir, db_path, simulation=simulation, progress=show)
            clock("flags_again", t0)
            console.print(
                f"    flags: {_flag_counts(rerun.flags)}", highlight=False, soft_wrap=True
            )
        else:
            step(5, "no effect added: the flags stand")

        recordings: list[Path] = []
        picked = pick_event(db_path)
        event_id = reason = None
        if config.recordings and picked is not None:
            event_id, wagon_id, reason = picked
            step(6, f"rerun recordings of wagon {wagon_id} and of event {event_id}")
            t0 = time.perf_counter()
            rec_dir = out / "recordings"
            with spinner("writing recordings", show, console):
                recordings.append(
                    record(db_path, wagon_id, rec_dir / f"{wagon_id}-timeline.rrd").out
                )
                recordings.append(
                    record(db_path, wagon_id, rec_dir / f"{event_id}.rrd", event_id=event_id).out
                )
            clock("record", t0)
        else:
            step(6, "no recordings")

        step(7, "the report")
        t0 = time.perf_counter()
        result = DemoResult(
            out_dir=out,
            config=config,
            fleet_dir=fleet_dir,
            db_path=db_path,
            close_loop_json=close_json,
            close_loop_md=close_json.with_suffix(".md"),
            report=out / "report.md",
            pictures=[],
            recordings=recordings,
            truth=truth,
            run=run,
            close_loop=loop,
            rerun=rerun,
            close_loop_error=loop_error,
            event_id=event_id,
            event_reason=reason,
            refinement=refinement,
            rom_seconds=rom_seconds,
            rom_built=rom_built,
            timings=timings,
        )
        notes = [
            f"Synthetic fleet of the demo: {_n(config.wagons, 'wagon')} x {config.days} "
            f"days, seed {config.seed}, undeclared effect `{truth.effects}`"
            + (", with anomalies" if config.anomalies else "")
            + f"; reduced model at refinement {refinement:g}. "
            f"Closed loop fitted before {config.holdout_from}, that day held out."
        ]
        if event_id is not None:
            notes.append(
                f"Recordings: wagon {picked[1] if picked else '-'} and event "
                f"`{event_id}` ({reason}); open them with `rerun FILE.rrd`."
            )
        if loop_error is not None:
            notes.append(f"The closed loop could not run: {loop_error}.")
        written = write_report(
            db_path,
            out,
            close_loop=loop or None,
            truth=truth,
            artefacts=[(w, p.relative_to(out)) for w, p in result.artefacts()],
            title="fleetbrake demo report",
            notes=notes,
        )
        result.pictures = written.pictures
        clock("report", t0)
    except DemoError:
        raise
    except (FleetbrakeError, OSError) as error:  # a step could not do its job: say which demo
        raise DemoError(f"demo in {out}: {error}") from error
    timings["total"] = round(time.perf_counter() - began, 2)
    result.summary = summary(result)
    (out / "summary.txt").write_text(result.summary + "\n", encoding="utf-8")
    (out / "timings.json").write_text(json.dumps(timings, indent=2) + "\n", encoding="utf-8")
    return result


def _loop_line(loop: dict[str, Any]) -> str:
    if not loop.get("new_revision"):
        return "no significant effect is missing: nothing added"
    params = ", ".join(f"{k} {v:.3g}" for k, v in loop.get("parameters", {}).items())
    hold = loop.get("holdout", {})
    return (
        f"added {loop['effect']} ({params}) as {loop['new_revision']}; holdout RMSE "
        f"{_k(hold.get('rmse_before_k'))} -> {_k(hold.get('rmse_after_k'))}"
    )


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def _k(value: Any) -> str:
    return "-" if value is None else f"{value:.2f} K"


def summary(result: DemoResult) -> str:
    """The demo's outcome for people: what was made, found and written, and how long it took."""
    truth, run, loop, config = result.truth, result.run, result.close_loop, result.config
    ingest = run.ingest
    by_wagon = Counter(r.wagon_id or "?" for r in ingest.quarantined)
    ok = {w.wagon_id for w in truth.wagons if w.registry == "ok"}
    registered = len(ok)
    made = sum(1 for e in truth.events if e.recorded and e.wagon_id in ok)
    lines = [
        "fleetbrake demo",
        "",
        f"fleet       {_n(config.wagons, 'wagon')} x {config.days} days from {config.start} "
        f"(seed {config.seed}); {len(truth.wagons)} wagons wrote logs ({registered} registered "
        f"and valid, the others have no or a bad registry entry); {len(truth.files)} log files",
        f"hidden      undeclared effect {truth.effects}; {len(truth.anomalies)} anomalies injected"
        if config.anomalies
        else f"hidden      undeclared effect {truth.effects}; no anomalies",
        f"model       reduced model at refinement {result.refinement:g}"
        + (" (the default mesh)" if result.refinement == 1.0 else " (coarser than the default)")
        + f", {'built' if result.rom_built else 'loaded from the cache'} in "
        f"{_seconds(result.rom_seconds)}",
        f"ingested    {len(ingest.ingested)} files ({ingest.rows:,} rows); quarantined "
        f"{len(ingest.quarantined)}"
        + (
            " (" + ", ".join(f"{w}: {n}" for w, n in sorted(by_wagon.items())) + ")"
            if by_wagon
            else ""
        ),
        f"events      {run.simulation.events_simulated} simulated of "
        f"{ingest.events.total if ingest.events else '?'} detected "
        f"(the generator made {made} brakings in the logs of the registered wagons)",
        f"flags       declared model: {_flag_counts(run.flags)}",
    ]
    if result.rerun is not None:
        lines.append(
            f"            after the closed loop ({loop['new_revision']}): "
            f"{_flag_counts(result.rerun.flags)}"
        )
    if truth.anomalies:
        flagged, missed = _found_anomalies(result.db_path, truth)
        lines.append(
            f"            injected anomalies flagged: {flagged} of {len(truth.anomalies)}"
            + (f"; missed: {'; '.join(missed)}" if missed else "")
        )
    if result.close_loop_error is not None:
        lines.append(f"closed loop could not run: {result.close_loop_error}")
    fit, hold = loop.get("fit", {}), loop.get("holdout", {})
    lines += [
        f"closed loop fit {fit.get('events', 0)} events before {config.holdout_from}, "
        f"holdout {hold.get('events', 0)} events on it",
        f"            RMSE fit {_k(fit.get('rmse_before_k'))} -> {_k(fit.get('rmse_after_k'))}, "
        f"holdout {_k(hold.get('rmse_before_k'))} -> {_k(hold.get('rmse_after_k'))}",
    ]
    if loop.get("new_revision"):
        params = ", ".join(f"{k} = {v:.3g}" for k, v in loop.get("parameters", {}).items())
        lines.append(f"            found {loop['effect']} ({params}) -> {loop['new_revision']}")
    else:
        lines.append("            found nothing significant to add")
    true_params = "; ".join(
        f"{e.name} (" + ", ".join(f"{k} = {v:.3g}" for k, v in e.parameters.items()) + ")"
        for e in truth.effects
    )
    found = set((loop.get("effect") or "").split("+")) - {""}
    extra = sorted(found - set(truth.effects.names))
    if result.effect_matched:
        verdict = "MATCHED"
    elif found & set(truth.effects.names):
        verdict = f"PARTLY matched (the true effect, with {' + '.join(extra)} on top)"
    else:
        verdict = "NOT matched"
    lines.append(f"            truth {true_params}: {verdict}")
    lines += ["", "written"]
    for what, path in result.artefacts():
        lines.append(f"  {path}  ({what})")
    for png in result.pictures:
        lines.append(f"  {png}")
    if result.event_id:
        lines.append(f"  (the event recording: {result.event_reason})")
    steps = ", ".join(
        f"{name.replace('_', ' ')} {_seconds(t)}"
        for name, t in result.timings.items()
        if name != "total"
    )
    total = result.timings.get("total", sum(result.timings.values()))
    lines += ["", f"took {_seconds(total)} ({steps})"]
    lines.append(f"read {result.report} first; open a recording with `rerun FILE.rrd`")
    return "\n".join(lines)


def print_summary(result: DemoResult, console: Console | None = None) -> None:
    (console or rich.get_console()).print(escape(result.summary), highlight=False, soft_wrap=True)
