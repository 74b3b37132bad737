//! Isoparametric hexahedra in VTK node order: 8-node trilinear and 20-node serendipity
//! (Ansys SOLID90's element). Reference cube [-1, 1]^3, natural coordinates (xi, eta, zeta).

/// Natural coordinates of the 20 nodes of VTK_QUADRATIC_HEXAHEDRON; the first 8 are those of
/// VTK_HEXAHEDRON.
pub const NODE_NATURAL: [[f64; 3]; 20] = [
    [-1.0, -1.0, -1.0],
    [1.0, -1.0, -1.0],
    [1.0, 1.0, -1.0],
    [-1.0, 1.0, -1.0],
    [-1.0, -1.0, 1.0],
    [1.0, -1.0, 1.0],
    [1.0, 1.0, 1.0],
    [-1.0, 1.0, 1.0],
    [0.0, -1.0, -1.0],
    [1.0, 0.0, -1.0],
    [0.0, 1.0, -1.0],
    [-1.0, 0.0, -1.0],
    [0.0, -1.0, 1.0],
    [1.0, 0.0, 1.0],
    [0.0, 1.0, 1.0],
    [-1.0, 0.0, 1.0],
    [-1.0, -1.0, 0.0],
    [1.0, -1.0, 0.0],
    [1.0, 1.0, 0.0],
    [-1.0, 1.0, 0.0],
];

/// The six faces of a hexahedron as (axis, side) with their corner nodes, counter-clockwise
/// seen from outside (outward normal), in VTK order.
pub const FACE_CORNERS: [(usize, f64, [usize; 4]); 6] = [
    (0, -1.0, [0, 4, 7, 3]),
    (0, 1.0, [1, 2, 6, 5]),
    (1, -1.0, [0, 1, 5, 4]),
    (1, 1.0, [3, 7, 6, 2]),
    (2, -1.0, [0, 3, 2, 1]),
    (2, 1.0, [4, 5, 6, 7]),
];

/// The 12 edges of a hexahedron: corner pair and the VTK index of the mid-edge node.
pub const EDGES: [(usize, usize, usize); 12] = [
    (0, 1, 8),
    (1, 2, 9),
    (2, 3, 10),
    (3, 0, 11),
    (4, 5, 12),
    (5, 6, 13),
    (6, 7, 14),
    (7, 4, 15),
    (0, 4, 16),
    (1, 5, 17),
    (2, 6, 18),
    (3, 7, 19),
];

/// The element types of the core.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ElementKind {
    /// 8-node trilinear hexahedron.
    Hex8,
    /// 20-node serendipity (quadratic) hexahedron.
    Hex20,
}

impl ElementKind {
    /// Nodes per element.
    pub fn n_nodes(self) -> usize {
        match self {
            ElementKind::Hex8 => 8,
            ElementKind::Hex20 => 20,
        }
    }

    /// Nodes per face (4 or 8).
    pub fn n_face_nodes(self) -> usize {
        match self {
            ElementKind::Hex8 => 4,
            ElementKind::Hex20 => 8,
        }
    }

    /// Gauss points per direction for volume integrals: exact for the mass matrix of an affine
    /// element, and one more for the curved (non-affine) geometry of the block.
    pub fn volume_order(self) -> usize {
        match self {
            ElementKind::Hex8 => 3,
            ElementKind::Hex20 => 4,
        }
    }

    /// Polynomial degree along an edge.
    pub fn degree(self) -> usize {
        match self {
            ElementKind::Hex8 => 1,
            ElementKind::Hex20 => 2,
        }
    }

    /// Parse a user-facing name.
    pub fn from_name(name: &str) -> Option<Self> {
        match name.to_ascii_lowercase().as_str() {
            "hex8" | "hex_8" | "8" => Some(ElementKind::Hex8),
            "hex20" | "hex_20" | "20" => Some(ElementKind::Hex20),
            _ => None,
        }
    }

