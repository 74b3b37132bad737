"""The close loop's fit events cached as arrays, evaluated for any effects in a few kernel calls.

::

    from fleetbrake.closeloop.fitdata import FitData

    data = FitData.build(loaded, wagons, events, sim, base)   # once per run
    r = data.residual(effects)        # measured - predicted at data.seconds, NaN: no prediction
    rs = data.residuals([e1, e2, e3]) # several parameter vectors (a finite-difference Jacobian)

What a candidate's evaluation needs that does not depend on its effects is computed once, when
the data is built (the same steps, with the same public functions, as
:func:`fleetbrake.simulation.batched.simulate_span_batched`): for every span holding a fit
event, its segments and event windows (:func:`~fleetbrake.simulation.chains.segment_bounds`,
:func:`~fleetbrake.simulation.chains.event_windows`), the trusted readings, the running-median
speed, the pieces of the chain (segments, coarse gap grids, window continuations) and the
declared loading of every sample before the effects
(:func:`fleetbrake.model.timeline.drive_inputs`: pointwise in the samples, so the effects can
be applied to the cached inputs). An evaluation applies the effects to those inputs in numpy,
forms each step's flux and air, has each step's convection and step system made in one Rust
pass (:func:`~fleetbrake.model.romchain.chain_convection`: the step means gathered, a
convection varying inside a piece rounded to ``H_QUANTUM_W_M2K``, piece by piece), and runs
each span's chain in one call of the reduced model's chain kernel with the two output rows it
reads, the sensor and the face mean, summed only at the seconds read (the fit seconds and
those the anchoring reads; every second for a state-dependent effect, whose next pass reads
the face mean): :func:`~fleetbrake.model.romchain.simulate_chain_sensor`, those of
:meth:`~fleetbrake.model.rom.ReducedModel.simulate_chain` bit for bit at those seconds; the
windows' sensor predictions are read at the cached seconds. An input the
effects leave as declared (the flux and the air under a convection law; every input of the
declared model) is turned into steps once per span and reused. No database, no polars frame, no
Python per event: equal to :func:`~fleetbrake.simulation.predictions.predict_wagon` to rounding
(a test holds it to 1e-9 K).

The seconds (:attr:`FitData.seconds`) are those of the wanted events' windows with a valid
measurement, in the order ``predict_wagon`` gives them (wagon, span, window, second); each
carries its event, its block (wagon-day, :attr:`FitData.blocks`), its chain (the span,
:attr:`FitData.chains`) and the drivers the evidence reads (speed, pressure, heat input with the
base effects, air, heating or cooling).

An effect depending on the block's temperature (friction fade) is solved by fixed-point
iteration over the whole chain, each pass one kernel call (the same fixed point as the
simulation's run-by-run iteration, to its tolerance). What the kernel cannot run (the full
model, a ``uniform`` initial state, a window starting on a coarse gap segment) is evaluated
with ``predict_wagon`` itself, wagon by wagon, and read at the same seconds.

A :class:`FitData` pickles without its models (a worker makes them, or reads them from the
reduced-model cache, once per process): an engine's workers get the data once each
(:func:`store` / :func:`stored`). Inside :func:`parallel` an evaluation runs its spans on
threads of this process (the kernel releases the GIL; a span's effect sets in order on one
thread: the same results bit for bit): the close loop's own process evaluates so while the
engine's workers are idle (a single fit, the interval terms).
"""

from __future__ import annotations

import contextlib
import pickle
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from fleetbrake.closeloop.spans import Span, prepare_span, steps_of
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.chaintypes import ChainPieces
from fleetbrake.model.effects import EffectSet
from fleetbrake.model.rom import ReducedModel
from fleetbrake.model.romchain import chain_convection, simulate_chain_sensor
from fleetbrake.model.timeline import H_QUANTUM_W_M2K
from fleetbrake.simulation.chains import Model, chain_rule
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.simulation.predictions import (
    Revision,
    WagonData,
    model_for,
    predict_wagon,
)
from fleetbrake.simulation.series import FloatArray, WagonSeries

