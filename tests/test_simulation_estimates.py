"""The estimation stage's reads, writes and engine: the wagons' samples read a chunk
of whole wagons per query and cut as the per-wagon query reads them, the rows committed in
bulk on a writer thread while the work goes on, the revision's sigma_w fitted wagon by wagon
on the engine; the rows the same as the per-wagon path's, bit for bit."""

from __future__ import annotations

import dataclasses
import json
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import polars as pl
import pytest

from fleetbrake.engine import LocalEngine
from fleetbrake.simulation import estimates as e
from fleetbrake.simulation.store import WriteBehind
from fleetbrake.warehouse.connection import open_warehouse, reader


@dataclass(frozen=True)
class Fleet:
    path: Path
    db: Path
    """Ingested, events detected and simulated; not estimated."""
    registry: Any
    config: e.EstimationConfig


@pytest.fixture(scope="module")
def fleet(
    tmp_path_factory: pytest.TempPathFactory,
    reduced_model_for: Callable[..., Any],
    rom_cache_dir: Path,
    rom_refinement: float,
) -> Iterator[Fleet]:
    """3 wagons (and the generator's unregistered one) x 1 day with the anomalies, through
    the simulation stage."""
    from fleetbrake.ingest.events import update_events
    from fleetbrake.ingest.files import load_fleet_registry, run_ingest
    from fleetbrake.simulation.config import SimulationConfig
    from fleetbrake.simulation.predictions import (
        current_revision,
        simulate_events,
        store_registry,
    )
    from fleetbrake.synth.generator import SynthConfig, generate_fleet

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        out = tmp_path_factory.mktemp("estimate-io")
        generate_fleet(out / "fleet", SynthConfig(wagons=3, days=1, seed=1), rom=reduced_model_for)
        run_ingest(out / "fleet", out / "fleet.duckdb", progress=False)
        registry = load_fleet_registry(out / "fleet")
        sim = SimulationConfig(refinement=rom_refinement)
        with open_warehouse(out / "fleet.duckdb") as wh:
            update_events(wh)
            store_registry(wh, registry)
            rev = current_revision(wh, sim.solver, sim.refinement)
            simulate_events(wh, registry, rev, sim, progress=False)
        yield Fleet(
            out / "fleet", out / "fleet.duckdb", registry, e.EstimationConfig(chain=sim.chain)
        )


def _copy(fleet: Fleet, tmp_path: Path, name: str) -> Path:
    db = tmp_path / f"{name}.duckdb"
    shutil.copy(fleet.db, db)
    return db


def _rows(db: Path) -> dict[str, pl.DataFrame]:
    con = duckdb.connect(str(db), read_only=True)
    try:
        return {
            "contact_estimates": con.sql(
                "SELECT * FROM contact_estimates ORDER BY wagon_id, time_utc"
            ).pl(),
            "estimated_spans": con.sql(
                "SELECT * EXCLUDE (created_utc) FROM estimated_spans "
                "ORDER BY wagon_id, span_start_utc"
            ).pl(),
        }
    finally:
        con.close()


def _spans(wh: object, fleet: Fleet) -> list[object]:
    from fleetbrake.ingest.spans import stored_spans

    return [s for s in stored_spans(wh) if s.wagon_id in fleet.registry.wagons]  # type: ignore[arg-type]


def test_the_chunk_holds_the_partitions_the_per_span_query_reads(fleet: Fleet) -> None:
    """One query for several spans' samples, cut per span (``chunk_tasks``), gives each
    span the very table ``estimate_task`` reads with a query of its own."""
    with open_warehouse(fleet.db, read_only=True) as wh:
        from fleetbrake.simulation.predictions import revision

        rev = revision(wh, "declared")
        spans = _spans(wh, fleet)
        assert len(spans) >= 3
        todo = [(fleet.registry.wagons[s.wagon_id], s, "model") for s in spans]  # type: ignore[attr-defined]
        chunk = e.estimation_chunk(wh, todo, rev, fleet.config, 3.0)
        assert str(chunk).startswith("spans ")
        tasks = e.chunk_tasks(chunk)
        for task, (wagon, span, model) in zip(tasks, todo, strict=True):
            alone = e.estimate_task(wh, wagon, span, rev, fleet.config, 3.0, model_key=model)  # type: ignore[arg-type]
            assert task.samples.num_rows > 10_000
            assert task.samples.equals(alone.samples), wagon.wagon_id
            assert dataclasses.replace(task, samples=alone.samples) == alone