    /// User-facing name.
    pub fn name(self) -> &'static str {
        match self {
            ElementKind::Hex8 => "hex8",
            ElementKind::Hex20 => "hex20",
        }
    }

    /// Local nodes of face `f` in VTK (quadratic) quad order: corners, then mid-edges.
    pub fn face_nodes(self, f: usize) -> Vec<usize> {
        let corners = FACE_CORNERS[f].2;
        let mut nodes = corners.to_vec();
        if self == ElementKind::Hex20 {
            for i in 0..4 {
                let (a, b) = (corners[i], corners[(i + 1) % 4]);
                let mid = EDGES
                    .iter()
                    .find(|(p, q, _)| (*p == a && *q == b) || (*p == b && *q == a))
                    .map(|e| e.2);
                // every consecutive pair of face corners is an edge of the cube
                nodes.push(mid.unwrap_or(usize::MAX));
            }
        }
        nodes
    }

    /// Shape function values at `xi` into `n` (length n_nodes).
    pub fn shape(self, xi: [f64; 3], n: &mut [f64]) {
        match self {
            ElementKind::Hex8 => {
                for (a, p) in NODE_NATURAL[..8].iter().enumerate() {
                    n[a] =
                        0.125 * (1.0 + p[0] * xi[0]) * (1.0 + p[1] * xi[1]) * (1.0 + p[2] * xi[2]);
                }
            }
            ElementKind::Hex20 => {
                for (a, p) in NODE_NATURAL.iter().enumerate() {
                    n[a] = hex20_shape(p, xi);
                }
            }
        }
    }

    /// Shape function gradients with respect to natural coordinates at `xi` into `dn`.
    pub fn grad(self, xi: [f64; 3], dn: &mut [[f64; 3]]) {
        match self {
            ElementKind::Hex8 => {
                for (a, p) in NODE_NATURAL[..8].iter().enumerate() {
                    let f = [1.0 + p[0] * xi[0], 1.0 + p[1] * xi[1], 1.0 + p[2] * xi[2]];
                    dn[a] = [
                        0.125 * p[0] * f[1] * f[2],
                        0.125 * f[0] * p[1] * f[2],
                        0.125 * f[0] * f[1] * p[2],
                    ];
                }
            }
            ElementKind::Hex20 => {
                for (a, p) in NODE_NATURAL.iter().enumerate() {
                    dn[a] = hex20_grad(p, xi);
                }
            }
        }
    }
}

fn hex20_shape(p: &[f64; 3], x: [f64; 3]) -> f64 {
    let zero_axis = p.iter().position(|c| *c == 0.0);
    match zero_axis {
        None => {
            0.125
                * (1.0 + p[0] * x[0])
                * (1.0 + p[1] * x[1])
                * (1.0 + p[2] * x[2])
                * (p[0] * x[0] + p[1] * x[1] + p[2] * x[2] - 2.0)
        }
        Some(m) => {
            let (i, j) = other_axes(m);
            0.25 * (1.0 - x[m] * x[m]) * (1.0 + p[i] * x[i]) * (1.0 + p[j] * x[j])
        }
    }
}

fn hex20_grad(p: &[f64; 3], x: [f64; 3]) -> [f64; 3] {
    let zero_axis = p.iter().position(|c| *c == 0.0);
    match zero_axis {
        None => {
            let f = [1.0 + p[0] * x[0], 1.0 + p[1] * x[1], 1.0 + p[2] * x[2]];
            let s = p[0] * x[0] + p[1] * x[1] + p[2] * x[2] - 2.0;
            let mut g = [0.0; 3];
            for d in 0..3 {
                let (i, j) = other_axes(d);
                g[d] = 0.125 * f[i] * f[j] * p[d] * (s + f[d]);
            }
            g
        }
        Some(m) => {
            let (i, j) = other_axes(m);
            let bubble = 1.0 - x[m] * x[m];
            let fi = 1.0 + p[i] * x[i];
            let fj = 1.0 + p[j] * x[j];
            let mut g = [0.0; 3];
            g[m] = 0.25 * (-2.0 * x[m]) * fi * fj;
            g[i] = 0.25 * bubble * p[i] * fj;
            g[j] = 0.25 * bubble * fi * p[j];
            g
        }
    }
}

fn other_axes(m: usize) -> (usize, usize) {
    match m {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    }
}

/// Shape functions and their reference gradients at a set of points (a quadrature rule's,
/// with its weights): the same for every element of a kind, so evaluated once per mesh.
pub struct ReferenceTable {
    pub nn: usize,
    pub points: Vec<ReferencePoint>,
}

pub struct ReferencePoint {
    pub xi: [f64; 3],
    pub weight: f64,
    pub n: Vec<f64>,
    pub dn: Vec<[f64; 3]>,
}

impl ReferenceTable {
    pub fn new(kind: ElementKind, rule: &[([f64; 3], f64)]) -> Self {
        let nn = kind.n_nodes();
        let points = rule
            .iter()
            .map(|&(xi, weight)| {
                let mut n = vec![0.0; nn];
                let mut dn = vec![[0.0; 3]; nn];
                kind.shape(xi, &mut n);
                kind.grad(xi, &mut dn);
                ReferencePoint { xi, weight, n, dn }
            })
            .collect();
        ReferenceTable { nn, points }
    }
}

/// Jacobian dx/dxi (rows: x, y, z; columns: xi, eta, zeta) from nodal coordinates and gradients.
pub fn jacobian(coords: &[[f64; 3]], dn: &[[f64; 3]]) -> [[f64; 3]; 3] {
    let mut j = [[0.0; 3]; 3];
    for (x, g) in coords.iter().zip(dn) {
        for r in 0..3 {
            for c in 0..3 {
                j[r][c] += x[r] * g[c];
            }
        }
    }
    j
}

