"""Tests of the paper reproduction (fleetbrake.paper: reproduction, study, plots, export,
outputs; `fleetbrake paper`)."""

from __future__ import annotations

import dataclasses
import io
import json
from pathlib import Path

import meshio
import numpy as np
import pytest
from rich.console import Console
from typer.testing import CliRunner

from fleetbrake.cli.main import app
from fleetbrake.errors import ConfigError, FleetbrakeError
from fleetbrake.model.physics import PAPER_MANOEUVRES, event_heat_input
from fleetbrake.paper.export import write_field_series, write_fields_vtu
from fleetbrake.paper.outputs import PaperOutputError, write_outputs
from fleetbrake.paper.peaks import find_peak
from fleetbrake.paper.plots import plot_block_field, plot_sensor_curve
from fleetbrake.paper.report import print_report, print_study
from fleetbrake.paper.reproduction import (
    calibrate_depth,
    free_decay_response,
    reproduce_paper,
    simulate_manoeuvre,
    superposed_curves,
)
from fleetbrake.paper.results import PaperReproduction
from fleetbrake.paper.settings import STUDY_DEPTHS_M, RunSettings
from fleetbrake.paper.study import remesh_check, run_study

PAPER_TIMES_S = {"A": 271.0, "B": 220.0}
COARSE = RunSettings(element="hex8", refinement=0.5, workers=1)
"""A coarse mesh (about 1,000 nodes): seconds per run, for trends and plumbing."""


@pytest.fixture(scope="module")
def coarse() -> PaperReproduction:
    return reproduce_paper(settings=COARSE)


# --------------------------------------------------------------------------------------------
# The command, on the real mesh (the acceptance test)


def test_paper_json_within_ten_percent() -> None:
    result = CliRunner().invoke(app, ["paper", "--json"])
    assert result.exit_code == 0, result.output
    figures = json.loads(result.stdout.strip().splitlines()[-1])
    assert {"A", "B", "calibration"} <= set(figures)
    for name, paper in PAPER_TIMES_S.items():
        run = figures[name]
        for key in (
            "time_to_peak_s",
            "paper_time_to_peak_s",
            "sensor_rise_k",
            "contact_max_end_c",
            "contact_mean_end_c",
            "contact_max_at_peak_c",
            "contact_mean_at_peak_c",
            "flux_w_m2",
            "alpha",
            "force_chain",
        ):
            assert key in run, (name, key)
        assert run["paper_time_to_peak_s"] == paper
        assert abs(run["time_to_peak_s"] / paper - 1.0) < 0.10, (name, run["time_to_peak_s"])
        assert 0.0 < run["sensor_rise_k"] < run["contact_max_end_c"] - run["t0_c"]
        assert run["force_chain"]["friction_force_n"] > 0
        calibrated = figures["calibration"][name]
        assert abs(calibrated["time_to_peak_s"] / paper - 1.0) < 0.10, (name, calibrated)
        assert calibrated["rel_error"] == pytest.approx(
            calibrated["time_to_peak_s"] / paper - 1, abs=1e-4
        )
    assert 0.030 <= figures["calibration"]["sensor_depth_m"] <= 0.070


# --------------------------------------------------------------------------------------------
# Peaks, fields, calibration


def test_find_peak_refines_between_samples() -> None:
    t = np.arange(0.0, 20.0)
    y = 5.0 - (t - 7.3) ** 2
    peak = find_peak(t, y)
    assert peak.time_s == pytest.approx(7.3, abs=1e-12)
    assert peak.value_c == pytest.approx(5.0, abs=1e-12)
    assert peak.interior
    rising = find_peak(t, t.copy())
    assert not rising.interior and rising.time_s == 19.0


def test_fields_are_those_of_the_run(coarse: PaperReproduction) -> None:
    """The stored-and-continued fields agree with the run's own time series."""
    mesh = coarse.model.mesh
    friction = np.unique(mesh.face_sets["friction"])
    sensor = np.asarray(coarse.wagon.sensor_point_m)
    node = int(np.argmin(np.linalg.norm(mesh.nodes - sensor, axis=1)))
    assert np.linalg.norm(mesh.nodes[node] - sensor) < 1e-9  # the mesh has a node at the seat
    for run in coarse.runs.values():
        end = round(run.manoeuvre.duration_s)
        assert run.field_end_c is not None and run.field_peak_c is not None
        assert run.field_end_c[friction].max() == pytest.approx(run.contact_max_c[end], abs=1e-9)
        step = round(run.field_peak_time_s)
        assert run.field_peak_c[node] == pytest.approx(run.sensor_c[step], abs=1e-9)
        assert abs(run.field_peak_time_s - run.time_to_peak_s) <= 0.5


