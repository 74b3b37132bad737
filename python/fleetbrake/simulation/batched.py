"""The chain/re-anchor algorithm of :mod:`~fleetbrake.simulation.chains` with a span in one call
of the reduced model's Rust kernel (:meth:`ReducedModel.simulate_chain`), no Python per
segment or per event.

::

    from fleetbrake.simulation.batched import batchable, simulate_span_batched

    if batchable(model, effects):
        result = simulate_span_batched(series, wagon, model, effects, chain)

What is decided before the kernel runs (it does not depend on the simulated temperatures):
the segments and the event windows (the functions of ``chains``), the trusted readings, and
the inputs of every step: the declared loading at every second of the span with the effects
applied once, in numpy (:func:`fleetbrake.model.timeline.drive_inputs`: pointwise in the
samples, so a stretch's inputs are the span's), and for a long gap its coarse grid with the
inputs interpolated to it, as ``chains._Chain.run`` does. A convection varying inside a piece
is rounded to ``H_QUANTUM_W_M2K`` piece by piece, as ``simulate_timeline`` does for each of
its runs. The kernel then does the sequential part: each segment from the state the one
before left, shifted by the mean of measured - predicted before it (or of its own first
seconds, simulated twice then), the sensor lag carried, each event window continued
un-anchored from its braking segment.

Not batched (``batchable`` false, :func:`~fleetbrake.simulation.chains.simulate_span` runs
instead): an effect that depends on the block's temperature (solved by fixed point per run),
the full model, and a window starting on a coarse gap segment (cannot happen with data: a
window starts at a logged activation).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Collection
from typing import NamedTuple

import numpy as np

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.chaintypes import CHAIN_ANCHORS, ChainPieces, ChainRun
from fleetbrake.model.effects import EffectSet
from fleetbrake.model.rom import ReducedModel
from fleetbrake.model.timeline import H_QUANTUM_W_M2K, drive_inputs
from fleetbrake.simulation.chains import (
    ChainParams,
    EventWindow,
    Model,
    SegmentState,
    SpanResult,
    chain_rule,
    event_windows,
    segment_bounds,
    simulate_span,
    trusted_readings,
)
from fleetbrake.simulation.series import FloatArray, WagonSeries, running_median

__all__ = ["batchable", "simulate_span_batched"]


def batchable(model: Model, effects: EffectSet) -> bool:
    """Whether :func:`simulate_span_batched` can run this model with these effects."""
    return isinstance(model, ReducedModel) and not effects.state_dependent


def _step_mean(samples: FloatArray) -> FloatArray:
    return 0.5 * (samples[:-1] + samples[1:])


class _Segment(NamedTuple):
    """One segment of the span as the kernel runs it: samples ``a .. b`` (``b`` the last
    sample, ``stop`` the segment's end), its kind, and whether it is a long gap run on a
    coarse grid."""

    a: int
    stop: int
    b: int
    kind: str
    coarse: bool


def simulate_span_batched(
    series: WagonSeries,
    wagon: WagonConfig,
    model: Model,
    effects: EffectSet,
    chain: ChainParams,
    *,
    event_ids: Collection[str] | None = None,
    until: int | None = None,
) -> SpanResult:
    """:func:`~fleetbrake.simulation.chains.simulate_span`, the span in one kernel call (the
    same result, to rounding); falls back to it where :func:`batchable` says no."""
    if not isinstance(model, ReducedModel) or not batchable(model, effects):
        return simulate_span(series, wagon, model, effects, chain, event_ids=event_ids, until=until)
    n = series.n
    bounds, kinds = segment_bounds(series, chain)
    windows = {
        w.start: w
        for w in event_windows(series, chain)
        if event_ids is None or w.event_id in event_ids
    }
    end = n if until is None else min(n, until + 1)
    segments: list[_Segment] = []
    for (a, stop), kind in zip(itertools.pairwise(bounds), kinds, strict=True):
        if a >= end:
            break
        b = min(stop, n - 1)
        if b > a:
            segments.append(
                _Segment(a, stop, b, kind, kind == "gap" and b - a > 2 * chain.gap_step_s)
            )
    if any(s.coarse and s.a in windows for s in segments):
        return simulate_span(series, wagon, model, effects, chain, event_ids=event_ids, until=until)

    speed = running_median(series.speed_kmh, chain.speed_median_samples)
    lag = effects.get("sensor_lag")
    block_effects = EffectSet(tuple(e for e in effects if e.name != "sensor_lag"))
    builder = _PieceBuilder(series, wagon, model, block_effects, chain, speed)
    for seg in segments:
        builder.add(seg.a, seg.b, seg.coarse)
    continuation: list[int] = []
    length: list[int] = []
    for seg in segments:
        window = windows.get(seg.a)
        length.append(0 if window is None else window.stop - seg.a + 1)
        continuation.append(
            builder.add(seg.b, window.stop, False) if window and window.stop > seg.b else -1
        )
    run = model.simulate_chain(
        builder.pieces(continuation, length),
        trusted_c=trusted_readings(series, chain),
        ambient_c=series.ambient_c,
        rule=chain_rule(chain, lag),
    )
    states = _segment_states(series, segments, run)
    done = _event_windows(segments, length, windows, run, builder.sample_flux)
    return SpanResult(run.sensor_c, run.contact_mean_c, run.contact_max_c, speed, states, done)


class _PieceBuilder:
    """The chain's pieces, gathered one by one: each piece's steps' flux, air and convection
    (the declared loading with the effects applied once, in numpy), the span's 1 s steps
    computed once and each fine piece taking its stretch of them, a coarse piece on a grid of
    its own with its inputs interpolated to it."""

    def __init__(
        self,
        series: WagonSeries,
        wagon: WagonConfig,
        model: ReducedModel,
        effects: EffectSet,
        chain: ChainParams,
        speed: FloatArray,
    ) -> None:
        self.series, self.wagon, self.model = series, wagon, model
        self.effects, self.chain, self.speed = effects, chain, speed
        self.faces = model.face_names
        # the span's 1 s steps, once; each piece takes its stretch of them
        self.fine_flux, self.fine_air, self.fine_h, self.sample_flux = self.loading(
            1.0, series.pressure_bar, speed, series.ambient_c
        )
        self.flux_parts: list[FloatArray] = []
        self.air_parts: list[FloatArray] = []
        self.h_parts: list[FloatArray] = []
        self.at_parts: list[FloatArray] = []
        self.piece_a: list[int] = []
        self.piece_b: list[int] = []
        self.piece_dt: list[float] = []
        self.step_counts: list[int] = []
        self.at_counts: list[int] = []

    def loading(
        self, dt_s: float, p: FloatArray, v: FloatArray, air: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Step flux, air and raw step convection (S, F) of samples, and the flux at the
        samples, effects applied."""
        inputs = self.effects.apply_to_inputs(
            drive_inputs(self.model, self.wagon, dt_s=dt_s, p_bar=p, speed_kmh=v, ambient_c=air)
        )
        h = np.zeros((p.size - 1, len(self.faces)))
        for j, face in enumerate(self.faces):
            if face in inputs.h_w_m2k:
                h[:, j] = _step_mean(np.asarray(inputs.h_w_m2k[face], dtype=np.float64))
        flux = np.asarray(inputs.flux_w_m2, dtype=np.float64)
        return _step_mean(flux), _step_mean(inputs.ambient_c), h, flux

    def add(self, a: int, b: int, coarse: bool) -> int:
        """Add the piece of samples ``a .. b``; its index."""
        series, speed = self.series, self.speed
        if coarse:
            steps = math.ceil((b - a) / self.chain.gap_step_s)
            at = np.linspace(a, b, steps + 1)
            dt_s = (b - a) / steps
            k = np.arange(a, b + 1)
            flux, air, h, _ = self.loading(
                dt_s,
                np.interp(at, k, series.pressure_bar[a : b + 1]),
                np.interp(at, k, speed[a : b + 1]),
                np.interp(at, k, series.ambient_c[a : b + 1]),
            )
            self.at_parts.append(at)
            self.at_counts.append(at.size)
        else:
            dt_s = 1.0
            flux, air, h = self.fine_flux[a:b], self.fine_air[a:b], self.fine_h[a:b]
            self.at_counts.append(0)
        varying = np.any(h != h[0], axis=0)
        if varying.any():  # a convection varying in the run: rounded, as simulate_timeline
            h = h.copy()
            h[:, varying] = np.round(h[:, varying] / H_QUANTUM_W_M2K) * H_QUANTUM_W_M2K
        self.flux_parts.append(flux)
        self.air_parts.append(air)
        self.h_parts.append(h)
        self.piece_a.append(a)
        self.piece_b.append(b)
        self.piece_dt.append(dt_s)
        self.step_counts.append(flux.size)
        return len(self.piece_a) - 1

    def pieces(self, continuation: list[int], length: list[int]) -> ChainPieces:
        """The pieces gathered, with each segment's window continuation and length."""

        def offsets(counts: list[int]) -> np.ndarray:
            return np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)

        empty = np.zeros(0)
        return ChainPieces(
            a=np.array(self.piece_a, dtype=np.int64),
            b=np.array(self.piece_b, dtype=np.int64),
            dt_s=np.array(self.piece_dt, dtype=np.float64),
            step_offsets=offsets(self.step_counts),
            at=np.concatenate(self.at_parts) if self.at_parts else empty,
            at_offsets=offsets(self.at_counts),
            flux_w_m2=np.concatenate(self.flux_parts) if self.flux_parts else empty,
            ambient_c=np.concatenate(self.air_parts) if self.air_parts else empty,
            h_w_m2k=(
                np.concatenate(self.h_parts) if self.h_parts else np.zeros((0, len(self.faces)))
            ),
            window_continuation=np.array(continuation, dtype=np.int64),
            window_length=np.array(length, dtype=np.int64),
        )