def test_the_stage_stores_what_the_per_wagon_path_computes_whatever_the_chunks(
    fleet: Fleet, tmp_path: Path, rom_cache_dir: Path
) -> None:
    """The stage's rows, read by chunks and committed in bulk, are bit for bit those of each
    wagon's own task estimated alone (the path before chunks), and the same whether the
    chunks and transactions hold one wagon or all."""
    from fleetbrake.simulation.predictions import revision

    stored = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        for name, config in (
            ("default", fleet.config),
            ("by_one", dataclasses.replace(fleet.config, chunk_rows=1, batch_rows=1)),
        ):
            db = _copy(fleet, tmp_path, name)
            with open_warehouse(db) as wh:
                rev = revision(wh, "declared")
                report = e.estimate_wagons(wh, fleet.registry, rev, config, progress=False)
                assert len(report.wagons_estimated) == 3 and report.rows > 30_000
                assert len(report.spans_estimated) >= 3
            stored[name] = _rows(db)
        with open_warehouse(fleet.db, read_only=True) as wh:
            rev = revision(wh, "declared")
            alone = [
                e.estimate_wagon(
                    e.estimate_task(
                        wh,
                        fleet.registry.wagons[s.wagon_id],  # type: ignore[attr-defined]
                        s,  # type: ignore[arg-type]
                        rev,
                        fleet.config,
                        fleet.config.power_noise_w_per_sqrt_s,
                        model_key="-",
                    )
                )
                for s in _spans(wh, fleet)
            ]
    frames = [pl.DataFrame(pl.from_arrow(r.rows)) for r in alone]
    expected = pl.concat(frames).sort("wagon_id", "time_utc")
    got = stored["default"]["contact_estimates"]
    assert got.height == expected.height
    assert got["resolution_s"].unique().to_list() == [1]  # the stage stores every second
    got = got.drop("resolution_s")
    assert got.equals(expected.select(got.columns))  # every value, nulls and all
    for table in ("contact_estimates", "estimated_spans"):
        assert stored["by_one"][table].equals(stored["default"][table]), table
    seconds = stored["default"]["estimated_spans"].select("wagon_id", "seconds").rows()
    assert seconds == [(r.wagon_id, r.seconds) for r in alone]


def test_a_wagon_with_stray_rows_is_replaced_and_the_others_only_inserted(
    fleet: Fleet, tmp_path: Path, rom_cache_dir: Path
) -> None:
    """A span with rows left over (no record of them in ``estimated_spans``, as a crashed
    older writer left them) has them replaced, not doubled."""
    from fleetbrake.simulation.predictions import revision

    reference = _copy(fleet, tmp_path, "reference")
    db = _copy(fleet, tmp_path, "stray")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        with open_warehouse(reference) as wh:
            e.estimate_wagons(wh, fleet.registry, revision(wh, "declared"), fleet.config)
        with open_warehouse(db) as wh:
            rev = revision(wh, "declared")
            wh.con.execute(f"ATTACH '{reference}' AS ref (READ_ONLY)")
            wh.con.execute(  # a wagon's first hour, as a crashed older writer left it
                "INSERT INTO contact_estimates SELECT * FROM ref.contact_estimates "
                "WHERE wagon_id = 'SGG-0002' ORDER BY time_utc LIMIT 3600"
            )
            wh.con.execute("DETACH ref")
            e.estimate_wagons(
                wh, fleet.registry, rev, dataclasses.replace(fleet.config, batch_rows=1)
            )
    assert _rows(db)["contact_estimates"].equals(_rows(reference)["contact_estimates"])


