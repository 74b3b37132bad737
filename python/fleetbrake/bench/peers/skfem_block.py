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
built, with a clear message if they are missing.

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
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake.fleet.block import Material

__all__ = [
    "DEFAULT_SOLVER",
    "SOLVERS",
    "VTK_HEX20_EDGES",
    "VTK_TO_SKFEM_HEX8",
    "SkfemBlockModel",
    "SkfemResult",
]

# --- node orders -----------------------------------------------------------------------------

VTK_HEX8_PARAM = np.array(
    [
        [0, 0, 0],
        [1, 0, 0],
        [1, 1, 0],
        [0, 1, 0],
        [0, 0, 1],
        [1, 0, 1],
        [1, 1, 1],
        [0, 1, 1],
    ],
    dtype=np.float64,
)
"""Parametric (r, s, t) in [0, 1]^3 of the 8 corners of a VTK_HEXAHEDRON."""

VTK_HEX20_EDGES = (
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 0),
    (4, 5),
    (5, 6),
    (6, 7),
    (7, 4),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
)
"""Corner pairs of the midside nodes 8..19 of a VTK_QUADRATIC_HEXAHEDRON, in order."""

# scikit-fem's reference hexahedron (RefHex.p, ElementHex1/ElementHexS2 doflocs) numbers the
# corners (1,1,1), (1,1,0), (1,0,1), (0,1,1), (1,0,0), (0,1,0), (0,0,1), (0,0,0). Identifying
# skfem's reference coordinates with VTK's parametric ones, skfem corner i is VTK corner
# VTK_TO_SKFEM_HEX8[i]; the map keeps the orientation, so a VTK cell with a positive Jacobian
# has a positive skfem Jacobian (checked on every element when a model is built). Note that
# skfem's own MeshHex1 constructors (the unit cube, init_tensor) use the mirror image, whose
# Jacobian is negative; skfem integrates with |det J| and does not mind either way.
VTK_TO_SKFEM_HEX8 = np.array([6, 2, 5, 7, 1, 3, 4, 0], dtype=np.int64)


def _skfem_local_to_vtk(n_nodes: int) -> NDArray[np.int64]:
    """VTK local node index of each local degree of freedom of ElementHex1 / ElementHexS2."""
    from skfem.refdom import RefHex

    if n_nodes == 8:
        return VTK_TO_SKFEM_HEX8.copy()
    midside = {frozenset(e): 8 + i for i, e in enumerate(VTK_HEX20_EDGES)}
    edges = [
        midside[frozenset((int(VTK_TO_SKFEM_HEX8[a]), int(VTK_TO_SKFEM_HEX8[b])))]
        for a, b in RefHex.edges
    ]
    return np.concatenate([VTK_TO_SKFEM_HEX8, np.array(edges, dtype=np.int64)])


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


# --- building a model: the mesh, its degrees of freedom, its face sets, its matrices -------


