"""One span's chain cached for the fit data, everything but the effects: its pieces (the
timeline's segments, coarse gap grids and window continuations), the declared loading of its
samples, and the seconds its windows are read at (:class:`Span`, :func:`prepare_span`); and
the kernel's per-step inputs of a loading with the effects applied (:func:`steps_of`)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.effects import DriveInputs
from fleetbrake.model.rom import ReducedModel
from fleetbrake.model.timeline import drive_inputs
from fleetbrake.simulation.chains import event_windows, segment_bounds, trusted_readings
from fleetbrake.simulation.config import SimulationConfig
from fleetbrake.simulation.series import FloatArray, WagonSeries, running_median

__all__ = ["Span", "prepare_span", "steps_of"]


def _step_mean(samples: FloatArray) -> FloatArray:
    return 0.5 * (samples[:-1] + samples[1:])


def steps_of(
    span: Span,
    applied: Sequence[DriveInputs],
    name: str,
    get: Callable[[DriveInputs], FloatArray | None],
) -> FloatArray:
    """One input of the kernel per step, the flux or the air (``get`` of each source's
    loading: the step means, the sources' steps concatenated and gathered into the chain's;
    None: zeros), for the span's loading with the effects ``applied`` (the
    fine samples', then each coarse piece's). Where every source's array is the declared
    one itself (the effects left it as it was), the span's declared steps, made once."""
    declared = [span.fine, *span.coarse]
    unchanged = all(get(a) is get(d) for a, d in zip(applied, declared, strict=True))
    if unchanged and name in span.declared_steps:
        return span.declared_steps[name]
    parts: list[FloatArray] = []
    for inputs in applied:
        values = get(inputs)
        size = inputs.flux_w_m2.size - 1
        parts.append(
            np.zeros(size) if values is None else _step_mean(np.asarray(values, dtype=np.float64))
        )
    steps = np.concatenate(parts)[span.gather]
    if unchanged:
        span.declared_steps[name] = steps
    return steps


@dataclass
class Span:
    """One span's chain, everything but the effects: its pieces (the timeline's segments in
    order, then the windows' continuations), where each piece's steps come from (``gather``
    into the fine steps followed by each coarse grid's), and the seconds read from its
    windows (``select`` into the kernel's concatenated window output)."""

    trusted_c: FloatArray
    ambient_c: FloatArray
    fine: DriveInputs
    """The declared loading at samples 0 .. last (before the effects)."""
    coarse: list[DriveInputs]
    """Each coarse gap piece's declared loading on its own grid."""
    coarse_at: list[tuple[int, int, FloatArray]]
    """Each coarse gap piece's samples ``a .. b`` and grid (for a state-dependent effect's
    face temperature there)."""
    gather: np.ndarray
    piece_a: np.ndarray
    piece_b: np.ndarray
    piece_dt: np.ndarray
    step_offsets: np.ndarray
    at: FloatArray
    at_offsets: np.ndarray
    continuation: np.ndarray
    length: np.ndarray
    select: np.ndarray
    """Positions in the window output of this span's seconds (in :attr:`FitData.seconds`
    order)."""
    read: np.ndarray = field(init=False, repr=False)
    """One flag per window output (``length.sum()``), set where :attr:`select` reads it: the
    chain kernel's ``windows`` (made once, not per evaluation)."""
    contact: FloatArray | None = None
    """The face temperature of the last state-dependent fixed point (a warm start)."""
    declared_steps: dict[str, FloatArray] = field(default_factory=dict, repr=False)
    """The kernel's per-step inputs (``flux``, ``air``) of the declared loading,
    made the first time an evaluation's effects leave that input as declared (the same
    arrays: an effect that does not change an input returns it as it was given), and reused
    by later evaluations that leave it so; not pickled (a worker makes its own)."""

    def __post_init__(self) -> None:
        self.read = np.zeros(int(self.length.sum()), dtype=np.bool_)
        self.read[self.select] = True

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["declared_steps"] = {}
        return state


