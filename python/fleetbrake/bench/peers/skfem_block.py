"""Independent finite-element reference of the block thermal model, written with scikit-fem.

Used only as a reference (tests) and as the benchmark peer of the Rust core
(``fleetbrake.model.thermal``); nothing in production imports it. It takes the mesh arrays of the
contract in ``docs/dev/thermal-api.md`` and reproduces its time scheme exactly, so that the
two codes can be compared like with like:

- inputs of step ``n`` hold on ``[t_n, t_n+1]``;
- ``K_n = K_cond + sum_s h_s,n H_s``, ``f_n = q_n F + sum_s h_s,n T_amb,n G_s``;
- ``(M/dt + theta K_n) T_n+1 = (M/dt - (1 - theta) K_n) T_n + f_n``, theta = 1/2 or 1;
- the first ``damped_steps`` steps are each two backward-Euler steps of ``dt/2``, and so are
  the ``damped_steps`` steps from every input jump (a change between consecutive steps of more
  than ``jump_fraction`` of the series' largest magnitude), for Crank-Nicolson only.

Elements: the contract's 8-node (VTK_HEXAHEDRON) and 20-node (VTK_QUADRATIC_HEXAHEDRON)
hexahedra. The scikit-fem mesh is always a ``MeshHex1`` built from the corner nodes, so the
geometry is trilinear; on 20-node meshes the field is the 20-node serendipity
``ElementHexS2`` whose edge degrees of freedom are the contract's midside nodes. Where a
midside node lies on an arc (the friction face r = R_w and the other cylindrical faces of the
block) the skfem geometry uses the chord instead. The resulting difference is second order in
the element's angular span d_theta: the chord polygon loses a relative area (and volume of the
outer layer) of about d_theta^2 / 24, and a midside node sits a sagitta R d_theta^2 / 8 off
its chord midpoint. For the reference block (R = 0.46 m, theta_c = 29.4 deg) with 16 elements
along the arc, d_theta = 0.032 rad: the friction-face area is 4.3e-5 relative smaller
(0.8 mm^2 of 0.01888 m^2) and the sagitta is 59 micrometres -- far below the differences
any comparison with the Rust core looks at. ``SkfemBlockModel.midside_offset_max_m``,
``volume_m3`` and ``friction_area_m2`` give the figures for the mesh actually passed in.

scikit-fem (and scipy) are optional dev dependencies: they are imported when a model is
built, with a clear message if they are missing. The building steps (the mesh, its degrees of
freedom, its face sets, its matrices) are in :mod:`fleetbrake.bench.peers.skfem_mesh`.

Linear solver: the system matrix is symmetric positive definite, but scipy has no sparse
Cholesky, and scikit-umfpack, scikit-sparse (CHOLMOD) and pypardiso are not installed, so
``scipy.sparse.linalg.factorized`` falls back to SuperLU with its default COLAMD ordering.
SuperLU (``splu``) with the minimum-degree ordering of A^T + A (``permc_spec="MMD_AT_PLUS_A"``),
``diag_pivot_thresh=0`` and SymmetricMode (diagonal pivots, the SPD setting) is the fastest
here: on a 21,603-node hex20 block mesh (1.13 M non-zeros), factorisation 2.0 s and a solve
20-25 ms, against 7-9 s and 47-51 ms for COLAMD, MMD_ATA and ``factorized`` (fill 18.7 M in
L + U; the plain MMD_AT_PLUS_A variants give the same fill and times within noise). Each
distinct system matrix (one per (dt, theta, h) combination) is factorised once; ``SOLVERS``
and ``solver=`` keep the alternatives for comparison.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake.bench.peers.skfem_mesh import (
    assemble,
    checked_mesh_arrays,
    dof_map,
    facet_sets,
    skfem_mesh,
)
from fleetbrake.fleet.block import Material

__all__ = [
    "DEFAULT_SOLVER",
    "SOLVERS",
    "SkfemBlockModel",
    "SkfemResult",
]

# --- linear solvers --------------------------------------------------------------------------


Solve = Callable[[NDArray[np.float64]], NDArray[np.float64]]
"""A factorised system: right-hand side -> solution."""


def _splu(permc_spec: str, symmetric: bool) -> Callable[[Any], Solve]:
    def factorise(a: Any) -> Solve:
        from scipy.sparse.linalg import splu

        if symmetric:
            lu = splu(
                a.tocsc(),
                permc_spec=permc_spec,
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        else:
            lu = splu(a.tocsc(), permc_spec=permc_spec)
        solve: Solve = lu.solve
        return solve

    return factorise


def _factorized(a: Any) -> Solve:
    from scipy.sparse.linalg import factorized

    solve: Solve = factorized(a.tocsc())
    return solve


SOLVERS: dict[str, Callable[[Any], Solve]] = {
    "splu-mmd-at-plus-a-sym": _splu("MMD_AT_PLUS_A", symmetric=True),
    "splu-mmd-at-plus-a": _splu("MMD_AT_PLUS_A", symmetric=False),
    "splu-colamd": _splu("COLAMD", symmetric=False),
    "splu-mmd-ata": _splu("MMD_ATA", symmetric=False),
    "factorized": _factorized,
}
"""Factorisations to choose from: matrix -> solve function."""

DEFAULT_SOLVER = "splu-mmd-at-plus-a-sym"
"""Fastest here; see the module docstring."""


# --- the model -------------------------------------------------------------------------------


@dataclass(frozen=True)
class SkfemResult:
    """Output of :meth:`SkfemBlockModel.simulate`, shaped like the contract's result."""

    time_s: NDArray[np.float64]
    """(n_steps + 1,) 0, dt, 2 dt, ..."""
    probe_c: NDArray[np.float64]
    """(n_steps + 1, P) temperature at each probe point."""
    face_mean_c: NDArray[np.float64]
    """(n_steps + 1,) area-weighted mean over the friction face."""
    face_max_c: NDArray[np.float64]
    """(n_steps + 1,) nodal maximum over the friction face."""
    fields_c: NDArray[np.float64] | None
    """(K, N) whole field every ``field_every`` steps (from step 0), in the caller's node order."""
    field_steps: NDArray[np.int64] | None
    """(K,) the step index of each row of ``fields_c``."""
    seconds_assembly: float
    """Mesh conversion, bases and assembly of every matrix and vector (done once per model)."""
    seconds_factorisation: float
    """Forming and factorising the system matrices of this run."""
    seconds_stepping: float
    """Locating the probes and the time loop (right-hand sides, solves, outputs), without
    factorisations."""
    n_factorisations: int
    solver: str


