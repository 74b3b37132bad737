"""The reproduction and the study as tables on the console (rich): what ``fleetbrake paper``
prints."""

from __future__ import annotations

from collections.abc import Callable

from rich.console import Console
from rich.table import Table

from fleetbrake.paper.results import ManoeuvreResult, PaperReproduction, Study, StudyRow

__all__ = ["print_report", "print_study"]


def print_report(rep: PaperReproduction, console: Console | None = None) -> None:
    """Rich tables: heat input, results against the paper, calibration."""
    console = console or Console()
    names = list(rep.runs)
    heat = Table(title="Heat input (paper eqs. 1-12, eq. 6 with F_t; registry defaults)")
    heat.add_column("quantity")
    for name in names:
        heat.add_column(name, justify="right")
    rows: list[tuple[str, Callable[[ManoeuvreResult], str]]] = [
        ("T0 / ambient, C", lambda r: f"{r.manoeuvre.t0_c:g} / {r.ambient_c:g}"),
        ("duration, s", lambda r: f"{r.manoeuvre.duration_s:g}"),
        ("d_f / Delta t, m/s", lambda r: f"{r.manoeuvre.mean_speed_m_s:.2f}"),
        ("p_mean, bar", lambda r: f"{r.manoeuvre.p_mean_bar:g}"),
        ("F_cyl, N", lambda r: f"{r.heat.forces.cylinder_force_n:,.0f}"),
        ("F_bogie, N", lambda r: f"{r.heat.forces.bogie_force_n:,.0f}"),
        ("F_block, N", lambda r: f"{r.heat.forces.block_force_n:,.1f}"),
        ("F_t = mu F_block, N", lambda r: f"{r.heat.forces.friction_force_n:,.1f}"),
        ("P = F_t d_f / Delta t, W", lambda r: f"{r.heat.power_w:,.0f}"),
        ("Phi_th, W/m^2", lambda r: f"{r.heat.frictional_flux_w_m2:,.0f}"),
        ("alpha (wheel share)", lambda r: f"{r.heat.alpha:.4f}"),
        ("Phi_b, W/m^2", lambda r: f"{r.block_flux_w_m2:,.0f}"),
        ("energy into block, kJ", lambda r: f"{r.energy_in_j / 1e3:.1f}"),
    ]
    for label, fmt in rows:
        heat.add_row(label, *(fmt(rep.runs[n]) for n in names))
    console.print(heat)

    res = Table(title=f"Sensor at {rep.wagon.sensor_depth_m:g} m and friction face")
    res.add_column("quantity")
    for name in names:
        res.add_column(name, justify="right")
    rows = [
        ("time to peak, s", lambda r: f"{r.time_to_peak_s:.1f}"),
        ("paper, s", lambda r: f"{r.paper_time_to_peak_s:g}"),
        ("difference", lambda r: f"{100 * (r.time_to_peak_rel_error or 0):+.1f} %"),
        ("sensor peak, C", lambda r: f"{r.sensor_peak_c:.2f}"),
        ("sensor rise, K", lambda r: f"{r.sensor_rise_k:.2f}"),
        (
            "contact max / mean at end of braking, C",
            lambda r: f"{r.contact_max_end_c:.1f} / {r.contact_mean_end_c:.1f}",
        ),
        (
            "contact max / mean at sensor peak, C",
            lambda r: f"{r.contact_max_at_peak_c:.1f} / {r.contact_mean_at_peak_c:.1f}",
        ),
        ("run, s", lambda r: f"{r.seconds:.1f}"),
    ]
    for label, fmt in rows:
        res.add_row(label, *(fmt(rep.runs[n]) for n in names))
    console.print(res)

    cal = rep.calibration
    table = Table(title=f"Calibrated sensor depth: {1000 * cal.sensor_depth_m:.2f} mm")
    for col in ("manoeuvre", "time to peak, s", "paper, s", "difference", "rise, K"):
        table.add_column(col, justify="right")
    for name in cal.time_to_peak_s:
        table.add_row(
            name,
            f"{cal.time_to_peak_s[name]:.1f}",
            f"{cal.paper_time_to_peak_s[name]:g}",
            f"{100 * cal.rel_error[name]:+.1f} %",
            f"{cal.sensor_rise_k[name]:.2f}",
        )
    console.print(table)
    console.print(
        f"{rep.model.n_nodes:,} nodes ({rep.settings.element}), "
        f"{rep.settings.n_steps} steps of {rep.settings.dt_s:g} s; "
        f"mesh {rep.seconds_mesh:.1f} s, total {rep.seconds:.1f} s"
    )


_PARAMETER_LABELS = {
    "sensor_depth_m": ("sensor depth", "depth, m", "{:.3f}"),
    "convection_w_m2k": ("convection on every surface but the friction face", "h, W/m2K", "{:g}"),
    "cylinder_diameter_m": ("brake cylinder bore", "bore, m", "{:.3f}"),
    "flux_scale": (
        "eq. 6 as the paper prints it (F_block for F_t: flux x 1/mu)",
        "flux x",
        "{:.2f}",
    ),
    "t0_c": ("A and B with each other's T0", "T0, C", "{:g}"),
}


def print_study(study: Study, console: Console | None = None) -> None:
    """Rich tables of the study: one per parameter, A and B side by side."""
    console = console or Console()
    for parameter, (title, label, fmt) in _PARAMETER_LABELS.items():
        rows = study.select(parameter)
        if not rows:
            continue
        table = Table(title=f"Study: {title}")
        table.add_column(label, justify="right", no_wrap=True)
        names = sorted({r.manoeuvre for r in rows})
        for name in names:
            table.add_column(f"{name} t_peak, s", justify="right")
            table.add_column(f"{name} rise, K", justify="right")
        table.add_column("method", no_wrap=True)
        if parameter == "t0_c":  # each manoeuvre with the other's T0: one row
            groups = [[r for r in rows if r.manoeuvre == name][:1] for name in names]
            keys: list[tuple[str, list[list[StudyRow]]]] = [("swapped", groups)]
        else:
            keys = [
                (
                    fmt.format(v),
                    [[r for r in rows if r.manoeuvre == n and r.value == v] for n in names],
                )
                for v in sorted({r.value for r in rows})
            ]
        for key, per_name in keys:
            cells = [key]
            method = ""
            for match in per_name:
                if not match:
                    cells += ["", ""]
                    continue
                r = match[0]
                mark = "" if r.peaked else " (rising)"
                cells += [f"{r.time_to_peak_s:.1f}{mark}", f"{r.sensor_rise_k:.2f}"]
                method = r.method
            table.add_row(*cells, method)
        console.print(table)
    if study.remesh:
        table = Table(title="Moving the probe vs re-meshing towards the depth (manoeuvre A)")
        for col in (
            "depth, m",
            "t_peak probe, s",
            "t_peak remesh, s",
            "rise probe, K",
            "rise remesh, K",
            "nodes",
        ):
            table.add_column(col, justify="right")
        for c in study.remesh:
            table.add_row(
                f"{c.depth_m:.3f}",
                f"{c.probe_time_to_peak_s:.2f}",
                f"{c.remesh_time_to_peak_s:.2f}",
                f"{c.probe_rise_k:.3f}",
                f"{c.remesh_rise_k:.3f}",
                f"{c.remesh_nodes:,}",
            )
        console.print(table)
    console.print(f"study: {study.seconds:.1f} s")