def prepare_span(
    series: WagonSeries,
    wagon: WagonConfig,
    model: ReducedModel,
    config: SimulationConfig,
    wanted: frozenset[str],
) -> tuple[Span | None, list[tuple[str, int, int, int]], bool]:
    """The span's cached chain and its wanted windows ``(event_id, start, release, stop)`` in
    output order; None when it holds no wanted window. The flag: whether the kernel path can
    run it (a window starting on a coarse gap segment cannot)."""
    chain = config.chain
    mine = [w for w in event_windows(series, chain) if w.event_id in wanted]
    if not mine:
        return None, [], True
    until = max(w.stop for w in mine)
    n = series.n
    bounds, kinds = segment_bounds(series, chain)
    windows = {w.start: w for w in mine}
    end = min(n, until + 1)
    segments: list[tuple[int, int, bool]] = []  # a, b, coarse
    for (a, stop), kind in zip(itertools.pairwise(bounds), kinds, strict=True):
        if a >= end:
            break
        b = min(stop, n - 1)
        if b > a:
            segments.append((a, b, kind == "gap" and b - a > 2 * chain.gap_step_s))
    if any(coarse and a in windows for a, _, coarse in segments):
        return None, [], False
    pieces: list[tuple[int, int, bool]] = list(segments)
    continuation: list[int] = []
    length: list[int] = []
    for a, b, _ in segments:
        window = windows.get(a)
        length.append(0 if window is None else window.stop - a + 1)
        if window is not None and window.stop > b:
            pieces.append((b, window.stop, False))
            continuation.append(len(pieces) - 1)
        else:
            continuation.append(-1)
    last = max(b for _, b, _ in pieces)
    speed = running_median(series.speed_kmh, chain.speed_median_samples)
    fine = drive_inputs(
        model,
        wagon,
        dt_s=1.0,
        p_bar=series.pressure_bar[: last + 1],
        speed_kmh=speed[: last + 1],
        ambient_c=series.ambient_c[: last + 1],
    )
    coarse: list[DriveInputs] = []
    coarse_at: list[tuple[int, int, FloatArray]] = []
    gather: list[np.ndarray] = []
    at_parts: list[FloatArray] = []
    at_counts: list[int] = []
    dts: list[float] = []
    counts: list[int] = []
    source = last  # the fine steps come first in the source arrays, the coarse grids after
    for a, b, is_coarse in pieces:
        if is_coarse:
            steps = math.ceil((b - a) / chain.gap_step_s)
            at = np.linspace(a, b, steps + 1)
            k = np.arange(a, b + 1)
            coarse.append(
                drive_inputs(
                    model,
                    wagon,
                    dt_s=(b - a) / steps,
                    p_bar=np.interp(at, k, series.pressure_bar[a : b + 1]),
                    speed_kmh=np.interp(at, k, speed[a : b + 1]),
                    ambient_c=np.interp(at, k, series.ambient_c[a : b + 1]),
                )
            )
            coarse_at.append((a, b, at))
            gather.append(np.arange(source, source + steps))
            source += steps
            at_parts.append(at)
            at_counts.append(at.size)
            dts.append((b - a) / steps)
            counts.append(steps)
        else:
            gather.append(np.arange(a, b))
            at_counts.append(0)
            dts.append(1.0)
            counts.append(b - a)
    # the windows' seconds with a valid measurement, in the kernel's output order
    select: list[np.ndarray] = []
    done: list[tuple[str, int, int, int]] = []
    offset = 0
    for (a, _, _), size in zip(segments, length, strict=True):
        if size:
            w = windows[a]
            k = np.arange(w.start, w.stop + 1)
            ok = np.flatnonzero(np.isfinite(series.measured_c[k]))
            select.append(offset + ok)
            done.append((w.event_id, w.start, w.release, w.stop))
            offset += size

    def offsets(values: list[int]) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(values, dtype=np.int64)]).astype(np.int64)

    span = Span(
        trusted_c=trusted_readings(series, chain),
        ambient_c=series.ambient_c,
        fine=fine,
        coarse=coarse,
        coarse_at=coarse_at,
        gather=np.concatenate(gather).astype(np.int64),
        piece_a=np.array([p[0] for p in pieces], dtype=np.int64),
        piece_b=np.array([p[1] for p in pieces], dtype=np.int64),
        piece_dt=np.array(dts, dtype=np.float64),
        step_offsets=offsets(counts),
        at=np.concatenate(at_parts) if at_parts else np.zeros(0),
        at_offsets=offsets(at_counts),
        continuation=np.array(continuation, dtype=np.int64),
        length=np.array(length, dtype=np.int64),
        select=np.concatenate(select) if select else np.zeros(0, dtype=np.int64),
    )
    return span, done, True
