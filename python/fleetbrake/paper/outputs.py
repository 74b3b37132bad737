"""The files of ``fleetbrake paper --out DIR``: the pictures (PNG, :mod:`.plots`) and the fields
(VTU, :mod:`.export`) of the reproduction and of the study."""

from __future__ import annotations

from pathlib import Path

from fleetbrake.errors import FleetbrakeError
from fleetbrake.paper.results import PaperReproduction, Study

__all__ = ["PaperOutputError", "write_outputs"]


class PaperOutputError(FleetbrakeError):
    """The pictures or fields cannot be written; the message names the file or directory."""


def write_outputs(
    rep: PaperReproduction, out_dir: str | Path, study: Study | None = None
) -> list[Path]:
    """The pictures (PNG) and fields (VTU) of the reproduction (and of the study) in ``out_dir``.

    Per manoeuvre X: ``paper_X_end_of_braking.png`` and ``paper_X_sensor_peak.png`` (the
    block's field; the paper's figures 4/5 and 7/8), ``paper_X_sensor.png`` (figures 6 and
    9), ``paper_X_fields.vtu``; then ``paper_calibration.png`` and ``paper_study.png``.
    Raises :class:`PaperOutputError` naming the file or directory that cannot be written.
    """
    try:
        return _write_outputs(rep, Path(out_dir), study)
    except OSError as error:
        where = error.filename or out_dir
        raise PaperOutputError(
            f"{where}: cannot write the pictures and fields: {error.strerror or error}"
        ) from None


def _write_outputs(rep: PaperReproduction, out: Path, study: Study | None) -> list[Path]:
    from fleetbrake.paper import plots  # matplotlib only when pictures are wanted
    from fleetbrake.paper.export import write_paper_fields

    out.mkdir(parents=True, exist_ok=True)
    mesh = rep.model.mesh
    geometry = rep.wagon.geometry
    sensor = rep.wagon.sensor_point_m
    cal = rep.calibration
    files: list[Path] = []
    for name, run in rep.runs.items():
        if run.field_end_c is not None:
            files.append(
                plots.plot_block_field(
                    mesh,
                    run.field_end_c,
                    geometry,
                    out / f"paper_{name}_end_of_braking.png",
                    title=f"Manoeuvre {name}: block temperature at the end of braking "
                    f"(t = {run.manoeuvre.duration_s:g} s)",
                    sensor_m=sensor,
                )
            )
        if run.field_peak_c is not None:
            files.append(
                plots.plot_block_field(
                    mesh,
                    run.field_peak_c,
                    geometry,
                    out / f"paper_{name}_sensor_peak.png",
                    title=f"Manoeuvre {name}: block temperature at the sensor's maximum "
                    f"(t = {run.field_peak_time_s:g} s)",
                    sensor_m=sensor,
                )
            )
        files.append(
            plots.plot_sensor_curve(
                run,
                out / f"paper_{name}_sensor.png",
                extra_depths_m={
                    f"calibrated depth {cal.sensor_depth_m * 1e3:.1f} mm": cal.sensor_depth_m
                },
            )
        )
    files.append(
        plots.plot_calibration(
            cal, out / "paper_calibration.png", registry_depth_m=rep.wagon.sensor_depth_m
        )
    )
    if study is not None:
        files.append(plots.plot_study(study, out / "paper_study.png"))
    files.extend(write_paper_fields(rep, out))
    return files
