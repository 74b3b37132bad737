"""What the reproduction computes: one manoeuvre's run, the calibration, the whole reproduction
and the study, as typed results (``to_dict()`` gives the JSON of ``fleetbrake paper --json``).

The computation is in :mod:`fleetbrake.paper.reproduction` and :mod:`fleetbrake.paper.study`;
the outputs (tables, pictures, VTU fields) read these types.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.physics import EventHeatInput, Manoeuvre
from fleetbrake.model.thermal import BlockModel
from fleetbrake.paper.peaks import Peak, peak_times
from fleetbrake.paper.settings import RunSettings

__all__ = [
    "Calibration",
    "ManoeuvreResult",
    "PaperReproduction",
    "RemeshCheck",
    "Study",
    "StudyRow",
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ManoeuvreResult:
    """One manoeuvre simulated in the declared model, with what the paper reports and more."""

    name: str
    manoeuvre: Manoeuvre
    heat: EventHeatInput
    convection_w_m2k: float
    ambient_c: float
    flux_scale: float
    """Multiplies Phi_b of the heat input (1 for the declared model)."""
    sensor_m: tuple[float, float, float]
    sensor_depth_m: float
    time_s: FloatArray
    flux_w_m2: FloatArray
    """Per step (n_steps): the flux into the friction face on [t_n, t_n+1]."""
    sensor_c: FloatArray
    depths_m: FloatArray
    depth_c: FloatArray
    """(n_steps + 1, len(depths_m)): probes on the sensor's radial line."""
    contact_mean_c: FloatArray
    contact_max_c: FloatArray
    peak: Peak
    field_end_c: FloatArray | None
    """The whole field at the end of braking (t = duration), or None."""
    field_peak_c: FloatArray | None
    """The whole field at the step nearest the sensor's maximum, or None."""
    field_peak_time_s: float
    seconds: float
    energy_in_j: float

    @property
    def time_to_peak_s(self) -> float:
        return self.peak.time_s

    @property
    def sensor_peak_c(self) -> float:
        return self.peak.value_c

    @property
    def sensor_rise_k(self) -> float:
        return self.peak.value_c - self.manoeuvre.t0_c

    @property
    def paper_time_to_peak_s(self) -> float | None:
        return self.manoeuvre.time_to_peak_s

    @property
    def time_to_peak_rel_error(self) -> float | None:
        paper = self.manoeuvre.time_to_peak_s
        return None if paper is None else self.time_to_peak_s / paper - 1.0

    @property
    def block_flux_w_m2(self) -> float:
        return self.heat.block_flux_w_m2 * self.flux_scale

    def _at(self, series: FloatArray, t_s: float) -> float:
        return float(np.interp(t_s, self.time_s, series))

    @property
    def contact_max_end_c(self) -> float:
        return self._at(self.contact_max_c, self.manoeuvre.duration_s)

    @property
    def contact_mean_end_c(self) -> float:
        return self._at(self.contact_mean_c, self.manoeuvre.duration_s)

    @property
    def contact_max_at_peak_c(self) -> float:
        return self._at(self.contact_max_c, self.time_to_peak_s)

    @property
    def contact_mean_at_peak_c(self) -> float:
        return self._at(self.contact_mean_c, self.time_to_peak_s)

    def curve_at_depth(self, depth_m: float) -> FloatArray:
        """The temperature at ``depth_m`` on the sensor's line, linear between the probes."""
        d = self.depths_m
        if not d[0] <= depth_m <= d[-1]:
            raise ValueError(f"depth {depth_m} m outside the probes' {d[0]}..{d[-1]} m")
        k = int(np.clip(np.searchsorted(d, depth_m) - 1, 0, d.size - 2))
        w = (depth_m - d[k]) / (d[k + 1] - d[k])
        return (1.0 - w) * self.depth_c[:, k] + w * self.depth_c[:, k + 1]

    def depth_peaks(self) -> tuple[FloatArray, FloatArray, NDArray]:
        """(time to peak, rise, interior) at every probe depth."""
        t, v, interior = peak_times(self.time_s, self.depth_c)
        return t, v - self.manoeuvre.t0_c, interior

    def to_dict(self, *, curve_every_s: float = 10.0) -> dict[str, Any]:
        forces = {k: float(v) for k, v in dataclasses.asdict(self.heat.forces).items()}
        every = max(1, round(curve_every_s / float(self.time_s[1] - self.time_s[0])))
        paper = self.paper_time_to_peak_s
        rel = self.time_to_peak_rel_error
        return {
            "time_to_peak_s": round(self.time_to_peak_s, 2),
            "paper_time_to_peak_s": paper,
            "time_to_peak_rel_error": None if rel is None else round(rel, 4),
            "peak_within_horizon": self.peak.interior,
            "sensor_rise_k": round(self.sensor_rise_k, 3),
            "sensor_peak_c": round(self.sensor_peak_c, 3),
            "sensor_depth_m": self.sensor_depth_m,
            "t0_c": self.manoeuvre.t0_c,
            "ambient_c": self.ambient_c,
            "convection_w_m2k": self.convection_w_m2k,
            "duration_s": self.manoeuvre.duration_s,
            "p_mean_bar": self.manoeuvre.p_mean_bar,
            "mean_speed_m_s": round(self.manoeuvre.mean_speed_m_s, 4),
            "contact_max_end_c": round(self.contact_max_end_c, 3),
            "contact_mean_end_c": round(self.contact_mean_end_c, 3),
            "contact_max_at_peak_c": round(self.contact_max_at_peak_c, 3),
            "contact_mean_at_peak_c": round(self.contact_mean_at_peak_c, 3),
            "power_w": round(self.heat.power_w * self.flux_scale, 3),
            "frictional_flux_w_m2": round(self.heat.frictional_flux_w_m2 * self.flux_scale, 3),
            "alpha": round(self.heat.alpha, 6),
            "flux_w_m2": round(self.block_flux_w_m2, 3),
            "block_energy_j": round(self.energy_in_j, 1),
            "force_chain": forces,
            "sensor_curve": {
                "time_s": [float(t) for t in self.time_s[::every]],
                "sensor_c": [round(float(v), 3) for v in self.sensor_c[::every]],
            },
        }