def test_the_revisions_sigma_w_is_fitted_on_the_engine_as_in_the_parent(
    fleet: Fleet, tmp_path: Path, rom_cache_dir: Path
) -> None:
    """``fit_revision_noise(engine=...)``: each wagon's likelihood fit runs as a partition
    on the workers; what is stored is what the fits in this process give."""
    from fleetbrake.simulation.predictions import revision

    config = dataclasses.replace(fleet.config, noise_fit_s=3_600.0)
    found = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        with LocalEngine(2) as engine:
            for name, on in (("inline", None), ("local", engine)):
                db = _copy(fleet, tmp_path, name)
                with open_warehouse(db) as wh:
                    rev = revision(wh, "declared")
                    events = wh.con.sql("SELECT wagon_id, start_utc FROM events").pl()
                    found[name] = e.fit_revision_noise(
                        wh, fleet.registry, rev, events, config, engine=on
                    )
                    assert e.stored_noise(wh, rev.name) == found[name]
    assert found["inline"] is not None and found["inline"].method == "ml"
    assert found["local"] == found["inline"]
    assert found["inline"].fit_wagons is not None
    assert len(json.loads(found["inline"].fit_wagons)) >= 2  # wagons fitted apart


def _full_search(
    problems: Any, config: Any, measurement_k: float, lo: float, hi: float, tolerance: float
) -> tuple[float, float, int]:
    """The reference: the bounded scalar search over ``lo`` .. ``hi`` and then the floor,
    without the shortcut at the floor: log σ_w, the negative log likelihood, passes."""
    import numpy as np
    from scipy.optimize import minimize_scalar

    from fleetbrake.model import estimator as m

    passes = 0

    def f(z: float) -> float:
        nonlocal passes
        passes += 1
        noise = m.EstimatorNoise(measurement_k, float(np.exp(np.clip(z, lo, hi))), None)
        raws = m.run_kernel(problems, noise, smooth=False, config=config, outputs=False)
        return -float(sum(raw.log_likelihood for raw in raws))

    result = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": tolerance})
    floor = f(lo)
    if floor <= float(result.fun):
        return lo, floor, passes
    return float(np.clip(result.x, lo, hi)), float(result.fun), passes


@pytest.mark.parametrize("misfit", [False, True])
def test_sigma_w_at_its_floor_takes_two_passes_and_the_full_searchs_answer(
    fleet: Fleet, rom_cache_dir: Path, misfit: bool
) -> None:
    """``fit_wagon_noise``'s σ_w: when the floor is at least as likely as a step of the
    tolerance above it, two filter passes (the bounded search took 18, five fit wagons 90 a
    revision) and the floor, which the full search finds too (to its tolerance, ``at_floor``
    the same); a revision that misfits (its friction heat halved) needs more than the floor, and
    gets the full search's answer bit for bit."""
    import math

    import numpy as np

    from fleetbrake.model.effects import EffectSet, HeatPartitionEffusivity
    from fleetbrake.model.estimator import noise as model_noise
    from fleetbrake.simulation.estimates import noise as stage_noise
    from fleetbrake.simulation.predictions import Revision, revision
    from fleetbrake.simulation.store import chunk_table, sample_parts

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        with open_warehouse(fleet.db, read_only=True) as wh:
            base = revision(wh, "declared")
            events = wh.con.sql("SELECT wagon_id, start_utc FROM events").pl()
            wagon_id = min(w for w in events["wagon_id"] if w in fleet.registry.wagons)
            samples = chunk_table(wh, "q_simulation_chunk_samples", [wagon_id])
        effects = EffectSet((HeatPartitionEffusivity(contact_factor=0.5),) if misfit else ())
        rev = Revision("r", effects, base.solver, base.refinement)
        days = tuple(sorted({s.date() for w, s in events.iter_rows() if w == wagon_id}))
        config = dataclasses.replace(fleet.config, noise_fit_s=3_600.0)
        task = e.NoiseFitTask(
            fleet.registry.wagons[wagon_id],
            sample_parts(samples, [wagon_id])[wagon_id],
            days,
            rev,
            config,
        )
        seen: dict[str, Any] = {}
        passes = [0]
        run, fit_noise = model_noise.run_kernel, stage_noise.fit_noise

        def counted(*args: Any, **kwargs: Any) -> Any:
            passes[0] += 1
            return run(*args, **kwargs)

        def kept(problems: Any, **kwargs: Any) -> Any:
            seen.update(problems=problems, **kwargs)
            return fit_noise(problems, **kwargs)

        mp.setattr(model_noise, "run_kernel", counted)
        mp.setattr(stage_noise, "fit_noise", kept)
        found = e.fit_wagon_noise(task)
        mp.undo()
    assert found is not None
    fit = found.fit
    lo = math.log(config.min_power_noise_w_per_sqrt_s)
    hi = math.log(1.0e4)
    z, nll, full_passes = _full_search(
        seen["problems"], seen["config"], seen["measurement_k"], lo, hi, 0.005
    )
    assert fit.evaluations == passes[0]
    z_found = math.log(fit.noise.power_w_per_sqrt_s)
    if not misfit:
        assert fit.power_noise_at_floor and z == lo, (z_found, z)
        assert passes[0] == 2 and full_passes == 18
        assert fit.noise.power_w_per_sqrt_s == math.exp(lo)
        assert fit.log_likelihood == -nll
    else:
        assert not fit.power_noise_at_floor and z > lo + 0.01, (z_found, z)
        assert passes[0] == full_passes + 1  # the step above the floor, then the search
        assert z_found == z and fit.log_likelihood == -nll
    assert abs(z_found - z) <= 0.005
    assert fit.power_noise_at_floor == (z <= lo + 2 * 0.005)
    assert np.isfinite(fit.log_likelihood)