def test_calibration_improves_on_the_registry_depth(coarse: PaperReproduction) -> None:
    cal = coarse.calibration
    cost_registry = sum(r.time_to_peak_rel_error**2 for r in coarse.runs.values())
    cost_calibrated = sum(e**2 for e in cal.rel_error.values())
    assert cost_calibrated <= cost_registry + 1e-12
    assert cal.depth_range_m[0] <= cal.sensor_depth_m <= cal.depth_range_m[1]
    # a narrower range that excludes the optimum puts the depth on its edge
    edge = calibrate_depth(coarse.runs, depth_range_m=(0.060, 0.070))
    assert edge.sensor_depth_m == pytest.approx(0.060, abs=2e-5)


# --------------------------------------------------------------------------------------------
# Trends physics guarantees (coarse mesh)


def test_deeper_sensor_peaks_later_and_lower(coarse: PaperReproduction) -> None:
    for run in coarse.runs.values():
        t, rise, interior = run.depth_peaks()
        k = [int(np.argmin(np.abs(run.depths_m - d))) for d in STUDY_DEPTHS_M]
        assert interior[k].all()
        assert np.all(np.diff(t[k]) > 0), t[k]
        assert np.all(np.diff(rise[k]) < 0), rise[k]


def test_more_convection_lowers_the_rise_and_brings_the_peak_forward(
    coarse: PaperReproduction,
) -> None:
    for name, manoeuvre in PAPER_MANOEUVRES.items():
        runs = [
            simulate_manoeuvre(
                coarse.model,
                coarse.wagon,
                name,
                manoeuvre,
                settings=COARSE,
                convection_w_m2k=h,
                keep_fields=False,
            )
            for h in (5.0, 10.0, 20.0, 50.0)
        ]
        rises = [r.sensor_rise_k for r in runs]
        times = [r.time_to_peak_s for r in runs]
        assert all(r.peak.interior for r in runs)
        assert np.all(np.diff(rises) < 0), rises
        assert np.all(np.diff(times) < 0), times


def test_superposition_is_exact_and_a_bigger_bore_heats_more_and_later(
    coarse: PaperReproduction,
) -> None:
    decay = free_decay_response(coarse.model, coarse.wagon, settings=COARSE)
    run = coarse.runs["A"]
    bigger = dataclasses.replace(coarse.wagon, cylinder_diameter_m=0.305)
    direct = simulate_manoeuvre(
        coarse.model, bigger, "A", run.manoeuvre, settings=COARSE, keep_fields=False
    )
    scale = event_heat_input(bigger, run.manoeuvre).block_flux_w_m2 / run.heat.block_flux_w_m2
    superposed = superposed_curves(run, decay, flux_scale=scale)  # exact up to round-off
    assert np.abs(superposed[:, 0] - direct.sensor_c).max() < 1e-5
    assert np.abs(superposed[:, 1:] - direct.depth_c).max() < 1e-5
    assert direct.sensor_rise_k > run.sensor_rise_k
    assert direct.time_to_peak_s > run.time_to_peak_s
    # another T0 by superposition too: B's T0 on A
    t0 = PAPER_MANOEUVRES["B"].t0_c
    other = dataclasses.replace(run.manoeuvre, t0_c=t0)
    direct_t0 = simulate_manoeuvre(
        coarse.model, coarse.wagon, "A", other, settings=COARSE, keep_fields=False
    )
    assert np.abs(superposed_curves(run, decay, t0_c=t0)[:, 0] - direct_t0.sensor_c).max() < 1e-5
    # a larger excess over ambient cools faster: the maximum comes earlier
    assert direct_t0.time_to_peak_s < run.time_to_peak_s


# --------------------------------------------------------------------------------------------
# Export and pictures


def test_vtu_round_trip(coarse: PaperReproduction, tmp_path: Path) -> None:
    mesh = coarse.model.mesh
    run = coarse.runs["A"]
    path = write_fields_vtu(
        mesh, tmp_path / "a.vtu", {"t_end_c": run.field_end_c, "t_peak_c": run.field_peak_c}
    )
    back = meshio.read(path)
    assert back.points.shape == (mesh.n_nodes, 3)
    np.testing.assert_allclose(back.points, mesh.nodes)
    np.testing.assert_array_equal(back.cells[0].data, mesh.elements)
    np.testing.assert_array_equal(back.point_data["t_end_c"], run.field_end_c)
    np.testing.assert_array_equal(back.point_data["t_peak_c"], run.field_peak_c)
    with pytest.raises(ValueError, match="values"):
        write_fields_vtu(mesh, tmp_path / "b.vtu", {"bad": np.zeros(3)})


