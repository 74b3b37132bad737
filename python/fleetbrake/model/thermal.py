"""The block's 3D finite-element thermal model (Rust core, ``fleetbrake._ext``).

Defaults, validation and documentation live here; the core meshes, assembles, factorises
(faer sparse Cholesky: symbolic analysis once per mesh, numeric factorisation once per
distinct system matrix, cached) and integrates in time with the GIL released.

>>> from fleetbrake.fleet.block import BlockGeometry, sensor_point_m
>>> from fleetbrake.model.thermal import BlockModel
>>> model = BlockModel(BlockGeometry(), element="hex8", refinement=0.5)
>>> res = model.simulate(dt_s=1.0, flux_w_m2=np.full(10, 4.0e4), initial_c=20.0,
...                      probes_m=[sensor_point_m(BlockGeometry())])
>>> res.probe_c.shape
(11, 1)

Time scheme (see ``docs/dev/thermal-api.md``): the inputs of step n hold on [t_n, t_n+1];
Crank-Nicolson (second order; the default) or backward Euler, the first ``damped_steps``
steps each taken as two backward-Euler half steps (Rannacher start).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake import _ext
from fleetbrake._ext import (
    InternalError,
    InvalidParameterError,
    InvalidTimeStepError,
    LengthMismatchError,
    LinearAlgebraError,
    MeshError,
    NotPositiveDefiniteError,
    ProbeOutsideError,
    ThermalCoreError,
    UnknownFaceSetError,
)
from fleetbrake.fleet.block import (
    BLOCK_MATERIAL,
    DEFAULT_AMBIENT_C,
    DEFAULT_CONVECTION_W_M2K,
    BlockGeometry,
    Material,
)

__all__ = [
    "BlockModel",
    "BoxModel",
    "InternalError",
    "InvalidParameterError",
    "InvalidTimeStepError",
    "LengthMismatchError",
    "LinearAlgebraError",
    "Mesh",
    "MeshError",
    "NotPositiveDefiniteError",
    "ProbeOutsideError",
    "SimulationResult",
    "ThermalCoreError",
    "UnknownFaceSetError",
]

Element = Literal["hex8", "hex20"]
SchemeName = Literal["crank-nicolson", "backward-euler"]
Precision = Literal["mixed", "double"]
Cholesky = Literal["auto", "simplicial", "supernodal"]

_THETA: dict[str, float] = {"crank-nicolson": 0.5, "backward-euler": 1.0}

AIR_FACES = ("air", "holder")
"""Face sets cooled by air in the declared model (every surface but the friction face)."""


@dataclass(frozen=True)
class Mesh:
    """The mesh arrays: nodes (N, 3) m; elements (E, 8|20) in VTK order; face sets name ->
    (F, 4|8) node indices in VTK quad order, counter-clockwise seen from outside."""

    nodes: NDArray[np.float64]
    elements: NDArray[np.int64]
    face_sets: dict[str, NDArray[np.int64]]
    element: str

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.shape[0])

    def write_vtu(self, path: str, point_data: Mapping[str, ArrayLike] | None = None) -> None:
        """Write the mesh (and nodal fields) as VTU for ParaView."""
        import meshio

        cell_type = "hexahedron" if self.element == "hex8" else "hexahedron20"
        data = {k: np.asarray(v, dtype=np.float64) for k, v in (point_data or {}).items()}
        meshio.Mesh(self.nodes, [(cell_type, self.elements)], point_data=data).write(path)


@dataclass(frozen=True)
class SimulationResult:
    """Outputs of one simulation; every time series has ``n_steps + 1`` rows (t = 0 first)."""

    time_s: NDArray[np.float64]
    probe_c: NDArray[np.float64]
    """(n_steps + 1, P) temperature at each probe."""
    face_mean_c: NDArray[np.float64]
    """Area-weighted mean over the friction face."""
    face_max_c: NDArray[np.float64]
    """Nodal maximum over the friction face."""
    fields_c: NDArray[np.float64]
    """(K, N) full fields at ``field_steps`` (empty unless ``field_every`` > 0)."""
    field_steps: NDArray[np.int64]
    final_c: NDArray[np.float64]
    """The field after the last step, to continue from."""
    energy_stored_j: float
    energy_flux_in_j: float
    energy_convected_out_j: float
    factorizations: int
    seconds_factorization: float
    seconds_stepping: float
    extra: dict[str, float] = field(default_factory=dict)


def _series(name: str, value: float | ArrayLike, n_steps: int) -> NDArray[np.float64]:
    arr = np.ascontiguousarray(np.asarray(value, dtype=np.float64).reshape(-1))
    if arr.size == 1:
        return arr
    if arr.size != n_steps:
        raise LengthMismatchError(
            f"{name} has {arr.size} values but the flux series has {n_steps} steps"
        )
    return arr


class _Model:
    """Shared behaviour of assembled models (the Rust object is ``self._core``)."""

    _core: _ext.ThermalModel

    @property
    def mesh(self) -> Mesh:
        if self._mesh is None:
            self._mesh = Mesh(
                nodes=self._core.nodes(),
                elements=self._core.elements(),
                face_sets=dict(self._core.face_sets()),
                element=self._core.element,
            )
        return self._mesh

    _mesh: Mesh | None = None

    @property
    def n_nodes(self) -> int:
        return int(self._core.n_nodes)

    @property
    def face_areas_m2(self) -> dict[str, float]:
        return dict(self._core.face_areas())

    @property
    def volume_m3(self) -> float:
        return float(self._core.volume_m3)

    @property
    def factor_nnz(self) -> int:
        """Stored entries of the Cholesky factor L."""
        return int(self._core.factor_nnz)

    @property
    def matrix_nnz(self) -> int:
        return int(self._core.matrix_nnz)

    @property
    def is_supernodal(self) -> bool:
        return bool(self._core.is_supernodal)

    @property
    def ordering(self) -> str:
        """Fill-reducing ordering of the factor: "amd" or "nested-dissection"."""
        return str(self._core.ordering)

    def operators(self) -> dict[str, NDArray[np.generic]]:
        """Capacity, conduction and per-face mass/load on the common CSC pattern."""
        return dict(self._core.operators())

    def default_convection(self) -> dict[str, float]:
        return {}

    def simulate(
        self,
        *,
        dt_s: float,
        flux_w_m2: ArrayLike,
        initial_c: float | ArrayLike,
        probes_m: ArrayLike | Sequence[Sequence[float]],
        ambient_c: float | ArrayLike = DEFAULT_AMBIENT_C,
        h_w_m2k: Mapping[str, float | ArrayLike] | None = None,
        scheme: SchemeName = "crank-nicolson",
        damped_steps: int = 1,
        jump_fraction: float = 0.05,
        field_every: int = 0,
        precision: Precision = "mixed",
    ) -> SimulationResult:
        """Integrate from ``initial_c`` over ``len(flux_w_m2)`` steps of ``dt_s``.

        ``flux_w_m2``: heat flux into the friction face per step (W/m^2).
        ``h_w_m2k``: convection coefficient per face set (constant or per step); face sets
        not named are adiabatic; ``None`` gives the declared model's 10 W/m^2 K on every
        surface but the friction face.
        ``ambient_c``: air temperature, constant or per step.
        ``initial_c``: a uniform temperature or a nodal field (N,).
        ``probes_m``: (P, 3) points in the block where the temperature is reported.
        ``damped_steps``/``jump_fraction``: Crank-Nicolson's damped start, restarted after
        every input jump larger than ``jump_fraction`` of the series' magnitude.
        ``precision``: each step solves for its increment from the residual of the current
        state (formed in double precision); "mixed" reads the Cholesky factor in single
        precision in those solves (half their memory traffic; the increment's error is of
        order 1e-6 of the increment, and the global heat balance is kept exact), "double"
        keeps it in double.
        """
        if scheme not in _THETA:
            raise InvalidParameterError(
                f"unknown scheme {scheme!r}; use 'crank-nicolson' or 'backward-euler'"
            )
        if precision not in ("mixed", "double"):
            raise InvalidParameterError(f"unknown precision {precision!r}; use 'mixed' or 'double'")
        if int(damped_steps) < 0 or int(field_every) < 0:
            raise InvalidParameterError("damped_steps and field_every must be >= 0")
        flux = np.ascontiguousarray(np.asarray(flux_w_m2, dtype=np.float64).reshape(-1))
        n_steps = int(flux.size)
        if n_steps == 0:
            raise LengthMismatchError("flux_w_m2 is empty: nothing to simulate")
        ambient = _series("ambient_c", ambient_c, n_steps)
        h = self.default_convection() if h_w_m2k is None else dict(h_w_m2k)
        h_faces = list(h)
        h_values = [_series(f"h_w_m2k[{name!r}]", h[name], n_steps) for name in h_faces]
        initial = np.ascontiguousarray(np.asarray(initial_c, dtype=np.float64).reshape(-1))
        probes = np.ascontiguousarray(np.asarray(probes_m, dtype=np.float64).reshape(-1, 3))
        raw = self._core.simulate(
            float(dt_s),
            n_steps,
            flux if n_steps > 1 else flux.copy(),
            ambient,
            h_faces,
            h_values,
            initial,
            probes,
            _THETA[scheme],
            int(damped_steps),
            float(jump_fraction),
            precision,
            int(field_every),
        )
        return SimulationResult(**raw)


class BlockModel(_Model):
    """The finite-element model of a brake block (body + lug), meshed and assembled.

    ``element``: "hex20" (20-node serendipity, as the paper's Ansys SOLID90; default) or
    "hex8". ``refinement`` multiplies the cell count along every direction (1.0: about 21,000
    nodes with hex20, the paper's 21,076). ``sensor_m``: the point the mesh is graded towards
    (the sensor seat). ``cholesky``: faer's variant, "auto" by default.
    """

    def __init__(
        self,
        geometry: BlockGeometry | None = None,
        material: Material = BLOCK_MATERIAL,
        *,
        element: Element = "hex20",
        refinement: float = 1.0,
        sensor_m: Sequence[float] | None = None,
        grading_ratio: float = 3.0,
        cholesky: Cholesky = "auto",
    ) -> None:
        self.geometry = geometry or BlockGeometry()
        self.material = material
        g = self.geometry
        focus = None if sensor_m is None else tuple(float(v) for v in sensor_m)
        if focus is not None and len(focus) != 3:
            raise InvalidParameterError(f"sensor_m must be a point (x, y, z), got {sensor_m!r}")
        self._mesh = None
        self._core = _ext.ThermalModel.block(
            (
                g.wheel_radius_m,
                g.contact_angle_deg,
                g.block_width_m,
                g.body_thickness_m,
                g.lug_height_m,
                g.lug_angle_deg,
                g.lug_width_m,
            ),
            (material.conductivity_w_mk, material.density_kg_m3, material.specific_heat_j_kgk),
            element,
            float(refinement),
            focus,
            float(grading_ratio),
            cholesky,
        )

    @property
    def friction_area_m2(self) -> float:
        return self.face_areas_m2["friction"]

    def default_convection(self) -> dict[str, float]:
        return dict.fromkeys(AIR_FACES, DEFAULT_CONVECTION_W_M2K)


class BoxModel(_Model):
    """A rectangular box [0, lx] x [0, ly] x [0, lz] (faces x0, x1, y0, y1, z0, z1), for
    verification against analytical solutions. The flux enters through ``flux_face``."""

    def __init__(
        self,
        lengths_m: Sequence[float],
        cells: Sequence[int],
        material: Material = BLOCK_MATERIAL,
        *,
        element: Element = "hex20",
        flux_face: str = "x0",
        cholesky: Cholesky = "auto",
    ) -> None:
        self.material = material
        self._mesh = None
        lx, ly, lz = (float(v) for v in lengths_m)
        nx, ny, nz = (int(v) for v in cells)
        self._core = _ext.ThermalModel.box_(
            (lx, ly, lz),
            (nx, ny, nz),
            (material.conductivity_w_mk, material.density_kg_m3, material.specific_heat_j_kgk),
            element,
            flux_face,
            cholesky,
        )
