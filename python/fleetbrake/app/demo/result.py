"""Everything a demo wrote and found."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fleetbrake.app.demo.config import DemoConfig

if TYPE_CHECKING:
    from fleetbrake.app.run import RunReport

__all__ = ["DemoResult"]


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