def test_vtu_round_trip_hex20_and_series(tmp_path: Path) -> None:
    from fleetbrake.model.thermal import BlockModel

    model = BlockModel(element="hex20", refinement=0.5)
    mesh = model.mesh
    fields = np.vstack([mesh.nodes[:, 1], 2.0 * mesh.nodes[:, 1]])
    pvd = write_field_series(mesh, tmp_path / "series", fields, [0.0, 10.0], stem="t")
    assert pvd.read_text().count("<DataSet ") == 2
    back = meshio.read(tmp_path / "series" / "t_0001.vtu")
    assert back.cells[0].type == "hexahedron20"
    assert back.points.shape[0] == mesh.n_nodes
    np.testing.assert_array_equal(back.point_data["temperature_c"], fields[1])


def test_plots_write_png(coarse: PaperReproduction, tmp_path: Path) -> None:
    run = coarse.runs["B"]
    field_png = plot_block_field(
        coarse.model.mesh,
        run.field_end_c,
        coarse.wagon.geometry,
        tmp_path / "field.png",
        title="B at the end of braking",
        sensor_m=coarse.wagon.sensor_point_m,
    )
    curve_png = plot_sensor_curve(run, tmp_path / "curve.png", extra_depths_m={"45 mm": 0.045})
    for png in (field_png, curve_png):
        data = png.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        assert len(data) > 10_000


def test_study_tables_and_outputs(coarse: PaperReproduction, tmp_path: Path) -> None:
    """A small study on the coarse mesh, its tables, and every file of ``--out``."""
    study = run_study(
        coarse,
        depths_m=(0.045, 0.055),
        convections_w_m2k=(10.0, 20.0),
        bores_m=(0.254, 0.305),
        remesh_depths_m=(),
    )
    by_parameter = {p: study.select(p) for p in ("sensor_depth_m", "convection_w_m2k")}
    assert {(r.manoeuvre, r.value) for r in by_parameter["sensor_depth_m"]} == {
        (n, d) for n in ("A", "B") for d in (0.045, 0.055)
    }
    methods = {r.value: r.method for r in by_parameter["convection_w_m2k"]}
    assert methods == {10.0: "probe", 20.0: "run"}
    bores = study.select("cylinder_diameter_m", "A")
    assert bores[1].sensor_rise_k > bores[0].sensor_rise_k  # a bigger bore heats more
    assert set(study.to_dict()) >= {"sensor_depth_m", "flux_scale", "t0_c", "remesh_check"}

    buffer = io.StringIO()
    console = Console(file=buffer, width=160)
    print_report(coarse, console)
    print_study(study, console)
    text = buffer.getvalue()
    assert "Calibrated sensor depth" in text and "Study: brake cylinder bore" in text

    files = write_outputs(coarse, tmp_path / "out", study)
    names = {f.name for f in files}
    for name in ("A", "B"):
        assert {
            f"paper_{name}_end_of_braking.png",
            f"paper_{name}_sensor_peak.png",
            f"paper_{name}_sensor.png",
            f"paper_{name}_fields.vtu",
        } <= names
    assert {"paper_calibration.png", "paper_study.png"} <= names
    assert all(f.stat().st_size > 0 for f in files)


def test_outputs_that_cannot_be_written_name_the_path(
    coarse: PaperReproduction, tmp_path: Path
) -> None:
    taken = tmp_path / "not-a-directory"
    taken.write_text("a file where the pictures should go")
    with pytest.raises(PaperOutputError, match="not-a-directory") as info:
        write_outputs(coarse, taken)
    assert isinstance(info.value, FleetbrakeError) and info.value.exit_code == 1


def test_bad_settings_are_a_configuration_error() -> None:
    with pytest.raises(ConfigError, match="RunSettings: dt_s"):
        RunSettings(dt_s=0.0)


# --------------------------------------------------------------------------------------------
# Slow: the probe against a mesh graded towards the depth, on the real mesh


@pytest.mark.slow
def test_moving_the_probe_is_as_good_as_remeshing() -> None:
    rep = reproduce_paper(settings=RunSettings(horizon_s=600.0))
    for check in remesh_check(rep, (0.045, 0.065)):
        assert abs(check.probe_time_to_peak_s - check.remesh_time_to_peak_s) < 2.0, check
        assert abs(check.probe_rise_k - check.remesh_rise_k) < 0.05, check