@dataclass(frozen=True)
class Calibration:
    """One sensor depth fitted to both paper times to peak (least squares of relative errors)."""

    sensor_depth_m: float
    time_to_peak_s: Mapping[str, float]
    paper_time_to_peak_s: Mapping[str, float]
    rel_error: Mapping[str, float]
    sensor_rise_k: Mapping[str, float]
    rms_rel_error: float
    depth_range_m: tuple[float, float]
    depths_m: FloatArray
    """The probe depths of the curves below."""
    time_to_peak_curves_s: Mapping[str, FloatArray]
    """Time to peak at every probe depth, per manoeuvre."""

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "sensor_depth_m": round(self.sensor_depth_m, 6),
            "rms_rel_error": round(self.rms_rel_error, 5),
            "depth_range_m": list(self.depth_range_m),
        }
        for name in self.time_to_peak_s:
            out[name] = {
                "time_to_peak_s": round(self.time_to_peak_s[name], 2),
                "paper_time_to_peak_s": self.paper_time_to_peak_s[name],
                "rel_error": round(self.rel_error[name], 5),
                "sensor_rise_k": round(self.sensor_rise_k[name], 3),
            }
        return out


@dataclass
class PaperReproduction:
    """Manoeuvres A and B on the wagon's block, and the calibrated sensor depth."""

    wagon: WagonConfig
    settings: RunSettings
    model: BlockModel
    runs: dict[str, ManoeuvreResult]
    calibration: Calibration
    seconds_mesh: float
    seconds: float

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {name: run.to_dict() for name, run in self.runs.items()}
        out["calibration"] = self.calibration.to_dict()
        out["model"] = {
            "element": self.settings.element,
            "refinement": self.settings.refinement,
            "nodes": self.model.n_nodes,
            "dt_s": self.settings.dt_s,
            "horizon_s": self.settings.horizon_s,
            "scheme": "crank-nicolson, 1 damped start step",
            "mesh_graded_towards_m": list(self.wagon.sensor_point_m),
            "probe_spacing_m": self.settings.probe_spacing_m,
        }
        out["seconds"] = {
            "mesh": round(self.seconds_mesh, 2),
            **{name: round(run.seconds, 2) for name, run in self.runs.items()},
            "total": round(self.seconds, 2),
        }
        return out


@dataclass(frozen=True)
class StudyRow:
    """Time to peak and rise of the sensor for one manoeuvre and one parameter value (the
    other parameters at their reproduction values)."""

    manoeuvre: str
    parameter: str
    """sensor_depth_m, convection_w_m2k, cylinder_diameter_m, flux_scale or t0_c."""
    value: float
    time_to_peak_s: float
    sensor_rise_k: float
    peaked: bool
    """False: the sensor still rose at the end of the horizon (time to peak = horizon)."""
    method: str
    """probe (a probe of the reproduction's run), run (its own simulation) or superposition."""


@dataclass(frozen=True)
class RemeshCheck:
    """A sensor at ``depth_m`` read on the mesh graded towards the registry's seat (probe)
    against a mesh graded towards ``depth_m`` itself (remesh)."""

    manoeuvre: str
    depth_m: float
    probe_time_to_peak_s: float
    remesh_time_to_peak_s: float
    probe_rise_k: float
    remesh_rise_k: float
    remesh_nodes: int


@dataclass
class Study:
    rows: list[StudyRow]
    remesh: list[RemeshCheck] = field(default_factory=list)
    seconds: float = 0.0

    def select(self, parameter: str, manoeuvre: str | None = None) -> list[StudyRow]:
        return [
            r
            for r in self.rows
            if r.parameter == parameter and (manoeuvre is None or r.manoeuvre == manoeuvre)
        ]

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for row in self.rows:
            out.setdefault(row.parameter, []).append(
                {
                    "manoeuvre": row.manoeuvre,
                    "value": row.value,
                    "time_to_peak_s": round(row.time_to_peak_s, 2),
                    "sensor_rise_k": round(row.sensor_rise_k, 3),
                    "peaked": row.peaked,
                    "method": row.method,
                }
            )
        out["remesh_check"] = [
            {k: (round(v, 4) if isinstance(v, float) else v) for k, v in vars(c).items()}
            for c in self.remesh
        ]
        out["seconds"] = round(self.seconds, 2)
        return out