/// Determinant of a 3x3 matrix.
pub fn det3(m: &[[f64; 3]; 3]) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// Inverse of a 3x3 matrix with its determinant; `None` when singular.
pub fn inv3(m: &[[f64; 3]; 3]) -> Option<([[f64; 3]; 3], f64)> {
    let d = det3(m);
    if d == 0.0 || !d.is_finite() {
        return None;
    }
    let inv = [
        [
            (m[1][1] * m[2][2] - m[1][2] * m[2][1]) / d,
            (m[0][2] * m[2][1] - m[0][1] * m[2][2]) / d,
            (m[0][1] * m[1][2] - m[0][2] * m[1][1]) / d,
        ],
        [
            (m[1][2] * m[2][0] - m[1][0] * m[2][2]) / d,
            (m[0][0] * m[2][2] - m[0][2] * m[2][0]) / d,
            (m[0][2] * m[1][0] - m[0][0] * m[1][2]) / d,
        ],
        [
            (m[1][0] * m[2][1] - m[1][1] * m[2][0]) / d,
            (m[0][1] * m[2][0] - m[0][0] * m[2][1]) / d,
            (m[0][0] * m[1][1] - m[0][1] * m[1][0]) / d,
        ],
    ];
    Some((inv, d))
}

/// Cross product.
pub fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn kinds() -> [ElementKind; 2] {
        [ElementKind::Hex8, ElementKind::Hex20]
    }

    #[test]
    fn kronecker_property_at_nodes() {
        for kind in kinds() {
            let nn = kind.n_nodes();
            let mut n = vec![0.0; nn];
            for (a, node) in NODE_NATURAL.iter().enumerate().take(nn) {
                kind.shape(*node, &mut n);
                for (b, v) in n.iter().enumerate() {
                    let expected = if a == b { 1.0 } else { 0.0 };
                    assert!(
                        (v - expected).abs() < 1e-14,
                        "{kind:?} N_{b}(node {a}) = {v}"
                    );
                }
            }
        }
    }

    #[test]
    fn face_nodes_lie_on_their_face() {
        for kind in kinds() {
            for (f, (axis, side, _)) in FACE_CORNERS.iter().enumerate() {
                let nodes = kind.face_nodes(f);
                assert_eq!(nodes.len(), kind.n_face_nodes());
                for a in nodes {
                    assert_eq!(NODE_NATURAL[a][*axis], *side, "{kind:?} face {f} node {a}");
                }
            }
        }
    }

    proptest! {
        #[test]
        fn partition_of_unity_and_gradients_match_finite_differences(
            x in -1.0f64..1.0, y in -1.0f64..1.0, z in -1.0f64..1.0
        ) {
            for kind in kinds() {
                let nn = kind.n_nodes();
                let mut n = vec![0.0; nn];
                let mut dn = vec![[0.0; 3]; nn];
                kind.shape([x, y, z], &mut n);
                kind.grad([x, y, z], &mut dn);
                let s: f64 = n.iter().sum();
                prop_assert!((s - 1.0).abs() < 1e-13);
                let h = 1e-6;
                for d in 0..3 {
                    let mut xp = [x, y, z];
                    let mut xm = [x, y, z];
                    xp[d] += h;
                    xm[d] -= h;
                    let mut np = vec![0.0; nn];
                    let mut nm = vec![0.0; nn];
                    kind.shape(xp, &mut np);
                    kind.shape(xm, &mut nm);
                    for a in 0..nn {
                        let fd = (np[a] - nm[a]) / (2.0 * h);
                        prop_assert!((fd - dn[a][d]).abs() < 1e-7, "{:?} node {} dir {}", kind, a, d);
                    }
                }
            }
        }

        #[test]
        fn interpolation_reproduces_complete_polynomials(
            x in -1.0f64..1.0, y in -1.0f64..1.0, z in -1.0f64..1.0
        ) {
            // Hex8 reproduces trilinear fields, Hex20 every complete quadratic.
            let lin = |p: [f64; 3]| 1.0 + 2.0 * p[0] - 3.0 * p[1] + 0.5 * p[2] + p[0] * p[1] * p[2];
            let quad = |p: [f64; 3]| {
                1.0 + p[0] - p[1] + 0.3 * p[2] + p[0] * p[0] - 2.0 * p[1] * p[2] + 0.7 * p[2] * p[2]
                    + 0.4 * p[0] * p[1]
            };
            let mut n8 = vec![0.0; 8];
            ElementKind::Hex8.shape([x, y, z], &mut n8);
            let v: f64 = (0..8).map(|a| n8[a] * lin(NODE_NATURAL[a])).sum();
            prop_assert!((v - lin([x, y, z])).abs() < 1e-12);
            let mut n20 = vec![0.0; 20];
            ElementKind::Hex20.shape([x, y, z], &mut n20);
            let v: f64 = (0..20).map(|a| n20[a] * quad(NODE_NATURAL[a])).sum();
            prop_assert!((v - quad([x, y, z])).abs() < 1e-12);
        }
    }
}