def _segment_states(
    series: WagonSeries, segments: list[_Segment], run: ChainRun
) -> list[SegmentState]:
    """Each segment's chain state as the kernel anchored it."""
    event_at = {a: event_id for event_id, a, _, _ in series.events}
    return [
        SegmentState(
            start=seg.a,
            stop=seg.stop,
            kind=seg.kind,
            event_id=event_at.get(seg.a) if seg.kind == "braking" else None,
            anchor=CHAIN_ANCHORS[int(code)],  # type: ignore[arg-type]  # one of the literals
            shift_k=float(shift),
            reference_c=float(reference),
        )
        for seg, code, shift, reference in zip(
            segments, run.anchor, run.shift_k, run.reference_c, strict=True
        )
    ]


def _event_windows(
    segments: list[_Segment],
    length: list[int],
    windows: dict[int, EventWindow],
    run: ChainRun,
    sample_flux: FloatArray,
) -> list[EventWindow]:
    """The event windows the kernel continued, cut out of its concatenated outputs."""
    done: list[EventWindow] = []
    at = 0
    for seg, size in zip(segments, length, strict=True):
        if size:
            w = windows[seg.a]
            part = slice(at, at + size)
            done.append(
                EventWindow(
                    w.event_id,
                    w.start,
                    w.release,
                    w.stop,
                    sensor_c=run.window_sensor_c[part],
                    contact_mean_c=run.window_mean_c[part],
                    contact_max_c=run.window_max_c[part],
                    # the flux is an input: the span's own at the window's seconds
                    flux_w_m2=sample_flux[seg.a : w.stop + 1],
                )
            )
            at += size
    return done
