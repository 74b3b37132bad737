"""The fleet report as one Markdown document: its sections in order, written with their
pictures beside it."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fleetbrake.app.report.closeloop import closeloop_section
from fleetbrake.app.report.data import load_report_data
from fleetbrake.app.report.estimates import estimates_section
from fleetbrake.app.report.events import events_section, hottest_section
from fleetbrake.app.report.flags import flags_section
from fleetbrake.app.report.markdown import Section
from fleetbrake.app.report.overview import (
    heading,
    overview_section,
    quarantined_section,
    written_section,
)
from fleetbrake.app.report.predictions import predictions_section

if TYPE_CHECKING:
    from fleetbrake.synth.generator import FleetTruth

__all__ = ["ReportResult", "write_report"]


@dataclass
class ReportResult:
    """What :func:`write_report` wrote: the Markdown file and the pictures it references."""

    path: Path
    pictures: list[Path]


def write_report(
    db_path: str | Path,
    out_dir: str | Path,
    *,
    close_loop: Mapping[str, Any] | None = None,
    truth: FleetTruth | None = None,
    artefacts: Sequence[tuple[str, str | Path]] = (),
    name: str = "report.md",
    title: str = "fleetbrake fleet report",
    notes: Sequence[str] = (),
) -> ReportResult:
    """Write ``out_dir/name`` (Markdown) and its pictures (``out_dir/report-*.png``) from the
    views of ``db_path``. ``artefacts``: (what, path) pairs listed at the end; ``notes``:
    sentences put under the title (how the data was made, timings, ...)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = load_report_data(db_path)
    stem = Path(name).stem

    def picture(kind: str) -> Path:
        return out_dir / f"{stem}-{kind}.png"

    sections = [
        heading(data, title, notes),
        overview_section(data),
        *(
            [closeloop_section(close_loop, truth, picture("close-loop"))]
            if close_loop is not None
            else []
        ),
        predictions_section(data, picture("predictions")),
        flags_section(data, truth, picture("flags")),
        estimates_section(data, picture("estimates")),
        events_section(data),
        hottest_section(data, picture("contact")),
        quarantined_section(data),
        written_section(artefacts),
    ]
    path = out_dir / name
    path.write_text("\n".join(_lines(sections)), encoding="utf-8")
    return ReportResult(path=path, pictures=[p for s in sections for p in s.pictures])


def _lines(sections: Sequence[Section]) -> list[str]:
    return [line for section in sections for line in section.lines]