def _checked_mesh_arrays(
    nodes: ArrayLike, elements: ArrayLike, face_sets: Mapping[str, ArrayLike]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The contract's node and element arrays, checked (shapes, types, indices)."""
    nodes = np.ascontiguousarray(nodes, dtype=np.float64)
    elements = np.asarray(elements)
    if nodes.ndim != 2 or nodes.shape[1] != 3 or not np.isfinite(nodes).all():
        raise ValueError(f"nodes must be a finite (N, 3) array, got shape {nodes.shape}")
    if elements.ndim != 2 or elements.shape[1] not in (8, 20) or elements.shape[0] == 0:
        raise ValueError(
            f"elements must be (E, 8) or (E, 20) node indices, got shape {elements.shape}"
        )
    if not np.issubdtype(elements.dtype, np.integer):
        raise ValueError(f"elements must be integers, got dtype {elements.dtype}")
    elements = elements.astype(np.int64)
    n_nodes = nodes.shape[0]
    if elements.min() < 0 or elements.max() >= n_nodes:
        raise ValueError("elements refer to nodes outside 0..N-1")
    if "friction" not in face_sets:
        raise ValueError("face_sets must contain 'friction'")
    return nodes, elements


class _Mesh(NamedTuple):
    """The scikit-fem mesh built from the corner nodes, its element and volume basis."""

    mesh: Any
    element: Any
    basis: Any
    node_to_vertex: NDArray[np.int64]
    """Each of the caller's nodes' vertex in the skfem mesh (-1: a midside node)."""


def _skfem_mesh(
    nodes: NDArray[np.float64], elements: NDArray[np.int64], quadratic: bool, intorder: int
) -> _Mesh:
    """The mesh from the corner nodes, in skfem's corner order, with a positive Jacobian at
    every quadrature point and every corner (checked)."""
    import skfem

    corners = np.unique(elements[:, :8])
    node_to_vertex = np.full(nodes.shape[0], -1, dtype=np.int64)
    node_to_vertex[corners] = np.arange(corners.size)
    t = node_to_vertex[elements[:, VTK_TO_SKFEM_HEX8]].T
    mesh = skfem.MeshHex1(np.ascontiguousarray(nodes[corners].T), np.ascontiguousarray(t))
    elem = skfem.ElementHexS2() if quadratic else skfem.ElementHex1()
    basis = skfem.CellBasis(mesh, elem, intorder=intorder)

    mapping = mesh.mapping()
    det_q = mapping.detDF(basis.X)
    det_c = mapping.detDF(np.ascontiguousarray(mesh.elem.refdom.p))
    det_min = np.minimum(det_q.min(axis=1), det_c.min(axis=1))
    if (det_min <= 0).any():
        bad = np.nonzero(det_min <= 0)[0]
        raise ValueError(
            f"{bad.size} element(s) have a non-positive Jacobian after the VTK -> skfem "
            f"node-order conversion (first: {bad[:10].tolist()}): inverted, degenerate or "
            "not in VTK node order"
        )
    return _Mesh(mesh, elem, basis, node_to_vertex)


class _DofMap(NamedTuple):
    """The degrees of freedom and the caller's nodes, one to one."""

    dof_to_node: NDArray[np.int64]
    node_to_dof: NDArray[np.int64]
    midside_offset_max_m: float
    """Largest distance of a midside node from skfem's chord midpoint of its edge."""


def _dof_map(
    nodes: NDArray[np.float64], elements: NDArray[np.int64], mesh: _Mesh, quadratic: bool
) -> _DofMap:
    """Each degree of freedom's node and each node's degree of freedom (checked to be one to
    one, and the midside nodes near the middle of their edges)."""
    n_nodes = nodes.shape[0]
    basis = mesh.basis
    local = _skfem_local_to_vtk(elements.shape[1])
    element_nodes = elements[:, local].T  # (nbfun, E), skfem local order
    edofs = basis.element_dofs
    dof_to_node = np.full(basis.N, -1, dtype=np.int64)
    dof_to_node[edofs.ravel()] = element_nodes.ravel()
    if (dof_to_node[edofs] != element_nodes).any():
        raise ValueError(
            "elements sharing an edge disagree on its midside node (non-conforming mesh "
            "or midside nodes not in VTK_QUADRATIC_HEXAHEDRON order)"
        )
    if basis.N != n_nodes or np.unique(dof_to_node).size != n_nodes:
        raise ValueError(
            f"the {n_nodes} nodes do not map one-to-one onto scikit-fem's {basis.N} degrees "
            f"of freedom (the elements use {np.unique(elements).size} nodes): every node "
            "must belong to an element, and be either a corner or a midside node"
        )
    node_to_dof = np.empty(n_nodes, dtype=np.int64)
    node_to_dof[dof_to_node] = np.arange(n_nodes)

    # midside nodes against skfem's (chord-midpoint) positions of the edge dofs
    offset = np.linalg.norm(basis.doflocs - nodes[dof_to_node].T, axis=0)
    offset_max_m = float(offset.max())
    if quadratic:
        edge_dofs = basis.dofs.edge_dofs[0]
        ends = mesh.mesh.p[:, mesh.mesh.edges]
        length = np.linalg.norm(ends[:, 0] - ends[:, 1], axis=0)
        ratio = offset[edge_dofs] / length
        if ratio.max() > 0.25:
            raise ValueError(
                "a midside node lies far from the middle of its edge "
                f"(offset / edge length = {ratio.max():.3g}): midside nodes not in "
                "VTK_QUADRATIC_HEXAHEDRON order?"
            )
    elif offset_max_m > 0:  # pragma: no cover - exact by construction
        raise AssertionError("hex8 degrees of freedom do not sit on their nodes")
    return _DofMap(dof_to_node, node_to_dof, offset_max_m)


def _facet_sets(
    face_sets: Mapping[str, ArrayLike], mesh: _Mesh, dofs: _DofMap, n_nodes: int, quadratic: bool
) -> tuple[dict[str, NDArray[np.int64]], dict[str, NDArray[np.int64]]]:
    """Each face set's boundary facets of the mesh, and its nodes (checked: every face a
    boundary face, listed once, its nodes those of the matched facets)."""
    boundary = mesh.mesh.boundary_facets()
    keys = np.sort(mesh.mesh.facets[:, boundary], axis=0).T
    facet_of = {tuple(k): int(f) for k, f in zip(keys.tolist(), boundary, strict=True)}
    face_nodes_per = 8 if quadratic else 4
    facet_sets: dict[str, NDArray[np.int64]] = {}
    face_node_sets: dict[str, NDArray[np.int64]] = {}
    for name, given in face_sets.items():
        faces = np.asarray(given)
        if faces.ndim != 2 or faces.shape[1] != face_nodes_per or faces.shape[0] == 0:
            raise ValueError(
                f"face set {name!r} must be a non-empty (F, {face_nodes_per}) array for "
                f"{20 if quadratic else 8}-node elements, got shape {faces.shape}"
            )
        faces = faces.astype(np.int64)
        if faces.min() < 0 or faces.max() >= n_nodes:
            raise ValueError(f"face set {name!r} refers to nodes outside 0..N-1")
        vkeys = np.sort(mesh.node_to_vertex[faces[:, :4]], axis=1)
        found = [facet_of.get(tuple(k)) for k in vkeys.tolist()]
        missing = [i for i, f in enumerate(found) if f is None]
        if missing:
            i = missing[0]
            raise ValueError(
                f"face set {name!r}: {len(missing)} face(s) are not boundary faces of the "
                f"mesh (first: face {i}, nodes {faces[i].tolist()})"
            )
        facets = np.array(found, dtype=np.int64)
        if np.unique(facets).size != facets.size:
            raise ValueError(f"face set {name!r} lists a face twice")
        # every node listed must be a dof of the matched facets, and vice versa
        want = np.unique(faces)
        have = np.unique(dofs.dof_to_node[mesh.basis.get_dofs(facets=facets).all()])
        if want.size != have.size or (want != have).any():
            raise ValueError(
                f"face set {name!r}: its nodes are not those of the matched boundary faces "
                "(midside nodes not in VTK quadratic-quad order?)"
            )
        facet_sets[name] = facets
        face_node_sets[name] = want
    return facet_sets, face_node_sets


class _Matrices(NamedTuple):
    """The assembled model, in skfem's degree-of-freedom order."""

    capacity: Any
    """M = rho c int N N^T dV (scipy CSR)."""
    conduction: Any
    """K_cond = k int grad N . grad N^T dV."""
    convection: dict[str, Any]
    """H_s = int_s N N^T dA per face set."""
    face_loads: dict[str, NDArray[np.float64]]
    """G_s = int_s N dA per face set."""
    volume_m3: float


def _assemble(
    mesh: _Mesh, facet_sets: Mapping[str, NDArray[np.int64]], material: Material, intorder: int
) -> _Matrices:
    """Every matrix and vector of the model, from tiny named forms."""
    import skfem
    from skfem import BilinearForm, LinearForm, asm
    from skfem.helpers import dot, grad

    def capacity(u: Any, v: Any, w: Any) -> Any:
        return u * v

    def conduction(u: Any, v: Any, w: Any) -> Any:
        return dot(grad(u), grad(v))

    def unit_load(v: Any, w: Any) -> Any:
        return v

    uv, grad_uv, v_only = (
        BilinearForm(capacity),
        BilinearForm(conduction),
        LinearForm(unit_load),
    )

    k = material.conductivity_w_mk
    rho_c = material.density_kg_m3 * material.specific_heat_j_kgk
    convection: dict[str, Any] = {}
    face_loads: dict[str, NDArray[np.float64]] = {}
    for name, facets in facet_sets.items():
        fb = skfem.FacetBasis(mesh.mesh, mesh.element, facets=facets, intorder=intorder)
        convection[name] = asm(uv, fb).tocsr()
        face_loads[name] = asm(v_only, fb)
    return _Matrices(
        capacity=(rho_c * asm(uv, mesh.basis)).tocsr(),
        conduction=(k * asm(grad_uv, mesh.basis)).tocsr(),
        convection=convection,
        face_loads=face_loads,
        volume_m3=float(asm(v_only, mesh.basis).sum()),
    )


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
        nodes, elements = _checked_mesh_arrays(nodes, elements, face_sets)
        n_nodes = nodes.shape[0]
        self.material = material
        self.solver = solver
        self.n_nodes = n_nodes
        self.nodes_per_element = elements.shape[1]
        quadratic = self.nodes_per_element == 20
        if intorder is None:
            intorder = 6 if quadratic else 4
        self.intorder = intorder

        mesh = _skfem_mesh(nodes, elements, quadratic, intorder)
        dofs = _dof_map(nodes, elements, mesh, quadratic)
        self._dof_to_node = dofs.dof_to_node
        self._node_to_dof = dofs.node_to_dof
        self.midside_offset_max_m = dofs.midside_offset_max_m
        facet_sets, self.face_node_sets = _facet_sets(face_sets, mesh, dofs, n_nodes, quadratic)
        self.face_set_names = tuple(facet_sets)

        matrices = _assemble(mesh, facet_sets, material, intorder)
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
        # our core does
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
