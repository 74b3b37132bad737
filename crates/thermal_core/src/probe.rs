//! Point location and interpolation: the element that holds a point, its natural coordinates
//! by Newton's method on the isoparametric map, and the interpolation weights there.

use crate::element::{inv3, jacobian};
use crate::error::{Result, ThermalError};
use crate::mesh::Mesh;

/// Interpolation of the nodal field at a set of points.
#[derive(Debug, Clone, PartialEq)]
pub struct Probes {
    /// Global node indices, `n_nodes_per_element` per probe.
    pub nodes: Vec<usize>,
    /// Interpolation weights, aligned with `nodes`.
    pub weights: Vec<f64>,
    /// Element holding each probe.
    pub elements: Vec<usize>,
    per_probe: usize,
}

impl Probes {
    pub fn len(&self) -> usize {
        self.elements.len()
    }

    pub fn is_empty(&self) -> bool {
        self.elements.is_empty()
    }

    /// Field values at every probe into `out`.
    pub fn interpolate(&self, field: &[f64], out: &mut [f64]) {
        for (p, o) in out.iter_mut().enumerate() {
            let range = p * self.per_probe..(p + 1) * self.per_probe;
            *o = self.nodes[range.clone()]
                .iter()
                .zip(&self.weights[range])
                .map(|(&i, w)| w * field[i])
                .sum();
        }
    }
}

/// Natural coordinates of point `x` in element `e`, if Newton converges to a point inside.
pub fn locate_in_element(mesh: &Mesh, e: usize, x: [f64; 3], tol: f64) -> Option<[f64; 3]> {
    let kind = mesh.kind;
    let coords = mesh.element_coords(e);
    let nn = kind.n_nodes();
    let mut n = vec![0.0; nn];
    let mut dn = vec![[0.0; 3]; nn];
    let mut xi = [0.0f64; 3];
    for _ in 0..30 {
        kind.shape(xi, &mut n);
        let mut r = [0.0; 3];
        for (a, c) in coords.iter().enumerate() {
            for d in 0..3 {
                r[d] += n[a] * c[d];
            }
        }
        for d in 0..3 {
            r[d] = x[d] - r[d];
        }
        kind.grad(xi, &mut dn);
        let (inv, _) = inv3(&jacobian(&coords, &dn))?;
        let mut step = [0.0; 3];
        for i in 0..3 {
            step[i] = inv[i][0] * r[0] + inv[i][1] * r[1] + inv[i][2] * r[2];
        }
        for i in 0..3 {
            // keep the iterate near the reference cube so the map stays meaningful
            xi[i] = (xi[i] + step[i]).clamp(-2.0, 2.0);
        }
        if step.iter().map(|s| s.abs()).fold(0.0, f64::max) < 1e-13 {
            break;
        }
    }
    if xi.iter().all(|v| v.abs() <= 1.0 + tol) {
        Some(xi.map(|v| v.clamp(-1.0, 1.0)))
    } else {
        None
    }
}

/// Locate every point; an error names the first point no element holds.
pub fn build_probes(mesh: &Mesh, points: &[[f64; 3]]) -> Result<Probes> {
    let kind = mesh.kind;
    let nn = kind.n_nodes();
    let boxes: Vec<([f64; 3], [f64; 3])> = (0..mesh.n_elements())
        .map(|e| {
            let mut lo = [f64::INFINITY; 3];
            let mut hi = [f64::NEG_INFINITY; 3];
            for c in mesh.element_coords(e) {
                for d in 0..3 {
                    lo[d] = lo[d].min(c[d]);
                    hi[d] = hi[d].max(c[d]);
                }
            }
            (lo, hi)
        })
        .collect();
    let size = boxes
        .iter()
        .map(|(lo, hi)| hi[0] - lo[0])
        .fold(0.0, f64::max);
    let pad = 0.05 * size;
    let mut probes = Probes {
        nodes: Vec::with_capacity(points.len() * nn),
        weights: Vec::with_capacity(points.len() * nn),
        elements: Vec::with_capacity(points.len()),
        per_probe: nn,
    };
    let mut n = vec![0.0; nn];
    for (index, &x) in points.iter().enumerate() {
        if x.iter().any(|v| !v.is_finite()) {
            return Err(ThermalError::ProbeOutside {
                index,
                x: x[0],
                y: x[1],
                z: x[2],
            });
        }
        let found = boxes.iter().enumerate().find_map(|(e, (lo, hi))| {
            let inside = (0..3).all(|d| x[d] >= lo[d] - pad && x[d] <= hi[d] + pad);
            if inside {
                locate_in_element(mesh, e, x, 1e-9).map(|xi| (e, xi))
            } else {
                None
            }
        });
        let (e, xi) = found.ok_or(ThermalError::ProbeOutside {
            index,
            x: x[0],
            y: x[1],
            z: x[2],
        })?;
        kind.shape(xi, &mut n);
        probes.elements.push(e);
        probes.nodes.extend_from_slice(mesh.element(e));
        probes.weights.extend_from_slice(&n);
    }
    Ok(probes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::element::ElementKind;

    #[test]
    fn interpolates_a_quadratic_field_exactly_on_the_block() {
        let (_, m) = crate::mesh::coarse_block_mesh();
        assert_eq!(m.kind, ElementKind::Hex20);
        // y is not polynomial in the (theta, r) parameters, but z and a linear field in z are
        let field: Vec<f64> = m
            .nodes
            .iter()
            .map(|p| 3.0 + 2.0 * p[2] - 5.0 * p[2] * p[2])
            .collect();
        let pts = [
            [0.0, 0.515, 0.0],
            [0.01, 0.48, 0.031],
            [-0.05, 0.47, -0.039],
        ];
        let probes = build_probes(&m, &pts).unwrap();
        let mut out = vec![0.0; 3];
        probes.interpolate(&field, &mut out);
        for (p, v) in pts.iter().zip(&out) {
            let exact = 3.0 + 2.0 * p[2] - 5.0 * p[2] * p[2];
            assert!((v - exact).abs() < 1e-10, "{v} vs {exact}");
        }
    }

    #[test]
    fn points_outside_are_rejected_with_their_index() {
        let (_, m) = crate::mesh::coarse_block_mesh();
        // inside the lug's radial range but beside it (z beyond the lug width)
        let pts = [[0.0, 0.515, 0.0], [0.0, 0.52, 0.035]];
        match build_probes(&m, &pts) {
            Err(ThermalError::ProbeOutside { index, .. }) => assert_eq!(index, 1),
            other => panic!("expected ProbeOutside, got {other:?}"),
        }
    }
}
