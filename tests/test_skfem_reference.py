"""The scikit-fem reference (``fleetbrake.bench.peers.skfem_block``) against exact results.

Everything here is independent of the module under test: the VTK node tables, the box mesh,
the trilinear maps, the quadrature weights and the analytical solution are written out
below from their definitions, not imported.
"""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from fleetbrake.fleet.block import BLOCK_MATERIAL, Material

pytest.importorskip("skfem")
pytest.importorskip("scipy")

from fleetbrake.bench.peers.skfem_block import SkfemBlockModel

K, RHO, C = 48.0, 7100.0, 520.0
RHO_C = RHO * C
ALPHA = K / RHO_C

# --- VTK tables (from the VTK file-format documentation) -------------------------------------

HEX8 = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]]
)
"""Parametric corners of VTK_HEXAHEDRON."""
HEX20_EDGES = [
    (0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7),
]  # fmt: skip
"""Midside nodes 8..19 of VTK_QUADRATIC_HEXAHEDRON: the corners they sit between."""
HEX_FACES = [(0, 4, 7, 3), (1, 2, 6, 5), (0, 1, 5, 4), (3, 7, 6, 2), (0, 3, 2, 1), (4, 5, 6, 7)]
"""Faces of VTK_HEXAHEDRON, counter-clockwise seen from outside: x-, x+, y-, y+, z-, z+."""
SIDES = ["xmin", "xmax", "ymin", "ymax", "zmin", "zmax"]


def _quad_face(face: tuple[int, ...], quadratic: bool) -> list[int]:
    """Local nodes of a hexahedron face in VTK quad / quadratic-quad order."""
    if not quadratic:
        return list(face)
    mid = {frozenset(e): 8 + i for i, e in enumerate(HEX20_EDGES)}
    return list(face) + [mid[frozenset((face[i], face[(i + 1) % 4]))] for i in range(4)]


