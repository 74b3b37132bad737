"""Overheating (``overheating``): brakings whose predicted wheel-block contact temperature
(from the stored predictions) exceeds the configured limit."""

from __future__ import annotations

from collections.abc import Sequence

from fleetbrake.flags.config import DEFAULT_FLAG_CONFIG, FlagConfig
from fleetbrake.flags.records import Finding
from fleetbrake.flags.stats import EventStat
from fleetbrake.flags.text import at_text, speeds_text

__all__ = ["find_overheating"]


def find_overheating(
    wagon_id: str, stats: Sequence[EventStat], config: FlagConfig = DEFAULT_FLAG_CONFIG
) -> list[Finding]:
    """Brakings whose predicted contact maximum exceeds ``contact_limit_c``; severity by the
    margin."""
    out = []
    for e in stats:
        over = e.contact_max_c - config.contact_limit_c
        if over <= 0:
            continue
        if over >= config.overheat_alarm_margin_k:
            severity = "alarm"
        elif over >= config.overheat_warning_margin_k:
            severity = "warning"
        else:
            severity = "info"
        out.append(
            Finding(
                "overheating",
                severity,
                e.start_utc,
                e.window_end_utc,
                f"Predicted wheel–block contact temperature of {wagon_id} reached "
                f"{e.contact_max_c:.0f} °C {at_text(e.contact_max_utc)}, {over:.0f} K over the "
                f"{config.contact_limit_c:.0f} °C limit, in the braking "
                f"{speeds_text(e.v_start_kmh, e.v_end_kmh)} with up to {e.p_max_bar:.2f} bar: "
                "inspect the wheel treads and blocks for hot spots, cracks and metal pick-up.",
                event_id=e.event_id,
            )
        )
    return out