class SkfemBlockModel:
    """scikit-fem model of heat conduction in a block meshed by the contract's arrays.

    Parameters
    ----------
    nodes
        (N, 3) node coordinates, metres.
    elements
        (E, 8) VTK_HEXAHEDRON or (E, 20) VTK_QUADRATIC_HEXAHEDRON node indices.
    face_sets
        name -> (F, 4) or (F, 8) node indices of boundary faces, VTK quad order (the first
        four are the corners). Must include ``"friction"``.
    material
        Block material (k, rho, c).
    intorder
        Quadrature order of the volume integrals (default 4 for hex8, 6 for hex20: the
        capacity matrix is then exact on trilinear geometry); faces use the same order.
    solver
        Key of :data:`SOLVERS`.
    """

    def __init__(
        self,
        nodes: ArrayLike,
        elements: ArrayLike,
        face_sets: Mapping[str, ArrayLike],
        material: Material,
        *,
        intorder: int | None = None,
        solver: str = DEFAULT_SOLVER,
    ) -> None:
        try:
            import skfem  # noqa: F401  # imported here to say what is missing
        except ImportError as exc:
            raise ImportError(
                "fleetbrake.bench.peers.skfem_block needs scikit-fem and scipy, optional dev "
                "dependencies: install them with `pip install -e '.[dev]'` "
                "(or `pip install scikit-fem scipy`)"
            ) from exc
        if solver not in SOLVERS:
            raise ValueError(f"unknown solver {solver!r}; choose one of {sorted(SOLVERS)}")
        t0 = time.perf_counter()
        nodes, elements = checked_mesh_arrays(nodes, elements, face_sets)
        n_nodes = nodes.shape[0]
        self.material = material
        self.solver = solver
        self.n_nodes = n_nodes
        self.nodes_per_element = elements.shape[1]
        quadratic = self.nodes_per_element == 20
        if intorder is None:
            intorder = 6 if quadratic else 4
        self.intorder = intorder

        mesh = skfem_mesh(nodes, elements, quadratic, intorder)
        dofs = dof_map(nodes, elements, mesh, quadratic)
        self._dof_to_node = dofs.dof_to_node
        self._node_to_dof = dofs.node_to_dof
        self.midside_offset_max_m = dofs.midside_offset_max_m
        facets, self.face_node_sets = facet_sets(face_sets, mesh, dofs, n_nodes, quadratic)
        self.face_set_names = tuple(facets)

        matrices = assemble(mesh, facets, material, intorder)
        self._M = matrices.capacity
        self._K = matrices.conduction
        self._H: dict[str, Any] = matrices.convection
        self._G: dict[str, NDArray[np.float64]] = matrices.face_loads
        self.volume_m3 = matrices.volume_m3
        self.face_area_m2 = {name: float(g.sum()) for name, g in self._G.items()}
        self.friction_area_m2 = self.face_area_m2["friction"]
        self._friction_dofs = dofs.node_to_dof[self.face_node_sets["friction"]]

        self.mesh = mesh.mesh
        self.basis = mesh.basis
        self.element = mesh.element
        self.seconds_assembly = time.perf_counter() - t0

    # -- matrices, in the caller's node order (for checks and tests)

    def _to_nodes(self, a: Any) -> Any:
        p = self._node_to_dof
        return a[p][:, p]

    @property
    def capacity_matrix(self) -> Any:
        """M = rho c int N N^T dV, caller's node order (scipy CSR)."""
        return self._to_nodes(self._M)

    @property
    def conduction_matrix(self) -> Any:
        """K_cond = k int grad N . grad N^T dV, caller's node order."""
        return self._to_nodes(self._K)

    def convection_matrix(self, name: str) -> Any:
        """H_s = int_s N N^T dA of face set ``name``, caller's node order."""
        return self._to_nodes(self._H[name])

    def face_load(self, name: str) -> NDArray[np.float64]:
        """G_s = int_s N dA of face set ``name``, caller's node order."""
        return self._G[name][self._node_to_dof]

    # -- probes

    def probe_matrix(self, points_m: ArrayLike, tol: float = 1e-7) -> Any:
        """(P, N) sparse matrix giving the field at each point, caller's node order.

        Each point is located in the element that holds it (inverse trilinear map by Newton
        from every element whose bounding box holds the point, keeping the one where the
        reference coordinates lie in [0, 1]^3, up to ``tol``); the value is interpolated
        with that element's shape functions. Points on a shared face get either element:
        the field is continuous.
        """
        from scipy.sparse import coo_matrix

        x = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        mesh, mapping = self.mesh, self.mesh.mapping()
        xyz = mesh.p[:, mesh.t]  # (3, 8, E)
        lo, hi = xyz.min(axis=1), xyz.max(axis=1)
        pad = tol * (hi - lo).max(axis=0)
        rows, cols, vals = [], [], []
        for i, point in enumerate(x):
            inside = ((point[:, None] >= lo - pad) & (point[:, None] <= hi + pad)).all(axis=0)
            cand = np.nonzero(inside)[0]
            if cand.size == 0:
                raise ValueError(f"probe {i} at {point.tolist()} is outside the mesh")
            target = np.repeat(point[:, None, None], cand.size, axis=1)  # (3, C, 1)
            ref = np.full((3, cand.size, 1), 0.5)
            for _ in range(50):
                step = np.einsum(
                    "ijkl,jkl->ikl", mapping.invDF(ref, cand), target - mapping.F(ref, cand)
                )
                ref = ref + step
                if np.abs(step).max() < 1e-13:
                    break
            outside = np.maximum(-ref, ref - 1.0).max(axis=0)[:, 0]
            best = int(np.argmin(outside))
            if outside[best] > tol:
                raise ValueError(f"probe {i} at {point.tolist()} is outside the mesh")
            e = int(cand[best])
            X = np.clip(ref[:, best, :], 0.0, 1.0)  # (3, 1)
            for j in range(self.basis.Nbfun):
                rows.append(i)
                cols.append(self._dof_to_node[self.basis.element_dofs[j, e]])
                vals.append(float(self.element.lbasis(X, j)[0][0]))
        return coo_matrix((vals, (rows, cols)), shape=(x.shape[0], self.n_nodes)).tocsr()

    # -- time stepping

    def simulate(
        self,
        dt_s: float,
        flux_w_m2: ArrayLike,
        ambient_c: float | ArrayLike,
        initial_c: float | ArrayLike,
        h_w_m2k: Mapping[str, float | ArrayLike],
        probes_m: ArrayLike,
        scheme: str = "crank-nicolson",
        damped_steps: int = 1,
        field_every: int = 0,
        jump_fraction: float = 0.05,
    ) -> SkfemResult:
        """Run the contract's time scheme; see the module docstring and thermal-api.md.

        ``h_w_m2k`` gives a convection coefficient (float or per step) for some face sets;
        a face set it does not name is adiabatic (the friction face in particular).
        """
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be positive, got {dt_s!r}")
        theta = {"crank-nicolson": 0.5, "backward-euler": 1.0}.get(scheme)
        if theta is None:
            raise ValueError(f"scheme must be 'crank-nicolson' or 'backward-euler', got {scheme!r}")
        if int(damped_steps) != damped_steps or damped_steps < 0:
            raise ValueError(f"damped_steps must be a non-negative integer, got {damped_steps!r}")
        if int(field_every) != field_every or field_every < 0:
            raise ValueError(f"field_every must be a non-negative integer, got {field_every!r}")
        flux = np.asarray(flux_w_m2, dtype=np.float64)
        if flux.ndim != 1 or not np.isfinite(flux).all():
            raise ValueError("flux_w_m2 must be a finite (n_steps,) array")
        n_steps = flux.size
        ambient = _per_step(ambient_c, n_steps, "ambient_c")
        unknown = set(h_w_m2k) - set(self.face_set_names)
        if unknown:
            raise KeyError(f"h_w_m2k names unknown face sets {sorted(unknown)}")
        conv = [(s, _per_step(h_w_m2k[s], n_steps, f"h_w_m2k[{s!r}]")) for s in h_w_m2k]
        conv = [(s, h) for s, h in conv if (h != 0).any()]
        init = np.asarray(initial_c, dtype=np.float64)
        if init.ndim == 0:
            T = np.full(self.n_nodes, float(init))
        elif init.shape == (self.n_nodes,):
            T = init[self._dof_to_node].copy()
        else:
            raise ValueError(f"initial_c must be a float or ({self.n_nodes},), got {init.shape}")
        if not np.isfinite(T).all():
            raise ValueError("initial_c must be finite")

        t_start = time.perf_counter()
        P = self.probe_matrix(probes_m)[:, self._dof_to_node]  # acts on dof-ordered fields
        g_fric = self._G["friction"] / self.friction_area_m2
        fdofs = self._friction_dofs
        probe = np.empty((n_steps + 1, P.shape[0]))
        mean = np.empty(n_steps + 1)
        peak = np.empty(n_steps + 1)
        keep = field_every > 0
        fields: list[NDArray[np.float64]] = []
        field_steps: list[int] = []

        def record(n: int, T: NDArray[np.float64]) -> None:
            probe[n] = P @ T
            mean[n] = g_fric @ T
            peak[n] = T[fdofs].max()
            if keep and n % field_every == 0:
                fields.append(T[self._node_to_dof])
                field_steps.append(n)

        record(0, T)
        damped = _damped_mask(
            n_steps,
            damped_steps,
            jump_fraction if theta < 1.0 else 0.0,
            [flux, ambient, *(h for _, h in conv)],
        )
        factorise = SOLVERS[self.solver]
        # A = M/dt + th K = th (M/tau + K) with tau = th dt: one factor per (tau, h), shared
        # by Crank-Nicolson's steps and the damped start's half steps (tau = dt/2 both), as
        # the Rust core does
        factors: dict[tuple[float, tuple[float, ...]], Solve] = {}
        cache: dict[tuple[float, float, tuple[float, ...]], tuple[Solve, Any]] = {}
        t_fact = 0.0
        n_fact = 0

        def system(dt: float, th: float, hs: tuple[float, ...]) -> tuple[Solve, Any]:
            """(solve, B) with (M/dt + th K_n) T+ = B T + f; factorised once per matrix."""
            nonlocal t_fact, n_fact
            key = (dt, th, hs)
            hit = cache.get(key)
            if hit is not None:
                return hit
            t1 = time.perf_counter()
            K = self._K.copy()
            for (s, _), h in zip(conv, hs, strict=True):
                K = K + h * self._H[s]
            tau = th * dt
            s_solve = factors.get((tau, hs))
            if s_solve is None:
                if len(factors) >= 4:  # factors are large: keep the 4 most recent matrices
                    factors.pop(next(iter(factors)))
                s_solve = factors[(tau, hs)] = factorise((self._M * (1.0 / tau) + K).tocsc())
                n_fact += 1
            B = (self._M * (1.0 / dt) - (1.0 - th) * K).tocsr()
            if len(cache) >= 8:
                cache.pop(next(iter(cache)))

            def solve(b: NDArray[np.float64], s_solve: Solve = s_solve) -> NDArray[np.float64]:
                return s_solve(b / th)

            cache[key] = (solve, B)
            t_fact += time.perf_counter() - t1
            return cache[key]

        for n in range(n_steps):
            hs = tuple(float(h[n]) for _, h in conv)
            f = flux[n] * self._G["friction"]
            for (s, _), h in zip(conv, hs, strict=True):
                f = f + (h * ambient[n]) * self._G[s]
            if damped[n]:
                solve, B = system(0.5 * dt_s, 1.0, hs)
                T = solve(B @ T + f)
                T = solve(B @ T + f)
            else:
                solve, B = system(dt_s, theta, hs)
                T = solve(B @ T + f)
            record(n + 1, T)
        t_total = time.perf_counter() - t_start

        return SkfemResult(
            time_s=dt_s * np.arange(n_steps + 1, dtype=np.float64),
            probe_c=probe,
            face_mean_c=mean,
            face_max_c=peak,
            fields_c=np.array(fields) if keep else None,
            field_steps=np.array(field_steps, dtype=np.int64) if keep else None,
            seconds_assembly=self.seconds_assembly,
            seconds_factorisation=t_fact,
            seconds_stepping=t_total - t_fact,
            n_factorisations=n_fact,
            solver=self.solver,
        )


def _per_step(value: float | ArrayLike, n_steps: int, name: str) -> NDArray[np.float64]:
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 0:
        a = np.full(n_steps, float(a))
    if a.shape != (n_steps,) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be a finite float or ({n_steps},) array")
    return a


def _damped_mask(
    n_steps: int, damped_steps: int, jump_fraction: float, series: list[Any]
) -> list[bool]:
    """Steps taken as two backward-Euler half steps: the first ``damped_steps`` and the
    ``damped_steps`` from every jump of an input series (the contract's rule)."""
    mask = [False] * n_steps
    starts = [0]
    if jump_fraction > 0.0:
        for s in series:
            values = np.asarray(s, dtype=np.float64).reshape(-1)
            if values.size != n_steps:
                continue
            scale = float(np.abs(values).max()) if values.size else 0.0
            if scale > 0.0:
                starts += (
                    np.flatnonzero(np.abs(np.diff(values)) > jump_fraction * scale) + 1
                ).tolist()
    for k in starts:
        for m in range(k, min(k + damped_steps, n_steps)):
            mask[m] = True
    return mask