__all__ = [
    "FitData",
    "kernel_calls",
    "parallel",
    "store",
    "stored",
]

_KERNEL_CALLS = [0]
_KERNEL_CALLS_LOCK = threading.Lock()


def _count(calls: int) -> None:
    with _KERNEL_CALLS_LOCK:  # the close loop may evaluate on two threads at once
        _KERNEL_CALLS[0] += calls


def kernel_calls() -> int:
    """Chain-kernel calls this process has made for fit data (spans simulated, those of
    ``predict_wagon`` where the kernel path cannot run included)."""
    return _KERNEL_CALLS[0]


_POOL: list[ThreadPoolExecutor | None] = [None]
"""The threads this process's evaluations split their spans across (None: one after
another; :func:`parallel`)."""


@contextlib.contextmanager
def parallel(threads: int) -> Iterator[None]:
    """Within it, each :meth:`FitData.predict_many` of this process runs its spans on
    ``threads`` threads (the chain kernel releases the GIL; a span's effect sets stay in order
    on one thread, so the results are those of one thread, bit for bit). For the process
    that drives a close loop while the engine's workers are idle (a single fit, the interval
    terms' evaluations); a worker evaluates on its one thread. ``threads <= 1``: no change."""
    if threads <= 1 or _POOL[0] is not None:
        yield
        return
    pool = ThreadPoolExecutor(threads, thread_name_prefix="fitdata")
    _POOL[0] = pool
    try:
        yield
    finally:
        _POOL[0] = None
        pool.shutdown(wait=True)


def _run_all(units: Sequence[Callable[[], None]]) -> None:
    """Run ``units`` (independent, each writing its own part of the output) on the threads
    of :func:`parallel`, or one after another outside it; the first error raised."""
    pool = _POOL[0]
    if pool is None or len(units) < 2:
        for unit in units:
            unit()
        return
    futures = [pool.submit(unit) for unit in units]
    for future in futures:
        future.result()


FIXED_POINT_TOL_K = 1.0e-4
"""K: a state-dependent effect's iteration stops when no prediction changed by more
(``simulate_timeline``'s ``tol_k``)."""

FIXED_POINT_MAX_ITERATIONS = 30

DRIVERS = ("speed_kmh", "brake_pressure_bar", "flux_w_m2", "ambient_c")
"""The drivers kept for each second (the prediction's columns of the same names)."""


@dataclass
class _Wagon:
    wagon: WagonConfig
    data: WagonData | None
    """The wagon's samples, kept only where the kernel path cannot run it."""
    event_ids: frozenset[str]
    spans: list[Span]
    batched: bool
    """Whether the kernel path can run this wagon's spans (else ``predict_wagon``)."""
    start: int
    stop: int
    """Its seconds are ``start .. stop`` of :attr:`FitData.seconds`."""
    keys: pl.DataFrame
    """(event_id, time_utc, position) of its seconds, for reading a frame at them."""


_MODELS: dict[tuple[object, ...], Model] = {}
"""The models of this process (a worker's, made once: they are not pickled with the data)."""


def _model(wagon: WagonConfig, solver: str, refinement: float) -> Model:
    key = (wagon.geometry, wagon.block, wagon.sensor_point_m, solver, refinement)
    if key not in _MODELS:
        _MODELS[key] = model_for(wagon, solver, refinement)
    return _MODELS[key]


