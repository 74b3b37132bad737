"""The scikit-fem model of :mod:`fleetbrake.bench.peers.skfem_block` built from the contract's
mesh arrays, step by step: the arrays checked (:func:`checked_mesh_arrays`), the skfem mesh from
the corner nodes (:func:`skfem_mesh`, VTK's corner order turned into skfem's), the degrees of
freedom matched to the caller's nodes (:func:`dof_map`), the face sets matched to boundary
facets (:func:`facet_sets`), and every matrix assembled (:func:`assemble`). scikit-fem is
imported inside the functions (an optional dev dependency)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fleetbrake.fleet.block import Material

__all__ = [
    "VTK_HEX8_PARAM",
    "VTK_HEX20_EDGES",
    "VTK_TO_SKFEM_HEX8",
    "DofMap",
    "SkfemMatrices",
    "SkfemMesh",
    "assemble",
    "checked_mesh_arrays",
    "dof_map",
    "facet_sets",
    "skfem_mesh",
]


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


def checked_mesh_arrays(
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


class SkfemMesh(NamedTuple):
    """The scikit-fem mesh built from the corner nodes, its element and volume basis."""

    mesh: Any
    element: Any
    basis: Any
    node_to_vertex: NDArray[np.int64]
    """Each of the caller's nodes' vertex in the skfem mesh (-1: a midside node)."""


def skfem_mesh(
    nodes: NDArray[np.float64], elements: NDArray[np.int64], quadratic: bool, intorder: int
) -> SkfemMesh:
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
    return SkfemMesh(mesh, elem, basis, node_to_vertex)


class DofMap(NamedTuple):
    """The degrees of freedom and the caller's nodes, one to one."""

    dof_to_node: NDArray[np.int64]
    node_to_dof: NDArray[np.int64]
    midside_offset_max_m: float
    """Largest distance of a midside node from skfem's chord midpoint of its edge."""


def dof_map(
    nodes: NDArray[np.float64], elements: NDArray[np.int64], mesh: SkfemMesh, quadratic: bool
) -> DofMap:
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
    return DofMap(dof_to_node, node_to_dof, offset_max_m)


def facet_sets(
    face_sets: Mapping[str, ArrayLike], mesh: SkfemMesh, dofs: DofMap, n_nodes: int, quadratic: bool
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


class SkfemMatrices(NamedTuple):
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


def assemble(
    mesh: SkfemMesh, facet_sets: Mapping[str, NDArray[np.int64]], material: Material, intorder: int
) -> SkfemMatrices:
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
    return SkfemMatrices(
        capacity=(rho_c * asm(uv, mesh.basis)).tocsr(),
        conduction=(k * asm(grad_uv, mesh.basis)).tocsr(),
        convection=convection,
        face_loads=face_loads,
        volume_m3=float(asm(v_only, mesh.basis).sum()),
    )