def box_mesh(
    lengths: tuple[float, float, float], divisions: tuple[int, int, int], order: int
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Structured box [0, Lx] x [0, Ly] x [0, Lz]: nodes, VTK hex8/hex20 cells, one face set per side."""
    m = order  # lattice points per element edge
    div = np.array(divisions)
    g = m * div + 1
    ix, iy, iz = np.meshgrid(*(np.arange(n) for n in g), indexing="ij")
    odd = (ix % m != 0).astype(int) + (iy % m != 0) + (iz % m != 0)
    keep = odd <= 1  # serendipity: no face or body centres
    ids = np.full(tuple(g), -1, dtype=np.int64)
    ids[keep] = np.arange(keep.sum())
    lat = np.stack([ix[keep], iy[keep], iz[keep]], axis=1)
    nodes = lat * (np.array(lengths) / (m * div))
    offsets = [m * HEX8[i] for i in range(8)]
    if order == 2:
        offsets += [HEX8[a] + HEX8[b] for a, b in HEX20_EDGES]
    offsets = np.array(offsets)
    cells = np.stack(np.meshgrid(*(np.arange(n) for n in div), indexing="ij"), axis=-1).reshape(
        -1, 3
    )
    base = m * cells
    corner = base[:, None, :] + offsets[None, :, :]
    elements = ids[corner[..., 0], corner[..., 1], corner[..., 2]]
    assert (elements >= 0).all()
    faces = {}
    for f, side in enumerate(SIDES):
        axis, high = divmod(f, 2)
        on = cells[:, axis] == (div[axis] - 1 if high else 0)
        faces[side] = elements[on][:, _quad_face(HEX_FACES[f], order == 2)]
    return nodes, elements, faces


def trilinear(corners: np.ndarray, rst: np.ndarray) -> np.ndarray:
    """x(r, s, t) of a VTK-ordered trilinear hexahedron; rst (n, 3) in [0, 1]^3."""
    w = np.prod(np.where(HEX8[None, :, :] == 1, rst[:, None, :], 1 - rst[:, None, :]), axis=2)
    return w @ corners


def trilinear_jacobian(corners: np.ndarray, rst: np.ndarray) -> np.ndarray:
    """(n, 3, 3) dx/d(r, s, t) of a VTK-ordered trilinear hexahedron."""
    jac = np.zeros((rst.shape[0], 3, 3))
    for d in range(3):
        f = np.where(HEX8[None, :, :] == 1, rst[:, None, :], 1 - rst[:, None, :])
        f[:, :, d] = np.where(HEX8[None, :, d] == 1, 1.0, -1.0)
        jac[:, :, d] = np.prod(f, axis=2) @ corners
    return jac


def gauss_cube(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    x, w = 0.5 * (x + 1), 0.5 * w
    P = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1).reshape(-1, 3)
    W = np.einsum("i,j,k->ijk", w, w, w).ravel()
    return P, W


def hex20_from_corners(corners: np.ndarray) -> np.ndarray:
    """Corners plus straight-edge midpoints, VTK_QUADRATIC_HEXAHEDRON order."""
    return np.vstack([corners] + [(corners[a] + corners[b]) / 2 for a, b in HEX20_EDGES])


def material() -> Material:
    return Material(conductivity_w_mk=K, density_kg_m3=RHO, specific_heat_j_kgk=C)


def test_box_mesh_helper_is_sound():
    """The helper itself: positive Jacobians, outward face orientation, node counts."""
    for order, per_node in ((1, 8), (2, 20)):
        nodes, elements, faces = box_mesh((0.3, 0.2, 0.1), (3, 2, 2), order)
        assert elements.shape == (12, per_node)
        assert np.unique(elements).size == nodes.shape[0]
        centre = np.array([0.15, 0.1, 0.05])
        for e in elements:
            j = trilinear_jacobian(nodes[e[:8]], np.full((1, 3), 0.5))
            assert np.linalg.det(j[0]) > 0
        for side, quads in faces.items():
            p = nodes[quads[:, :4]]
            normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 1])
            outward = p.mean(axis=1) - centre
            assert (np.einsum("ij,ij->i", normal, outward) > 0).all(), side
            if order == 2:  # midside nodes between the corners they belong to
                mids = nodes[quads[:, 4:]]
                ends = (p + np.roll(p, -1, axis=1)) / 2
                assert np.allclose(mids, ends)


# --- one distorted element -------------------------------------------------------------------

DISTORTED = 0.02 * (
    HEX8
    + np.array(
        [
            [0.10, -0.05, 0.08],
            [0.30, 0.12, -0.10],
            [-0.15, 0.20, 0.05],
            [0.05, -0.10, -0.12],
            [-0.08, 0.15, 0.20],
            [0.12, -0.07, 0.30],
            [0.25, 0.18, -0.05],
            [-0.20, 0.06, 0.11],
        ]
    )
)
"""A hexahedron with non-planar faces (metres); Jacobian positive everywhere (checked)."""


@pytest.mark.parametrize("order", [1, 2])
def test_distorted_single_element(order):
    corners = DISTORTED
    nodes = corners if order == 1 else hex20_from_corners(corners)
    element = np.arange(nodes.shape[0])[None, :]
    faces = {side: np.array([_quad_face(HEX_FACES[f], order == 2)]) for f, side in enumerate(SIDES)}
    faces["friction"] = faces["zmin"]
    model = SkfemBlockModel(nodes, element, faces, material())

    # exact integrals on the trilinear geometry, by Gauss quadrature written here
    P, W = gauss_cube(4)
    jac = trilinear_jacobian(corners, P)
    det = np.linalg.det(jac)
    assert det.min() > 0.2 * det.max()  # distorted but sound
    volume = W @ det
    assert not np.isclose(volume, 0.02**3, rtol=1e-3)  # really distorted
    assert model.volume_m3 == pytest.approx(volume, rel=1e-13)

    # a linear field: interpolation exact, conduction energy exact, capacity exact
    a, b = np.array([310.0, -170.0, 240.0]), 21.5
    u = nodes @ a + b
    rng = np.random.default_rng(7)
    rst = rng.uniform(0.02, 0.98, size=(25, 3))
    pts = trilinear(corners, rst)
    got = model.probe_matrix(pts) @ u
    np.testing.assert_allclose(got, pts @ a + b, rtol=1e-12, atol=0)
    Kc, M = model.conduction_matrix, model.capacity_matrix
    assert u @ (Kc @ u) == pytest.approx(K * (a @ a) * volume, rel=1e-12)
    xq = trilinear(corners, P)
    assert u @ (M @ u) == pytest.approx(RHO_C * (W @ ((xq @ a + b) ** 2 * det)), rel=1e-12)
    assert (Kc @ np.ones(nodes.shape[0])) == pytest.approx(0, abs=1e-9 * K * 0.02)

    # faces: area and the integral of the linear field over each (non-planar) face
    x2, w2 = np.polynomial.legendre.leggauss(16)
    x2, w2 = 0.5 * (x2 + 1), 0.5 * w2
    for f, side in enumerate(SIDES):
        q = corners[list(HEX_FACES[f])]  # bilinear patch, VTK quad order
        area = integral = 0.0
        for s, ws in zip(x2, w2, strict=True):
            for t, wt in zip(x2, w2, strict=True):
                x = (
                    (1 - s) * (1 - t) * q[0]
                    + s * (1 - t) * q[1]
                    + s * t * q[2]
                    + (1 - s) * t * q[3]
                )
                dxs = (1 - t) * (q[1] - q[0]) + t * (q[2] - q[3])
                dxt = (1 - s) * (q[3] - q[0]) + s * (q[2] - q[1])
                dA = np.linalg.norm(np.cross(dxs, dxt)) * ws * wt
                area += dA
                integral += (x @ a + b) * dA
        # |n| of a non-planar face is not a polynomial: skfem's 3-point rule is near, not exact
        assert model.face_area_m2[side] == pytest.approx(area, rel=1e-5)
        assert model.face_load(side) @ u == pytest.approx(integral, rel=1e-5)
        assert model.face_load(side).sum() == pytest.approx(model.face_area_m2[side], rel=1e-14)


@pytest.mark.parametrize("order", [1, 2])
def test_wrong_node_orders_are_rejected(order):
    nodes = DISTORTED if order == 1 else hex20_from_corners(DISTORTED)
    element = np.arange(nodes.shape[0])[None, :]
    faces = {"friction": np.array([_quad_face(HEX_FACES[4], order == 2)])}
    SkfemBlockModel(nodes, element, faces, material())  # the right order is accepted

    mirrored = element.copy()
    mirrored[0, [0, 1, 2, 3, 4, 5, 6, 7]] = element[0, [4, 5, 6, 7, 0, 1, 2, 3]]
    if order == 2:
        mirrored[0, 8:16] = element[0, [12, 13, 14, 15, 8, 9, 10, 11]]
    with pytest.raises(ValueError, match="non-positive Jacobian"):
        SkfemBlockModel(nodes, mirrored, faces, material())

    if order == 2:
        swapped = element.copy()
        swapped[0, [8, 18]] = element[0, [18, 8]]
        with pytest.raises(ValueError, match="midside node"):
            SkfemBlockModel(nodes, swapped, faces, material())
        bad_face = faces["friction"].copy()
        bad_face[0, [4, 5]] = bad_face[0, [5, 4]]
        SkfemBlockModel(nodes, element, {"friction": bad_face}, material())  # same node set
        bad_face[0, 4] = 16  # a midside node not on that face
        with pytest.raises(ValueError, match="not those of the matched"):
            SkfemBlockModel(nodes, element, {"friction": bad_face}, material())


def test_faces_not_on_the_boundary_are_rejected():
    nodes, elements, faces = box_mesh((0.1, 0.01, 0.01), (4, 1, 1), 1)
    interior = elements[1][[0, 4, 7, 3]]  # x- face of the 2nd element = x+ face of the 1st
    with pytest.raises(ValueError, match="not boundary faces"):
        SkfemBlockModel(nodes, elements, {"friction": faces["xmin"], "x": [interior]}, material())
    with pytest.raises(ValueError, match="'friction'"):
        SkfemBlockModel(nodes, elements, {"air": faces["xmax"]}, material())


def test_missing_scikit_fem_says_how_to_install(monkeypatch):
    nodes, elements, faces = box_mesh((0.1, 0.01, 0.01), (2, 1, 1), 1)
    monkeypatch.setitem(sys.modules, "skfem", None)
    with pytest.raises(ImportError, match="scikit-fem"):
        SkfemBlockModel(nodes, elements, {"friction": faces["xmin"]}, material())


# --- the bar against the analytical solution -------------------------------------------------


def slab_flux_insulated(x: float, t: np.ndarray, q: float, L: float, n_terms: int = 400):
    """Temperature rise in a slab 0 <= x <= L, flux q into x = 0, x = L insulated, from rest.

    T - T0 = (q L / k) [alpha t / L^2 + 1/3 - x/L + x^2 / (2 L^2)
                        - (2 / pi^2) sum_n exp(-n^2 pi^2 alpha t / L^2) cos(n pi x / L) / n^2]
    (Carslaw & Jaeger, Conduction of Heat in Solids, sec. 3.3). The bracket vanishes at t = 0
    because sum_n cos(n u) / n^2 = pi^2/6 - pi u/2 + u^2/4 on [0, 2 pi]; at x = L,
    cos(n pi) = (-1)^n.
    """
    n = np.arange(1, n_terms + 1)[:, None]
    tau = ALPHA * np.asarray(t, dtype=np.float64)[None, :] / L**2
    series = (np.exp(-(n**2) * math.pi**2 * tau) * np.cos(n * math.pi * x / L) / n**2).sum(axis=0)
    poly = tau[0] + 1 / 3 - x / L + x**2 / (2 * L**2)
    return q * L / K * (poly - 2 / math.pi**2 * series)


def test_series_solution_is_right():
    """The reference formula itself: zero at t = 0, flux and insulation at the ends."""
    L, q = 0.1, 1e5
    # at t = 0 the series converges slowly (1/n^2): many terms
    zero = np.array([0.0])
    assert slab_flux_insulated(L, zero, q, L, 20000)[0] == pytest.approx(0, abs=1e-6)
    assert slab_flux_insulated(0.0, zero, q, L, 20000)[0] == pytest.approx(0, abs=5e-3)
    t = np.array([200.0])
    eps = 1e-6
    d0 = (slab_flux_insulated(eps, t, q, L) - slab_flux_insulated(0, t, q, L)) / eps
    dL = (slab_flux_insulated(L, t, q, L) - slab_flux_insulated(L - eps, t, q, L)) / eps
    assert -K * d0[0] == pytest.approx(q, rel=1e-3)
    assert dL[0] == pytest.approx(0, abs=1e-3 * q / K)
    # energy: rho c L mean(T - T0) = q t
    xs = np.linspace(0, L, 2001)
    rise = np.array([slab_flux_insulated(x, t, q, L)[0] for x in xs])
    mean = (rise[:-1] + rise[1:]).sum() / 2 / (xs.size - 1)
    assert RHO_C * L * mean == pytest.approx(q * t[0], rel=1e-5)


@pytest.mark.parametrize(
    ("order", "divisions"), [(1, (40, 1, 1)), (2, (20, 1, 1))], ids=["hex8", "hex20"]
)
def test_bar_far_end_matches_the_series_solution(order, divisions):
    L, q, T0, dt, n_steps = 0.1, 1e5, 23.0, 1.0, 600
    nodes, elements, faces = box_mesh((L, 0.01, 0.01), divisions, order)
    air = np.vstack([faces[s] for s in SIDES[1:]])
    model = SkfemBlockModel(nodes, elements, {"friction": faces["xmin"], "air": air}, material())
    probes = np.array([[L, 0.005, 0.005], [L / 2, 0.003, 0.007], [L, 0.0, 0.01]])
    res = model.simulate(
        dt_s=dt,
        flux_w_m2=np.full(n_steps, q),
        ambient_c=10.0,
        initial_c=T0,
        h_w_m2k={"air": 0.0},
        probes_m=probes,
    )
    exact_far = slab_flux_insulated(L, res.time_s, q, L)
    exact_mid = slab_flux_insulated(L / 2, res.time_s, q, L)
    final = exact_far[-1]
    assert final > 10.0  # a real rise, well resolved
    for j, exact in ((0, exact_far), (2, exact_far), (1, exact_mid)):
        err = res.probe_c[:, j] - T0 - exact
        assert np.abs(err).max() <= 0.005 * final
        late = exact >= 0.05 * final
        assert late.sum() > n_steps / 2
        assert (np.abs(err[late]) <= 0.005 * exact[late]).all()
    # the friction face (x = 0): mean and max over a 1D field are the same
    exact_face = slab_flux_insulated(0.0, res.time_s, q, L)
    np.testing.assert_allclose(res.face_mean_c[60:] - T0, exact_face[60:], rtol=0.005)
    np.testing.assert_allclose(res.face_max_c, res.face_mean_c, rtol=1e-9)
    assert res.time_s.shape == (n_steps + 1,) and res.probe_c.shape == (n_steps + 1, 3)
    assert res.n_factorisations == 1  # the damped half steps share Crank-Nicolson's factor


# --- the time scheme, time-discretely --------------------------------------------------------


def _energy_inputs(n_steps: int):
    rng = np.random.default_rng(3)
    flux = np.where(np.arange(n_steps) < n_steps // 2, 2e5, 0.0) * rng.uniform(0.5, 1.0, n_steps)
    ambient = 10.0 + 5.0 * np.sin(np.arange(n_steps) / 7.0)
    h_air = np.where(np.arange(n_steps) % 10 < 5, 400.0, 250.0)  # 2 distinct matrices
    return flux, ambient, {"air": h_air, "xmax": 900.0}


def _box_integration_weights(order: int):
    """Exact integration weights of a rectangular element's nodes: volume and face."""
    if order == 1:
        return np.full(8, 1 / 8), np.full(4, 1 / 4)
    return (
        np.r_[np.full(8, -1 / 8), np.full(12, 1 / 6)],
        np.r_[np.full(4, -1 / 12), np.full(4, 1 / 3)],
    )


@pytest.mark.parametrize("scheme", ["crank-nicolson", "backward-euler"])
@pytest.mark.parametrize("order", [1, 2], ids=["hex8", "hex20"])
def test_energy_balance_is_exact_time_discretely(order, scheme):
    """rho c int (T_N - T0) = sum_n dt [q_n A_f - sum_s h_s,n int_s (T_theta,n - T_amb,n)]."""
    L, dt, n_steps, T0 = 0.1, 2.0, 60, 37.0
    nodes, elements, faces = box_mesh((L, 0.012, 0.01), (8, 2, 2), order)
    sets = {
        "friction": faces["xmin"],
        "air": np.vstack([faces[s] for s in SIDES[2:]]),
        "xmax": faces["xmax"],
    }
    model = SkfemBlockModel(nodes, elements, sets, material())
    flux, ambient, h = _energy_inputs(n_steps)
    res = model.simulate(
        dt, flux, ambient, T0, h, np.array([[L, 0.006, 0.005]]), scheme, 0, field_every=1
    )
    theta = 0.5 if scheme == "crank-nicolson" else 1.0
    wv, wf = _box_integration_weights(order)
    vol = np.prod(np.ptp(nodes[elements[0]], axis=0))

    def face_integral(name, T):
        quads = sets[name]
        p = nodes[quads[:, :4]]
        area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 3] - p[:, 0]), axis=1)
        return area @ (T[:, quads] @ wf).T

    area = {s: face_integral(s, np.ones((1, nodes.shape[0])))[0] for s in sets}
    assert area["friction"] == pytest.approx(0.012 * 0.01)
    stored = RHO_C * vol * ((res.fields_c[:, elements] @ wv) - T0).sum(axis=1)
    T_theta = theta * res.fields_c[1:] + (1 - theta) * res.fields_c[:-1]
    inflow = dt * flux * area["friction"]
    outflow = np.zeros(n_steps)
    for s, hs in h.items():
        outflow += (
            dt * np.broadcast_to(hs, n_steps) * (face_integral(s, T_theta) - ambient * area[s])
        )
    ledger = np.r_[0.0, np.cumsum(inflow - outflow)]
    assert outflow.sum() > 0.2 * inflow.sum()  # convection matters in this run
    np.testing.assert_allclose(stored, ledger, rtol=0, atol=1e-9 * inflow.sum())
    assert res.n_factorisations == 2