def test_a_state_dependent_revisions_filtered_passes_are_the_smoothed_ones_without_smoothing(
    fleet: Fleet, rom_cache_dir: Path
) -> None:
    """``fit_wagon_noise`` evaluates a fade on the first estimate's filtered contact, which it
    takes from filter-only passes (``wagon_estimate(smooth=False)``): their filtered values, and so
    their number of passes and the fit, are those of the smoothed estimate, bit for bit; and
    ``estimate_contact`` iterates a fade on filter-only passes, smoothing only the last one."""
    import numpy as np

    from fleetbrake.model.effects import EffectSet, FrictionTemperature
    from fleetbrake.model.estimator import estimates as m
    from fleetbrake.simulation.estimates.wagon import wagon_estimate
    from fleetbrake.simulation.predictions import Revision, revision

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLEETBRAKE_CACHE_DIR", str(rom_cache_dir))
        with open_warehouse(fleet.db, read_only=True) as wh:
            base = revision(wh, "declared")
            span = _spans(wh, fleet)[0]
            wagon = fleet.registry.wagons[span.wagon_id]  # type: ignore[attr-defined]
            task = e.estimate_task(wh, wagon, span, base, fleet.config, 3.0, model_key="")  # type: ignore[arg-type]
        rev = Revision(
            "fade",
            EffectSet((FrictionTemperature(fade_per_k=2.0e-3),)),
            base.solver,
            base.refinement,
        )
        series, _ = e.estimator_series(
            wagon,
            pl.DataFrame(pl.from_arrow(task.samples)),
            fleet.config.chain,
            config=fleet.config,
        )
        noise = e.wagon_noise(series, fleet.config, 3.0)
        calls: dict[bool, list[bool]] = {True: [], False: []}
        run = m.estimate
        found = {}
        for smooth in (True, False):

            def counted(*args: Any, _to: list[bool] = calls[smooth], **kwargs: Any) -> Any:
                _to.append(kwargs["smooth"])
                return run(*args, **kwargs)

            mp.setattr(m, "estimate", counted)
            found[smooth] = wagon_estimate(wagon, series, rev, fleet.config, noise, smooth=smooth)
    smoothed, filtered = found[True], found[False]
    assert smoothed is not None and filtered is not None
    # the fade iterated on filter-only passes; the smoothed estimate smooths the last once more
    assert calls[False] == [False] * len(calls[False]) and len(calls[False]) >= 2
    assert calls[True] == calls[False] + [True]
    assert filtered.smoothed_contact_mean_c is None
    for name in ("contact_mean_c", "contact_mean_sd_k", "innovation_k", "innovation_var_k2"):
        assert np.array_equal(getattr(filtered, name), getattr(smoothed, name), equal_nan=True)
    assert filtered.log_likelihood == smoothed.log_likelihood


