"""Brake anomalies: a brake pressing too weakly (``weak_brake``: brakings heating the block far
less than predicted, from the stored predictions) and a dragging one (``dragging_brake``:
quiet windows of the stored timeline heating while the model, with no cylinder pressure,
cools; or brakings heating far more than predicted)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fleetbrake.flags.config import DEFAULT_FLAG_CONFIG, FlagConfig
from fleetbrake.flags.records import Finding
from fleetbrake.flags.stats import EventStat, Segment
from fleetbrake.flags.text import at_text, duration_text, speeds_text, when_text
from fleetbrake.simulation.series import WagonSeries

__all__ = ["find_dragging", "find_weak"]


def find_weak(
    wagon_id: str, stats: Sequence[EventStat], config: FlagConfig = DEFAULT_FLAG_CONFIG
) -> list[Finding]:
    """Runs of weak brakings (measured rise below ``weak_ratio`` x the predicted one, and short
    of it by ``weak_min_deficit_k``) with no normal braking between them; brakings not judged,
    with a small predicted rise or a shortfall within ``weak_min_deficit_k`` neither count nor
    break a run."""
    out = []
    run: list[EventStat] = []

    def close() -> None:
        if len(run) < config.weak_min_events:
            return
        ratios = np.array([e.ratio for e in run])
        median = float(np.median(ratios))
        worst = min(run, key=lambda e: e.ratio)
        start, end = run[0].start_utc, run[-1].end_utc
        if len(run) == 1:
            what = f"the braking {at_text(start)}"
        else:
            what = f"{len(run)} brakings {when_text(start, end)}"
        out.append(
            Finding(
                "weak_brake",
                "alarm" if median < config.weak_alarm_ratio else "warning",
                start,
                end,
                f"Block of {wagon_id} heated only {100 * median:.0f} % of the predicted rise in "
                f"{what} (e.g. {worst.m_rise:.1f} K instead of {worst.p_rise:.1f} K "
                f"{at_text(worst.start_utc)}, {speeds_text(worst.v_start_kmh, worst.v_end_kmh)} "
                f"with up to {worst.p_max_bar:.2f} bar): the block presses with too little force; "
                "check the brake cylinder, rigging, slack adjuster and the blocks.",
                event_id=run[0].event_id if len(run) == 1 else None,
            )
        )

    for e in stats:
        if not e.judged or e.p_rise < config.weak_min_predicted_rise_k:
            continue
        if e.ratio < config.weak_ratio:
            if e.p_rise - e.m_rise < config.weak_min_deficit_k:
                continue  # within the model's error: neither weak nor normal
            run.append(e)
        else:
            close()
            run = []
    close()
    return out


def find_dragging(
    series: WagonSeries,
    segments: Sequence[Segment],
    stats: Sequence[EventStat] = (),
    config: FlagConfig = DEFAULT_FLAG_CONFIG,
    *,
    excluded: Sequence[tuple[int, int]] = (),
) -> list[Finding]:
    """Quiet windows (no cylinder pressure, moving) in which the block heats by
    ``drag_min_rise_k`` and by ``drag_min_excess_k`` more than the model predicts, and
    brakings heating ``drag_event_ratio`` x and ``drag_event_excess_k`` more than predicted;
    those closer than ``drag_merge_gap_s`` are one flag. Segments overlapping ``excluded``
    ([start, stop) seconds: sensor faults) are not used."""
    items: list[tuple[int, int, str, Any]] = []
    for s in segments:
        if s.kind != "quiet" or not s.enough:
            continue
        if any(a < s.stop and s.start < b for a, b in excluded):
            continue
        if not s.calm and not s.excess_k >= config.drag_unsure_excess_k:
            continue
        if (
            s.speed_kmh >= config.drag_min_speed_kmh
            and s.m_end - s.m_start >= config.drag_min_rise_k
            and s.excess_k >= config.drag_min_excess_k
        ):
            items.append((s.start, s.stop, "window", s))
    for e in stats:
        if not e.judged or e.p_rise <= 0:
            continue
        if e.m_rise - e.p_rise >= config.drag_event_excess_k and e.ratio >= config.drag_event_ratio:
            a = int((e.start_utc - series.t0).total_seconds())
            b = int((e.window_end_utc - series.t0).total_seconds())
            items.append((a, b, "braking", e))
    items.sort(key=lambda x: x[0])
    groups: list[list[tuple[int, int, str, Any]]] = []
    for item in items:
        if groups and item[0] - max(x[1] for x in groups[-1]) <= config.drag_merge_gap_s:
            groups[-1].append(item)
        else:
            groups.append([item])
    out = []
    for group in groups:
        a = min(x[0] for x in group)
        b = max(x[1] for x in group)
        start, end = series.utc(a), series.utc(b)
        windows = [x[3] for x in group if x[2] == "window"]
        brakings = [x[3] for x in group if x[2] == "braking"]
        parts = []
        excess = 0.0
        if windows:
            dm = sum(w.m_end - w.m_start for w in windows)
            dp = sum(w.p_end - w.p_start for w in windows)
            excess += dm - dp
            seconds = sum(w.stop - w.start for w in windows)
            speed = sum(w.speed_kmh * (w.stop - w.start) for w in windows) / seconds
            pressure = max(w.pressure_max_bar for w in windows)
            w0, w1 = series.utc(windows[0].start), series.utc(windows[-1].stop)
            model = f"cooling by {-dp:.1f} K" if dp < 0 else f"a rise of only {dp:.1f} K"
            parts.append(
                f"heated {dm:.1f} K {when_text(w0, w1)} ({duration_text(seconds)} at {speed:.0f} km/h "
                f"on average) with at most {pressure:.2f} bar in the brake cylinder; the model "
                f"predicts {model}"
            )
        if brakings:
            extra = [e.m_rise - e.p_rise for e in brakings]
            excess += sum(extra)
            worst = max(brakings, key=lambda e: e.m_rise - e.p_rise)
            what = (
                f"{worst.m_rise:.1f} K in the braking {at_text(worst.start_utc)} "
                f"({speeds_text(worst.v_start_kmh, worst.v_end_kmh)} with up to "
                f"{worst.p_max_bar:.2f} bar) where {worst.p_rise:.1f} K were predicted"
            )
            if len(brakings) > 1:
                what = (
                    f"{sum(extra):.1f} K more than predicted in {len(brakings)} brakings, "
                    f"the most {what}"
                )
            parts.append(f"{'and it heated' if windows else 'heated'} {what}")
        severity = "alarm" if excess >= config.drag_alarm_excess_k else "warning"
        event_id = brakings[0].event_id if (len(brakings) == 1 and not windows) else None
        out.append(
            Finding(
                "dragging_brake",
                severity,
                start,
                end,
                f"Block of {series.wagon_id} {'; '.join(parts)}: check for a dragging brake "
                "(handbrake left on, stuck distributor or release valve, binding rigging).",
                event_id=event_id,
                detail="no_pressure" if windows else "braking",
            )
        )
    return out