@pytest.mark.parametrize("order", [1, 2], ids=["hex8", "hex20"])
def test_scheme_is_the_contracts_including_the_damped_start(order):
    """Step by step against the formula of thermal-api.md, written out with dense algebra."""
    nodes, elements, faces = box_mesh((0.05, 0.02, 0.01), (3, 2, 1), order)
    sets = {"friction": faces["ymin"], "air": np.vstack([faces[s] for s in SIDES if s != "ymin"])}
    model = SkfemBlockModel(nodes, elements, sets, material())
    n_steps, dt = 12, 3.0
    rng = np.random.default_rng(11)
    flux = rng.uniform(0, 3e5, n_steps)
    ambient = rng.uniform(0, 30, n_steps)
    h_air = rng.choice([5.0, 500.0], n_steps)
    T0 = 20.0 + rng.uniform(0, 50, nodes.shape[0])
    probes = np.array([[0.01, 0.015, 0.005]])
    M = model.capacity_matrix.toarray()
    Kc = model.conduction_matrix.toarray()
    H = model.convection_matrix("air").toarray()
    F, G = model.face_load("friction"), model.face_load("air")

    def reference(theta, damped, flux=flux, damped_at=()):
        T, out = T0.copy(), [T0.copy()]
        for n in range(n_steps):
            Kn = Kc + h_air[n] * H
            f = flux[n] * F + h_air[n] * ambient[n] * G
            is_damped = n < damped or any(k <= n < k + damped for k in damped_at)
            sub = [(dt / 2, 1.0)] * 2 if is_damped else [(dt, theta)]
            for d, th in sub:
                T = np.linalg.solve(M / d + th * Kn, (M / d - (1 - th) * Kn) @ T + f)
            out.append(T)
        return np.array(out)

    scale = np.abs(T0).max()
    for scheme, theta in (("crank-nicolson", 0.5), ("backward-euler", 1.0)):
        for damped in (0, 1, 3):
            res = model.simulate(
                dt,
                flux,
                ambient,
                T0,
                {"air": h_air},
                probes,
                scheme,
                damped,
                field_every=1,
                jump_fraction=0.0,
            )
            ref = reference(theta, damped)
            np.testing.assert_allclose(res.fields_c, ref, rtol=0, atol=1e-11 * scale)
            np.testing.assert_allclose(
                res.probe_c[:, 0], (model.probe_matrix(probes) @ ref.T)[0], atol=1e-11 * scale
            )
            mean = ref @ F / F.sum()
            np.testing.assert_allclose(res.face_mean_c, mean, atol=1e-11 * scale)
            fnodes = np.unique(sets["friction"])
            np.testing.assert_allclose(res.face_max_c, ref[:, fnodes].max(axis=1), rtol=1e-13)
    # the damping restarts after a jump of an input (Crank-Nicolson only): a step of flux at
    # step 5 on an otherwise smooth run (ambient and h held constant)
    steady_amb, steady_h = np.full(n_steps, 12.0), np.full(n_steps, 40.0)
    step_flux = np.where(np.arange(n_steps) < 5, 0.0, 2e5)
    ambient[:], h_air[:] = steady_amb, steady_h
    for damped in (1, 2):
        res = model.simulate(
            dt,
            step_flux,
            ambient,
            T0,
            {"air": h_air},
            probes,
            "crank-nicolson",
            damped,
            field_every=1,
        )
        ref = reference(0.5, damped, flux=step_flux, damped_at=(5,))
        np.testing.assert_allclose(res.fields_c, ref, rtol=0, atol=1e-11 * scale)
        plain = reference(0.5, damped, flux=step_flux)
        assert np.abs(plain - ref).max() > 1e-3 * scale  # the restart changes the answer
    # the damped start changes the answer (so the comparison above is not vacuous)
    a = model.simulate(dt, flux, ambient, T0, {"air": h_air}, probes, damped_steps=0)
    b = model.simulate(dt, flux, ambient, T0, {"air": h_air}, probes, damped_steps=1)
    assert np.abs(a.probe_c - b.probe_c).max() > 1e-3


