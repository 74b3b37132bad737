"""The one chain/re-anchor algorithm: a wagon's block simulated through its data, re-anchored
to the measurement, giving the per-event predictions and the timeline the flags judge.

::

    from fleetbrake.simulation.chains import ChainParams, simulate_span

    result = simulate_span(series, wagon, model, effects, ChainParams())
    result.sensor_c, result.contact_max_c        # the timeline, on the series' grid
    result.segments                              # where it was re-anchored, and by how much
    result.windows                               # one EventWindow per braking event

How (``ChainParams`` names every number; each field's docstring says why its value):

1. **Spans.** A wagon's samples are cut where two rows are more than ``bridge_max_s`` apart
   (:meth:`WagonSeries.spans_from_frame`); each span is simulated on its own 1 Hz grid from a
   uniform block at its first trusted reading. Shorter gaps are simulated through, the inputs
   interpolated across them (in steps of ``gap_step_s`` when long). The speed driving the
   model is the running median over ``speed_median_samples`` seconds of the logged one.
2. **Segments** (:func:`segment_bounds`). Every activation starts a ``braking`` segment
   lasting until ``quiet_after_release_s`` after the release; the stretches between are cut
   into ``quiet`` windows of about ``window_s``; a data gap longer than ``max_gap_s`` is a
   ``gap`` segment of its own.
3. **Re-anchoring.** The block's state is carried from segment to segment; at the start of
   each the field is shifted uniformly (exact in the reduced model's ``T = T_ref + θ`` form)
   by the mean of measured - predicted over the ``anchor_s`` seconds before it, or, with
   fewer than ``anchor_min_readings`` trusted readings there (after a gap or a fault), over
   the first ``anchor_s`` seconds of the segment. So measured - predicted starts at zero in
   every segment, and what it does then is what the model cannot explain. Readings a faulty
   sensor may have given (see :func:`trusted_readings`) never anchor. A sensor lag of the
   effects is carried across segments (it acts on the block, the shifts on the reading).
4. **Event windows** (:func:`event_windows`). A braking event's prediction is the chain's
   continuation from its activation (where the braking segment was just anchored) until
   ``event_after_release_s`` after its release, the next activation or a data gap, *not*
   re-anchored inside: the error it accumulates is the model's error for that braking.

:func:`simulate_span` runs this segment by segment in Python: it is the reference. The
pipeline runs the same algorithm with a span in one call of the reduced model's Rust kernel
(:func:`fleetbrake.simulation.batched.simulate_span_batched`, equal to it to 1e-9 K, tested).

``uniform_windows`` is the paper's initialisation instead: each event from a uniform block at
the reading at activation (no chain; the close loop screens candidates this way).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Collection
from dataclasses import dataclass
from typing import Any, Literal, cast

import numpy as np

from fleetbrake.errors import ConfigError
from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.ingest.config import EventConfig
from fleetbrake.ingest.spans import SPAN_GAP_S
from fleetbrake.model.chaintypes import ChainRule
from fleetbrake.model.effects import Effect, EffectSet
from fleetbrake.model.fullmodel import FullModelRunner
from fleetbrake.model.rom import ReducedModel, first_order_lag
from fleetbrake.model.timeline import TimelineResult, simulate_timeline
from fleetbrake.simulation.series import (
    FloatArray,
    WagonSeries,
    merge_spans,
    running_median,
    runs,
)

__all__ = [
    "ANCHOR_TOLERANCE_K",
    "SEGMENT_KINDS",
    "ChainParams",
    "ChainParamsError",
    "EventWindow",
    "Model",
    "SegmentState",
    "SpanResult",
    "chain_rule",
    "constant_runs",
    "data_gaps",
    "event_windows",
    "segment_bounds",
    "simulate_span",
    "trusted_readings",
    "uniform_windows",
]

Model = ReducedModel | FullModelRunner
"""What a revision predicts with (the full model has the reduced model's interface)."""

SEGMENT_KINDS: tuple[str, ...] = ("braking", "quiet", "gap")

ANCHOR_TOLERANCE_K = 1e-3
"""K: a shift found from a segment's own first seconds smaller than this is not worth
simulating the segment again for (numerical, not a threshold of judgement)."""


class ChainParamsError(ConfigError):
    """Chain parameters that cannot be used; the message names the key."""


@dataclass(frozen=True)
class ChainParams:
    """Every number of the chain/re-anchor algorithm, named once (see the module docstring).

    Predictions, the timeline the flags judge and the close loop's re-simulations all use
    these, so that the three agree; each docstring says why its value is what it is.

    Read by: ``fleetbrake run``, ``fleetbrake watch``, ``fleetbrake close-loop``.
    """

    max_gap_s: float = EventConfig.max_gap_s
    """s: two samples further apart than this have a data gap between them: an event window
    ends at it, and it is a ``gap`` segment, re-anchored after. The event detection's value
    (``EventConfig.max_gap_s``, 15 s), so that a gap too short to end an event does not cut
    its simulation either (a shorter value, such as 10 s, would cut the window of an event
    holding a 12 s hole)."""
    bridge_max_s: float = SPAN_GAP_S
    """s: a gap up to this long is simulated through, speed, pressure and air interpolated
    across it (the logger sleeps while the wagon stands); after a longer one the block starts
    afresh, uniform at its first reading. It is also how far back an event's state reaches:
    the whole span before it, and nothing before the span (a fixed look-back, such as 12 h,
    would make an event's prediction depend on which other events are simulated with it).
    6 h: after that long at rest a block has lost nearly all the heat and the uneven
    field its brakings left, so a uniform start at the first reading is as good, and spans
    stay independent of each other. The stored spans, the stages' unit of work
    (:mod:`fleetbrake.ingest.spans`), are cut at the default."""
    anchor_s: int = 30
    """s: the field is shifted by the mean of measured - predicted over this many seconds
    before a segment (one reading would add its noise to every prediction of the segment;
    30 readings average it down about fivefold; docs/pipeline.md has the comparison)."""
    anchor_min_readings: int = 5
    """Fewer trusted readings than this in those seconds (after a gap or a sensor fault): the
    shift is taken from the first ``anchor_s`` seconds of the segment itself instead."""
    window_s: int = 600
    """s: the stretches between brakings are cut into ``quiet`` windows of about this
    length, each re-anchored (a window's measured - predicted then shows one window's worth
    of model error, whatever happened hours before)."""
    quiet_after_release_s: int = 120
    """s: a braking's segment of the timeline ends this long after its release, where quiet
    windows begin: the heat of the braking still spreading to the sensor (and any sensor lag)
    is the braking's. Not to be confused with ``event_after_release_s``, the end of an
    event's prediction window."""
    event_after_release_s: int = 600
    """s: an event's prediction window runs from activation until this long after its
    release (or the next activation, or a data gap, whichever is first), not re-anchored
    inside: ``v_predictions`` holds at least 600 s after release (interface.md)."""
    speed_median_samples: int = EventConfig.speed_median_samples
    """The speed driving the model is the running median over this many 1 Hz samples of the
    logged speed (the event detection's value, 7): a GPS jump of a few seconds would put a
    burst of friction heat into a braking, and a median removes it without blunting real
    changes of speed. Predictions, timeline and close loop all drive the model with it."""
    gap_step_s: int = 60
    """s: a ``gap`` segment longer than twice this is simulated in steps of about this length
    (its inputs are interpolated anyway), and the result interpolated to seconds."""
    distrust_fault_gap_s: int = 600
    """s: valid-looking readings between out-of-range readings less than this apart are not
    used to anchor (an intermittent circuit's)."""
    distrust_constant_s: int = 120
    """s: readings unchanged for at least this long are not used to anchor (a frozen
    sensor's value would pull the simulated block to it) ..."""
    distrust_resolution_k: float = 0.01
    """K: ... unchanged meaning within this of each other (the logging resolution)."""
    activation_reading_s: int = 3
    """s: ``uniform_windows`` start each event at the reading at activation, or at the
    nearest valid one within this many seconds."""

    def __post_init__(self) -> None:
        problems = []
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                problems.append(f"{f.name} must be a number, got {value!r}")
            elif f.type == "int" and not isinstance(value, int):
                problems.append(f"{f.name} must be an integer, got {value!r}")
            elif not (math.isfinite(value) and value > 0):
                problems.append(f"{f.name} must be > 0 and finite, got {value!r}")
        if not problems and self.max_gap_s >= self.bridge_max_s:
            problems.append("max_gap_s must be below bridge_max_s")
        if not problems and self.anchor_min_readings > self.anchor_s:
            problems.append("anchor_min_readings must not exceed anchor_s")
        if problems:
            raise ChainParamsError("ChainParams: " + "; ".join(problems))


@dataclass(frozen=True)
class SegmentState:
    """One segment of a span's timeline and how it was anchored (the chain state)."""

    start: int
    stop: int
    """[start, stop), seconds since the series' t0."""
    kind: str
    """``braking``, ``quiet`` or ``gap``."""
    event_id: str | None
    """The event whose activation starts a ``braking`` segment."""
    anchor: Literal["start", "before", "after", "none"]
    """How the field was set at ``start``: ``start`` uniform at the span's first trusted
    reading (then possibly shifted by its first seconds), ``before`` shifted by the readings
    before, ``after`` by the segment's own first readings, ``none`` not shifted (no readings
    to anchor to)."""
    shift_k: float
    """The uniform shift applied at ``start`` (0 if none)."""
    reference_c: float
    """The field's reference temperature after the shift (``T = T_ref + θ``)."""


@dataclass(frozen=True)
class EventWindow:
    """One event's prediction window: samples ``start`` .. ``stop`` (inclusive) of the grid."""

    event_id: str
    start: int
    release: int
    stop: int
    sensor_c: FloatArray | None = None
    contact_mean_c: FloatArray | None = None
    contact_max_c: FloatArray | None = None
    flux_w_m2: FloatArray | None = None
    """Heat flux into the block at each sample (effects included)."""


@dataclass
class SpanResult:
    """A span simulated: its timeline on the series' grid (NaN past where it stopped), the
    segments with their anchoring, and the event windows asked for."""

    sensor_c: FloatArray
    contact_mean_c: FloatArray
    contact_max_c: FloatArray
    speed_kmh: FloatArray
    """The speed the model was driven with (running median of the logged one)."""
    segments: list[SegmentState]
    windows: list[EventWindow]
    """The windows asked for (events whose window holds fewer than 3 samples have none)."""


# --------------------------------------------------------------------------------------------
# Where the timeline is cut and anchored


def data_gaps(series: WagonSeries, chain: ChainParams) -> list[tuple[int, int]]:
    """[first missing second, next row) of each gap longer than ``max_gap_s``."""
    present = np.flatnonzero(series.present)
    return [
        (int(present[g]) + 1, int(present[g + 1]))
        for g in np.flatnonzero(np.diff(present) > chain.max_gap_s)
    ]


def segment_bounds(series: WagonSeries, chain: ChainParams) -> tuple[list[int], list[str]]:
    """Segment starts (then the series' end) and kinds: every activation starts a
    ``braking`` segment lasting until ``quiet_after_release_s`` after the release; the quiet
    stretches between are cut into ``quiet`` windows of about ``window_s``; every data gap
    longer than ``max_gap_s`` is a ``gap`` segment of its own."""
    n = series.n
    braking = np.zeros(n, dtype=bool)
    starts = set()
    for _, a, b, _ in series.events:
        lo, hi = max(a, 0), min(b + chain.quiet_after_release_s, n)
        if hi > lo:
            braking[lo:hi] = True
        if 0 <= a < n:
            starts.add(a)
    bounds = {0} | starts
    gaps = data_gaps(series, chain)
    for a, b in runs(~braking):
        windows = max(1, round((b - a) / chain.window_s))
        bounds |= {a + ((b - a) * j) // windows for j in range(windows)}
    for a, _ in runs(braking):  # a braking segment starts at its activation
        bounds.add(a)
    inside = np.zeros(n + 1, dtype=bool)
    for a, b in gaps:
        inside[a + 1 : b] = True
    bounds = {k for k in bounds if not inside[k]} | {k for gap in gaps for k in gap}
    gap_starts = {a for a, _ in gaps}
    ordered = sorted(k for k in bounds if 0 <= k < n - 1)
    kinds = ["gap" if k in gap_starts else "braking" if braking[k] else "quiet" for k in ordered]
    return [*ordered, n], kinds


def constant_runs(
    values: FloatArray, min_s: int, resolution_k: float
) -> list[tuple[int, int, float]]:
    """[start, stop) and value of runs of valid readings within ``resolution_k`` of their
    neighbours lasting ``min_s`` or more (missing readings inside do not break a run)."""
    idx = np.flatnonzero(np.isfinite(values))
    if idx.size < 2:
        return []
    v = values[idx]
    same = np.abs(np.diff(v)) < resolution_k
    # runs of ``same``: same[a:b] means readings idx[a] .. idx[b] equal their neighbours
    edges = np.flatnonzero(np.diff(np.r_[0, same.astype(np.int8), 0]))
    a, b = edges[::2], edges[1::2]
    long = idx[b] - idx[a] + 1 >= min_s
    return [
        (int(first), int(last) + 1, float(value))
        for first, last, value in zip(idx[a[long]], idx[b[long]], v[a[long]], strict=True)
    ]


def chain_rule(chain: ChainParams, sensor_lag: Effect | None) -> ChainRule:
    """The re-anchoring rule the chain kernel runs (:class:`ChainRule`): the chain's numbers
    and the time constant of the effects' sensor lag (None: no lag)."""
    return ChainRule(
        anchor_s=chain.anchor_s,
        anchor_min_readings=chain.anchor_min_readings,
        window_s=chain.window_s,
        tolerance_k=ANCHOR_TOLERANCE_K,
        lag_tau_s=None if sensor_lag is None else float(getattr(sensor_lag, "tau_s", 0.0)),
    )


def trusted_readings(series: WagonSeries, chain: ChainParams) -> FloatArray:
    """The readings the anchoring may use: the valid ones, less those between out-of-range
    readings closer than ``distrust_fault_gap_s`` and those of runs unchanged for
    ``distrust_constant_s`` (NaN there)."""
    trusted = series.measured_c.copy()
    for a, b in merge_spans(runs(series.fault), chain.distrust_fault_gap_s):
        trusted[a:b] = np.nan
    for a, b, _ in constant_runs(
        series.measured_c, chain.distrust_constant_s, chain.distrust_resolution_k
    ):
        trusted[a:b] = np.nan
    return trusted


def event_windows(series: WagonSeries, chain: ChainParams) -> list[EventWindow]:
    """Each event's window: from activation to ``event_after_release_s`` after release, the
    next activation, the last sample before a data gap or the end of the span, whichever is
    first (events with fewer than three samples in it are left out)."""
    n = series.n
    gap_starts = np.array([a for a, _ in data_gaps(series, chain)], dtype=np.int64)
    events = [e for e in series.events if 0 <= e[1] < n]
    out = []
    for i, (event_id, a, b, _) in enumerate(events):
        stop = min(b + chain.event_after_release_s, n - 1)
        if i + 1 < len(events):
            stop = min(stop, events[i + 1][1])
        later = gap_starts[gap_starts > a]
        if later.size:
            stop = min(stop, int(later[0]) - 1)
        if stop - a >= 2:
            out.append(EventWindow(event_id, a, b, stop))
    return out


# --------------------------------------------------------------------------------------------
# The simulation


@dataclass
class _Piece:
    """[a, b] simulated (samples a .. b inclusive)."""

    result: TimelineResult
    sensor: FloatArray
    contact_mean: FloatArray
    contact_max: FloatArray
    flux: FloatArray
    lag_last: float | None


class _Chain:
    """Runs pieces of one span's timeline with the state, reference and lag carried."""

    def __init__(
        self,
        series: WagonSeries,
        wagon: WagonConfig,
        model: Model,
        effects: EffectSet,
        chain: ChainParams,
    ) -> None:
        self.series = series
        self.wagon = wagon
        # FullModelRunner has the reduced model's simulate interface (rom.py)
        self.model = cast(ReducedModel, model)
        self.chain = chain
        self.speed = running_median(series.speed_kmh, chain.speed_median_samples)
        lag = effects.get("sensor_lag")
        self.tau_s = float(getattr(lag, "tau_s", 0.0)) if lag is not None else 0.0
        self.has_lag = lag is not None
        self.block_effects = EffectSet(tuple(e for e in effects if e.name != "sensor_lag"))
        self.t_first = 0.0

    def run(
        self,
        a: int,
        b: int,
        ref: float,
        state: Any,
        lag_last: float | None,
        *,
        coarse: bool = False,
    ) -> _Piece:
        """Samples a .. b from ``state`` (None: uniform) at reference ``ref``. A long gap (no
        readings, the wagon standing or unknown) is simulated in steps of up to
        ``gap_step_s`` and interpolated."""
        series = self.series
        k = np.arange(a, b + 1)
        if coarse:
            steps = math.ceil((b - a) / self.chain.gap_step_s)
            at = np.linspace(a, b, steps + 1)
            dt_s = (b - a) / steps
        else:
            at, dt_s = k.astype(np.float64), 1.0
        result = simulate_timeline(
            self.model,
            self.wagon,
            dt_s=dt_s,
            p_bar=np.interp(at, k, series.pressure_bar[a : b + 1]),
            speed_kmh=np.interp(at, k, self.speed[a : b + 1]),
            ambient_c=np.interp(at, k, series.ambient_c[a : b + 1]),
            initial_c=ref,
            initial_state=state,
            effects=self.block_effects,
        )
        sensor, last = result.sensor_c, None
        if self.has_lag:
            # the lag acts on the block's temperature; the anchoring shifts act on the whole
            # field at once, as a correction of the reading's level does
            shift = ref - self.t_first
            base = first_order_lag(sensor - shift, dt_s, self.tau_s, initial=lag_last)
            sensor, last = base + shift, float(base[-1])
        if coarse:
            return _Piece(
                result,
                np.interp(k, at, sensor),
                np.interp(k, at, result.contact_mean_c),
                np.interp(k, at, result.contact_max_c),
                np.interp(k, at, result.sample_flux_w_m2),
                last,
            )
        return _Piece(
            result,
            sensor,
            result.contact_mean_c,
            result.contact_max_c,
            result.sample_flux_w_m2,
            last,
        )


def simulate_span(
    series: WagonSeries,
    wagon: WagonConfig,
    model: Model,
    effects: EffectSet,
    chain: ChainParams,
    *,
    event_ids: Collection[str] | None = None,
    until: int | None = None,
) -> SpanResult:
    """The span's timeline and the windows of its events (``event_ids``: only those; None:
    all), simulated as the module docstring says. ``until``: stop after the segment holding
    this second (the timeline is NaN after it); default the whole span."""
    n = series.n
    trusted = trusted_readings(series, chain)
    bounds, kinds = segment_bounds(series, chain)
    windows = {
        w.start: w
        for w in event_windows(series, chain)
        if event_ids is None or w.event_id in event_ids
    }
    event_at = {a: event_id for event_id, a, _, _ in series.events}
    end = n if until is None else min(n, until + 1)
    sim = _Chain(series, wagon, model, effects, chain)
    predicted = np.full(n, np.nan)
    contact_mean = np.full(n, np.nan)
    contact_max = np.full(n, np.nan)
    segments: list[SegmentState] = []
    done: list[EventWindow] = []
    t_ref: float | None = None
    state: Any = None
    lag_last: float | None = None
    for (a, stop), kind in zip(itertools.pairwise(bounds), kinds, strict=True):
        if a >= end:
            break
        b = min(stop, n - 1)
        if b <= a:
            continue
        coarse = kind == "gap" and b - a > 2 * chain.gap_step_s
        anchor: Literal["start", "before", "after", "none"] = "none"
        shift = 0.0
        if t_ref is None:  # uniform at the first trusted reading
            ahead = trusted[a : min(a + chain.window_s, n)]
            ok = np.flatnonzero(np.isfinite(ahead))
            t_ref = sim.t_first = float(ahead[ok[0]]) if ok.size else float(series.ambient_c[a])
            state, anchor = None, "start"
        lo = max(a - chain.anchor_s, 0)
        back = trusted[lo:a] - predicted[lo:a]
        back = back[np.isfinite(back)]
        if back.size >= chain.anchor_min_readings:
            shift = float(back.mean())
            t_ref += shift
            anchor = "before"
            piece = sim.run(a, b, t_ref, state, lag_last, coarse=coarse)
        else:
            piece = sim.run(a, b, t_ref, state, lag_last, coarse=coarse)
            length = min(chain.anchor_s, piece.sensor.size)
            own = trusted[a : a + length] - piece.sensor[:length]
            own = own[np.isfinite(own)]
            if own.size >= chain.anchor_min_readings and abs(float(own.mean())) > (
                ANCHOR_TOLERANCE_K
            ):
                shift = float(own.mean())
                t_ref += shift
                anchor = "after" if anchor == "none" else anchor
                piece = sim.run(a, b, t_ref, state, lag_last, coarse=coarse)
        segments.append(
            SegmentState(
                start=int(a),
                stop=int(stop),
                kind=kind,
                event_id=event_at.get(a) if kind == "braking" else None,
                anchor=anchor,
                shift_k=shift,
                reference_c=float(t_ref),
            )
        )
        if a in windows:
            done.append(_window(sim, windows[a], a, b, piece, t_ref))
        state, lag_last = piece.result.final_state, piece.lag_last
        predicted[a : b + 1] = piece.sensor
        contact_mean[a : b + 1] = piece.contact_mean
        contact_max[a : b + 1] = piece.contact_max
    return SpanResult(predicted, contact_mean, contact_max, sim.speed, segments, done)


def _window(
    sim: _Chain, window: EventWindow, a: int, b: int, piece: _Piece, t_ref: float
) -> EventWindow:
    """The event's window: the braking segment just simulated from its anchored start, then
    carried on un-anchored to the window's end."""
    parts = [(piece.sensor, piece.contact_mean, piece.contact_max, piece.flux)]
    if window.stop > b:
        more = sim.run(b, window.stop, t_ref, piece.result.final_state, piece.lag_last)
        parts.append((more.sensor[1:], more.contact_mean[1:], more.contact_max[1:], more.flux[1:]))
    size = window.stop - a + 1
    sensor, mean, top, flux = (np.concatenate(column)[:size] for column in zip(*parts, strict=True))
    return dataclasses.replace(
        window, sensor_c=sensor, contact_mean_c=mean, contact_max_c=top, flux_w_m2=flux
    )


def uniform_windows(
    series: WagonSeries,
    wagon: WagonConfig,
    model: Model,
    effects: EffectSet,
    chain: ChainParams,
    *,
    event_ids: Collection[str] | None = None,
) -> tuple[list[EventWindow], dict[str, str]]:
    """Each event's window from a uniform block at the reading at activation (or the nearest
    valid one within ``activation_reading_s``), all effects applied from there (a sensor lag
    starting settled): the paper's initialisation, no chain. Returns the windows, and why
    each event without one was skipped."""
    sim = _Chain(series, wagon, model, EffectSet(), chain)
    out: list[EventWindow] = []
    skipped: dict[str, str] = {}
    for window in event_windows(series, chain):
        if event_ids is not None and window.event_id not in event_ids:
            continue
        start = _reading_near(series.measured_c, window.start, chain.activation_reading_s)
        if start is None:
            skipped[window.event_id] = "no valid reading at activation"
            continue
        a, b = window.start, window.stop
        result = simulate_timeline(
            sim.model,
            wagon,
            dt_s=1.0,
            p_bar=series.pressure_bar[a : b + 1],
            speed_kmh=sim.speed[a : b + 1],
            ambient_c=series.ambient_c[a : b + 1],
            initial_c=start,
            effects=effects,
        )
        out.append(
            dataclasses.replace(
                window,
                sensor_c=result.sensor_c,
                contact_mean_c=result.contact_mean_c,
                contact_max_c=result.contact_max_c,
                flux_w_m2=result.sample_flux_w_m2,
            )
        )
    return out, skipped


def _reading_near(measured: FloatArray, k: int, window_s: int) -> float | None:
    """The reading at sample k, or the nearest valid one within ``window_s``."""
    for d in range(window_s + 1):
        for j in (k - d, k + d):
            if 0 <= j < measured.size and np.isfinite(measured[j]):
                return float(measured[j])
    return None