@dataclass
class FitData:
    """The fit events of a close loop as arrays (see the module docstring)."""

    config: SimulationConfig
    base: Revision
    wagons: list[_Wagon]
    event_ids: list[str]
    """The events, by index (:attr:`event`)."""
    event: np.ndarray
    """(n) index into :attr:`event_ids` of each second."""
    time_utc: np.ndarray
    """(n) datetime64[us] of each second."""
    measured_c: FloatArray
    blocks: np.ndarray
    """(n) block id of each second: the wagon-day (whole blocks are independent enough to
    hold out; seconds of one day are not)."""
    chains: np.ndarray
    """(n) the span (one carried chain) of each second."""
    heating: np.ndarray
    """(n) True up to the release (the prediction's ``phase`` heating), else cooling."""
    drivers: dict[str, FloatArray] = field(default_factory=dict)
    """(n) each of :data:`DRIVERS`, the heat input with the base revision's effects."""
    evaluations: int = 0
    """Effect sets evaluated."""

    @property
    def seconds(self) -> int:
        return int(self.measured_c.size)

    # ------------------------------------------------------------------ building
    @classmethod
    def build(
        cls,
        loaded: Mapping[str, WagonData],
        events: pl.DataFrame,
        config: SimulationConfig,
        base: Revision,
    ) -> FitData:
        """The events of ``events`` (columns ``wagon_id``, ``event_id``) of the wagons in
        ``loaded``, simulated as ``base``'s predictions are (its solver and mesh)."""
        wagons: list[_Wagon] = []
        parts: dict[str, list[np.ndarray]] = {
            k: [] for k in ("event", "time", "measured", "chain", "heating", *DRIVERS)
        }
        event_ids: list[str] = []
        chain_count = 0
        position = 0
        for wagon_id in events["wagon_id"].unique(maintain_order=True).to_list():
            data = loaded.get(wagon_id)
            if data is None:
                continue
            wanted = frozenset(events.filter(pl.col("wagon_id") == wagon_id)["event_id"])
            model = _model(data.wagon, base.solver, base.refinement)
            batched = isinstance(model, ReducedModel) and config.initial_state == "carried"
            spans: list[Span] = []
            start = position
            keys: list[pl.DataFrame] = []
            base_effects = EffectSet(tuple(e for e in base.effects if e.name != "sensor_lag"))
            for series in data.spans if batched else ():
                assert isinstance(model, ReducedModel)
                span, windows, ok = prepare_span(series, data.wagon, model, config, wanted)
                if not ok:
                    batched = False
                    break
                if span is None:
                    continue
                spans.append(span)
                flux = base_effects.apply_to_inputs(span.fine).flux_w_m2
                speed = span.fine.speed_kmh
                for event_id, a, release, stop in windows:
                    k = np.arange(a, stop + 1)
                    k = k[np.isfinite(series.measured_c[k])]
                    index = len(event_ids)
                    event_ids.append(event_id)
                    parts["event"].append(np.full(k.size, index, dtype=np.int64))
                    parts["time"].append(_times(series, k))
                    parts["measured"].append(series.measured_c[k])
                    parts["chain"].append(np.full(k.size, chain_count, dtype=np.int64))
                    parts["heating"].append(k <= release)
                    parts["speed_kmh"].append(speed[k])
                    parts["brake_pressure_bar"].append(series.pressure_bar[k])
                    parts["flux_w_m2"].append(np.asarray(flux, dtype=np.float64)[k])
                    parts["ambient_c"].append(series.ambient_c[k])
                    keys.append(
                        pl.DataFrame(
                            {"event_id": event_id, "time_utc": parts["time"][-1]},
                            schema={"event_id": pl.String, "time_utc": pl.Datetime("us")},
                        )
                    )
                    position += k.size
                chain_count += 1
            if not batched:
                # the reference path's own seconds (the same windows, read from its frame)
                for key in ("event", "time", "measured", "chain", "heating", *DRIVERS):
                    del parts[key][len(parts[key]) - len(keys) :]
                del event_ids[len(event_ids) - len(keys) :]
                position = start
                spans, keys = [], []
                frame = predict_wagon(
                    data, model, base, config, event_ids=wanted, timeline=False
                ).predictions.filter(pl.col("measured_sensor_c").is_not_null())
                for group, part in frame.group_by("event_id", maintain_order=True):
                    index = len(event_ids)
                    event_ids.append(str(group[0]))
                    size = part.height
                    times = part["time_utc"].to_numpy().astype("datetime64[us]")
                    parts["event"].append(np.full(size, index, dtype=np.int64))
                    parts["time"].append(times)
                    parts["measured"].append(part["measured_sensor_c"].to_numpy())
                    parts["chain"].append(np.full(size, chain_count, dtype=np.int64))
                    parts["heating"].append((part["phase"] == "heating").to_numpy())
                    for name in DRIVERS:
                        parts[name].append(part[name].to_numpy().astype(np.float64))
                    keys.append(part.select("event_id", "time_utc"))
                    position += size
                chain_count += 1
            key_frame = (
                pl.concat(keys)
                if keys
                else pl.DataFrame(schema={"event_id": pl.String, "time_utc": pl.Datetime("us")})
            )
            wagons.append(
                _Wagon(
                    wagon=data.wagon,
                    data=None if batched else data,
                    event_ids=wanted,
                    spans=spans,
                    batched=batched,
                    start=start,
                    stop=position,
                    keys=key_frame.with_row_index("position"),
                )
            )
        n = position

        def joined(name: str, dtype: Any) -> np.ndarray:
            return np.concatenate(parts[name]) if parts[name] else np.zeros(0, dtype=dtype)

        time_utc = joined("time", "datetime64[us]")
        # wagon-day blocks: the wagon's index and the UTC day of the second
        day = time_utc.astype("datetime64[D]").astype(np.int64)
        wagon_of = np.zeros(n, dtype=np.int64)
        for i, w in enumerate(wagons):
            wagon_of[w.start : w.stop] = i
        _, blocks = np.unique(np.stack([wagon_of, day]), axis=1, return_inverse=True)
        return cls(
            config=config,
            base=base,
            wagons=wagons,
            event_ids=event_ids,
            event=joined("event", np.int64),
            time_utc=time_utc,
            measured_c=joined("measured", np.float64),
            blocks=np.asarray(blocks, dtype=np.int64).reshape(-1),
            chains=joined("chain", np.int64),
            heating=joined("heating", bool),
            drivers={name: joined(name, np.float64) for name in DRIVERS},
        )

    # ------------------------------------------------------------------ evaluation
    def predict(self, effects: EffectSet) -> FloatArray:
        """The predicted sensor temperature at every second, with ``effects`` (NaN where
        nothing is predicted)."""
        return self.predict_many([effects])[0]

    def residual(self, effects: EffectSet) -> FloatArray:
        """measured - predicted at every second (NaN where nothing is predicted)."""
        return self.measured_c - self.predict(effects)

    def residuals(self, effect_sets: Sequence[EffectSet]) -> list[FloatArray]:
        """:meth:`residual` of each effect set: one pass over the cached data (a
        finite-difference Jacobian's perturbed vectors together)."""
        return [self.measured_c - p for p in self.predict_many(effect_sets)]

    def predict_many(self, effect_sets: Sequence[EffectSet]) -> list[FloatArray]:
        """The predictions of each effect set (:meth:`predict`). Each span (each wagon the
        kernel path cannot run) is a unit of its own, run over the effect sets in order; the
        units on the threads of :func:`parallel` when inside it, the longest chains first."""
        out = [np.full(self.seconds, np.nan) for _ in effect_sets]
        self.evaluations += len(effect_sets)
        units: list[tuple[int, Callable[[], None]]] = []
        for w in self.wagons:
            model = _model(w.wagon, self.base.solver, self.base.refinement)
            if w.batched and isinstance(model, ReducedModel):
                at = w.start
                for span in w.spans:
                    size = int(span.select.size)
                    units.append(
                        (
                            int(span.gather.size),
                            self._span_unit(span, model, effect_sets, out, at, at + size),
                        )
                    )
                    at += size
            else:
                units.append((w.stop - w.start, self._reference_unit(w, model, effect_sets, out)))
        units.sort(key=lambda unit: -unit[0])
        _run_all([unit for _, unit in units])
        return out

    def _span_unit(
        self,
        span: Span,
        model: ReducedModel,
        effect_sets: Sequence[EffectSet],
        out: list[FloatArray],
        start: int,
        stop: int,
    ) -> Callable[[], None]:
        def run() -> None:
            for i, effects in enumerate(effect_sets):
                out[i][start:stop] = self._run_span(span, model, effects)

        return run

    def _reference_unit(
        self, w: _Wagon, model: Model, effect_sets: Sequence[EffectSet], out: list[FloatArray]
    ) -> Callable[[], None]:
        def run() -> None:
            for i, effects in enumerate(effect_sets):
                out[i][w.start : w.stop] = self._reference(w, model, effects)

        return run

    def _run_span(self, span: Span, model: ReducedModel, effects: EffectSet) -> FloatArray:
        """The span's chain with ``effects``, in one kernel call; the predictions at its
        seconds. An effect depending on the block's temperature: fixed-point iteration over
        the whole chain (the face temperature of one pass feeding the heat input of the next,
        until the sensor changes by less than ``FIXED_POINT_TOL_K``, as
        :func:`~fleetbrake.model.timeline.simulate_timeline` iterates each run): the same
        fixed point, to that tolerance."""
        if not effects.state_dependent:
            return self._run_span_once(span, model, effects, None)[0]
        # warm start: the face temperature the last fixed point of this span converged to (a
        # fit's next parameters are close; the fixed point reached is the same, to the
        # tolerance)
        contact: FloatArray | None = span.contact
        previous: FloatArray | None = None
        for _ in range(FIXED_POINT_MAX_ITERATIONS):
            values, run_contact = self._run_span_once(span, model, effects, contact)
            if previous is not None and float(np.nanmax(np.abs(values - previous))) < (
                FIXED_POINT_TOL_K
            ):
                break
            previous, contact = values, run_contact
        span.contact = run_contact
        return values

    def _run_span_once(
        self,
        span: Span,
        model: ReducedModel,
        effects: EffectSet,
        contact: FloatArray | None,
    ) -> tuple[FloatArray, FloatArray]:
        """One pass of the span's chain (``contact``: the face temperature of the pass before,
        None: none yet); its predictions at its seconds and its face temperature."""
        lag = effects.get("sensor_lag")
        block = EffectSet(tuple(e for e in effects if e.name != "sensor_lag"))
        faces = model.face_names
        fine, coarse = span.fine, span.coarse
        if contact is not None:
            last = fine.flux_w_m2.size
            fine = fine.replace(contact_c=contact[:last])
            coarse = [
                c.replace(contact_c=np.interp(at, np.arange(a, b + 1), contact[a : b + 1]))
                for c, (a, b, at) in zip(coarse, span.coarse_at, strict=True)
            ]
        applied = [block.apply_to_inputs(fine), *(block.apply_to_inputs(c) for c in coarse)]
        flux = steps_of(span, applied, "flux", lambda x: x.flux_w_m2)
        air = steps_of(span, applied, "air", lambda x: x.ambient_c)
        # the convection per step and its systems in one Rust pass: the step means gathered,
        # a convection varying inside a piece rounded, piece by piece (simulate_timeline's);
        # a face set the loading has no convection for: zeros
        h, systems = chain_convection(
            model,
            [
                [
                    np.zeros(x.flux_w_m2.size) if x.h_w_m2k.get(face) is None else x.h_w_m2k[face]
                    for x in applied
                ]
                for face in faces
            ],
            gather=span.gather,
            step_offsets=span.step_offsets,
            piece_dt_s=span.piece_dt,
            quantum_w_m2k=H_QUANTUM_W_M2K,
        )
        pieces = ChainPieces(
            a=span.piece_a,
            b=span.piece_b,
            dt_s=span.piece_dt,
            step_offsets=span.step_offsets,
            at=span.at,
            at_offsets=span.at_offsets,
            flux_w_m2=flux,
            ambient_c=air,
            h_w_m2k=h,
            window_continuation=span.continuation,
            window_length=span.length,
        )
        rule = chain_rule(self.config.chain, lag)
        # the sensor and the face mean only (what an evaluation reads): the same as
        # ``model.simulate_chain``'s, bit for bit; summed at the seconds read only (the face
        # mean of every second for a state-dependent effect's next pass)
        run = simulate_chain_sensor(
            model,
            pieces,
            trusted_c=span.trusted_c,
            ambient_c=span.ambient_c,
            rule=rule,
            systems=systems,
            windows=None if effects.state_dependent else span.read,
        )
        _count(1)
        values = np.asarray(run.window_sensor_c, dtype=np.float64)[span.select]
        return values, np.asarray(run.contact_mean_c, dtype=np.float64)

    def _reference(self, w: _Wagon, model: Model, effects: EffectSet) -> FloatArray:
        """The wagon's seconds predicted by ``predict_wagon`` (what the kernel path cannot
        run), read at its seconds by (event, second)."""
        assert w.data is not None
        rev = Revision("candidate", effects, self.base.solver, self.base.refinement)
        frame = predict_wagon(
            w.data, model, rev, self.config, event_ids=w.event_ids, timeline=False
        ).predictions
        _count(len(w.data.spans))
        got = w.keys.join(
            frame.select("event_id", "time_utc", "predicted_sensor_c"),
            on=["event_id", "time_utc"],
            how="left",
        ).sort("position")
        return got["predicted_sensor_c"].fill_null(np.nan).to_numpy().astype(np.float64)

    # ------------------------------------------------------------------ views
    def frame(self, effects: EffectSet, predicted: FloatArray | None = None) -> pl.DataFrame:
        """The seconds as prediction rows (``event_id``, ``time_utc``, ``phase``,
        ``measured_sensor_c``, ``predicted_sensor_c`` and the drivers), for the evidence."""
        if predicted is None:
            predicted = self.predict(effects)
        ids = np.asarray(self.event_ids, dtype=object)
        return pl.DataFrame(
            {
                "event_id": pl.Series(ids[self.event] if self.seconds else [], dtype=pl.String),
                "time_utc": pl.Series(self.time_utc, dtype=pl.Datetime("us")),
                "phase": np.where(self.heating, "heating", "cooling"),
                "measured_sensor_c": self.measured_c,
                "predicted_sensor_c": predicted,
                **{name: self.drivers[name] for name in DRIVERS},
            }
        )

    def subset(self, keep: np.ndarray) -> np.ndarray:
        """Boolean mask of the seconds whose event index is in ``keep``."""
        return np.isin(self.event, keep)


def _times(series: WagonSeries, k: np.ndarray) -> np.ndarray:
    return np.datetime64(series.t0, "us") + (k.astype(np.int64) * 1_000_000).astype(
        "timedelta64[us]"
    )


def store(data: FitData, path: Path) -> Path:
    """Write ``data`` for an engine's workers to read once each (:func:`stored`)."""
    with open(path, "wb") as fh:
        pickle.dump(data, fh, protocol=pickle.HIGHEST_PROTOCOL)
    return path


_STORED: dict[str, FitData] = {}


def stored(path: str | Path) -> FitData:
    """The data :func:`store` wrote at ``path``, read once per process."""
    key = str(path)
    if key not in _STORED:
        with open(key, "rb") as fh:
            if len(_STORED) >= 3:  # a run's fit, screening and holdout data at most
                _STORED.clear()
            _STORED[key] = pickle.load(fh)
    return _STORED[key]