def test_simulate_rejects_bad_inputs():
    nodes, elements, faces = box_mesh((0.1, 0.01, 0.01), (2, 1, 1), 1)
    model = SkfemBlockModel(nodes, elements, {"friction": faces["xmin"]}, BLOCK_MATERIAL)
    probes = np.array([[0.05, 0.005, 0.005]])
    with pytest.raises(KeyError, match="air"):
        model.simulate(1.0, [1.0], 10.0, 20.0, {"air": 10.0}, probes)
    with pytest.raises(ValueError, match="scheme"):
        model.simulate(1.0, [1.0], 10.0, 20.0, {}, probes, scheme="rk4")
    with pytest.raises(ValueError, match="ambient_c"):
        model.simulate(1.0, [1.0, 2.0], [10.0], 20.0, {}, probes)
    with pytest.raises(ValueError, match="outside the mesh"):
        model.simulate(1.0, [1.0], 10.0, 20.0, {}, np.array([[0.2, 0.005, 0.005]]))


def test_curved_midside_nodes_are_taken_on_the_chords():
    """Midside nodes on arcs: accepted, and the geometry is the chord polygon (quantified)."""
    R, t, H, span, n_arc = 0.46, 0.045, 0.08, math.radians(29.4), 8
    nodes, elements, faces = box_mesh((1.0, 1.0, 1.0), (n_arc, 2, 2), 2)
    theta = (nodes[:, 0] - 0.5) * span
    r = R + t * nodes[:, 1]
    curved = np.stack([r * np.sin(theta), r * np.cos(theta), H * (nodes[:, 2] - 0.5)], axis=1)
    model = SkfemBlockModel(curved, elements, {"friction": faces["ymin"]}, BLOCK_MATERIAL)
    d = span / n_arc
    chord_area = n_arc * 2 * R * math.sin(d / 2) * H
    arc_area = R * span * H
    assert model.friction_area_m2 == pytest.approx(chord_area, rel=1e-12)
    assert 1 - chord_area / arc_area == pytest.approx(d**2 / 24, rel=1e-2)
    # the largest offset: a midside node on the outer arc, one sagitta off its chord
    assert model.midside_offset_max_m == pytest.approx((R + t) * (1 - math.cos(d / 2)), rel=1e-9)
    chord_volume = n_arc * math.sin(d) / 2 * ((R + t) ** 2 - R**2) * H  # trapezoidal prisms
    assert model.volume_m3 == pytest.approx(chord_volume, rel=1e-12)