def test_write_behind_commits_in_order_on_its_thread_and_raises_a_writes_error() -> None:
    """``WriteBehind``: batches written one at a time, in order, off the caller's thread;
    the caller goes on while one is written; a failed write raises at the next submit or at
    the end of the block."""
    written: list[int] = []
    threads: set[str] = set()
    started = threading.Event()

    def write(batch: int) -> None:
        threads.add(threading.current_thread().name)
        started.set()
        time.sleep(0.05)
        written.append(batch)

    with WriteBehind(write) as writer:
        writer.submit(1)
        assert started.wait(5)
        assert written == []  # the caller is not held while batch 1 is written
        for batch in (2, 3, 4):
            writer.submit(batch)
    assert written == [1, 2, 3, 4]
    assert threads and threading.current_thread().name not in threads

    def fail(batch: int) -> None:
        raise ValueError(f"batch {batch}")

    with pytest.raises(ValueError, match="batch 1"), WriteBehind(fail) as failing:
        failing.submit(1)
        failing.submit(2)
    with pytest.raises(ValueError, match="batch 7"), WriteBehind(fail) as failing:
        failing.submit(7)


def test_a_reader_sees_what_was_committed_while_the_writer_holds_a_transaction(
    tmp_path: Path,
) -> None:
    """``reader``: a second connection to the same database, usable while the writer's
    connection is inside a transaction on another thread."""
    with open_warehouse(tmp_path / "w.duckdb") as wh:
        wh.con.execute("CREATE TABLE t AS SELECT range AS k FROM range(10)")
        with reader(wh) as source, wh.transaction() as con:
            con.execute("INSERT INTO t SELECT range FROM range(10, 20)")
            assert source.con.execute("SELECT count(*) FROM t").fetchall() == [(10,)]
        with reader(wh) as source:
            assert source.con.execute("SELECT count(*) FROM t").fetchall() == [(20,)]


def test_the_stage_estimates_with_the_configured_quiet_noise_and_keys_on_it() -> None:
    """The stage's noise when none is given is the wagon's σ_v and the revision's σ_w with
    the rest of ``config.estimator.noise`` (σ_q): a σ_q set there is used, not the class's
    default, and the stored estimates' key changes with it (a warehouse is estimated again)."""
    import numpy as np

    from fleetbrake.fleet.registry import WagonConfig
    from fleetbrake.model.estimator import EstimatorConfig, EstimatorNoise, WagonSeries
    from fleetbrake.simulation.estimates.stage import model_key
    from fleetbrake.simulation.predictions import Revision

    rng = np.random.default_rng(3)
    time_s = np.arange(600.0)
    series = WagonSeries.of(
        time_s=time_s,
        p_bar=np.zeros(600),
        speed_kmh=np.zeros(600),
        ambient_c=np.full(600, 10.0),
        reading_c=20.0 + rng.normal(0.0, 0.1, 600),
        wagon_id="SGG-0001",
    )
    default = e.EstimationConfig()
    quiet = e.EstimationConfig(
        estimator=EstimatorConfig(noise=EstimatorNoise(quiet_power_w_per_sqrt_s=0.05))
    )
    found = {c: e.wagon_noise(series, c, 7.0) for c in (default, quiet)}
    assert found[default].quiet_power_w_per_sqrt_s == EstimatorNoise().quiet_power_w_per_sqrt_s
    assert found[quiet].quiet_power_w_per_sqrt_s == 0.05
    for noise in found.values():  # σ_v the wagon's, σ_w the revision's, whatever σ_q
        assert noise.measurement_k == found[default].measurement_k
        assert 0.08 < noise.measurement_k < 0.12
        assert noise.power_w_per_sqrt_s == 7.0
    wagon, rev = WagonConfig("SGG-0001"), Revision("declared")
    keys = {c: model_key(wagon, rev, c, 7.0) for c in (default, quiet)}
    assert keys[default] != keys[quiet]
    assert keys[default] == model_key(wagon, rev, e.EstimationConfig(), 7.0)
