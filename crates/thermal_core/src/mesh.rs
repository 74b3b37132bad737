//! Meshes of hexahedra: the data structure, a structured mesher over graded parameter axes,
//! and the two geometries built on it (a rectangular box, and the brake block: body + lug).

use std::collections::BTreeMap;

use crate::element::{det3, jacobian, ElementKind, ReferenceTable, FACE_CORNERS, NODE_NATURAL};
use crate::error::{check_positive, Result, ThermalError};
use crate::quadrature::cube_rule;

/// Boundary faces that share one boundary condition, as (element, local face) pairs.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceSet {
    pub name: String,
    pub faces: Vec<(usize, usize)>,
}

/// A mesh of one element kind: nodes, connectivity in VTK order, and named boundary face sets.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    pub kind: ElementKind,
    pub nodes: Vec<[f64; 3]>,
    /// Flat connectivity, `kind.n_nodes()` entries per element.
    pub elements: Vec<usize>,
    pub face_sets: Vec<FaceSet>,
    /// A fill-reducing elimination order proposed by the mesher (nested dissection of a
    /// structured mesh): `ordering[k]` is the node eliminated k-th.
    pub ordering: Option<Vec<usize>>,
}

impl Mesh {
    pub fn n_nodes(&self) -> usize {
        self.nodes.len()
    }

    pub fn n_elements(&self) -> usize {
        self.elements.len() / self.kind.n_nodes()
    }

    /// Node indices of element `e`.
    pub fn element(&self, e: usize) -> &[usize] {
        let n = self.kind.n_nodes();
        &self.elements[e * n..(e + 1) * n]
    }

    /// Coordinates of the nodes of element `e`.
    pub fn element_coords(&self, e: usize) -> Vec<[f64; 3]> {
        self.element(e).iter().map(|&i| self.nodes[i]).collect()
    }

    /// The face set called `name`.
    pub fn face_set(&self, name: &str) -> Result<&FaceSet> {
        self.face_sets
            .iter()
            .find(|s| s.name == name)
            .ok_or_else(|| ThermalError::UnknownFaceSet {
                name: name.to_string(),
                known: self.face_set_names().join(", "),
            })
    }

    /// Names of the face sets, in mesh order.
    pub fn face_set_names(&self) -> Vec<String> {
        self.face_sets.iter().map(|s| s.name.clone()).collect()
    }

    /// Global node indices of every face of a set, flat, `kind.n_face_nodes()` per face, in VTK
    /// (quadratic) quad order with the outward normal.
    pub fn face_connectivity(&self, name: &str) -> Result<Vec<usize>> {
        let set = self.face_set(name)?;
        let mut out = Vec::with_capacity(set.faces.len() * self.kind.n_face_nodes());
        for &(e, f) in &set.faces {
            let conn = self.element(e);
            out.extend(self.kind.face_nodes(f).iter().map(|&a| conn[a]));
        }
        Ok(out)
    }

    /// Sorted, unique node indices of a face set.
    pub fn face_set_nodes(&self, name: &str) -> Result<Vec<usize>> {
        let mut nodes = self.face_connectivity(name)?;
        nodes.sort_unstable();
        nodes.dedup();
        Ok(nodes)
    }

    /// Smallest Jacobian determinant over every element's quadrature points; an error when an
    /// element is inverted or degenerate.
    pub fn check_jacobians(&self) -> Result<f64> {
        // the quadrature points and the corners
        let mut points = cube_rule(self.kind.volume_order());
        points.extend(NODE_NATURAL[..8].iter().map(|p| (*p, 0.0)));
        let table = ReferenceTable::new(self.kind, &points);
        let mut min_det = f64::INFINITY;
        for e in 0..self.n_elements() {
            let coords = self.element_coords(e);
            for p in &table.points {
                let d = det3(&jacobian(&coords, &p.dn));
                if !(d > 0.0) {
                    return Err(ThermalError::InvalidMesh(format!(
                        "element {e} has a non-positive Jacobian determinant {d:e} at {:?}",
                        p.xi
                    )));
                }
                min_det = min_det.min(d);
            }
        }
        Ok(min_det)
    }
}

/// How cell sizes vary inside one segment of an axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Grading {
    Uniform,
    /// Smallest cell at the segment's start; largest / smallest = the ratio.
    FineAtStart(f64),
    /// Smallest cell at the segment's end.
    FineAtEnd(f64),
    /// Smallest cells at both ends, largest in the middle.
    FineAtBoth(f64),
}

/// Cell boundaries along one parameter direction, strictly increasing.
#[derive(Debug, Clone, PartialEq)]
pub struct Axis {
    pub points: Vec<f64>,
}

impl Axis {
    /// `n` equal cells on [a, b].
    pub fn uniform(a: f64, b: f64, n: usize) -> Result<Axis> {
        Axis::from_segments(a, &[(b, n, Grading::Uniform)])
    }

    /// Consecutive segments from `start`: each (end, cells, grading).
    pub fn from_segments(start: f64, segments: &[(f64, usize, Grading)]) -> Result<Axis> {
        let mut points = vec![start];
        let mut a = start;
        for &(b, n, grading) in segments {
            if !(b > a) || n == 0 {
                return Err(ThermalError::InvalidMesh(format!(
                    "axis segment [{a}, {b}] with {n} cells is empty or reversed"
                )));
            }
            let sizes = segment_sizes(n, grading)?;
            let total: f64 = sizes.iter().sum();
            let mut x = a;
            for s in &sizes[..n - 1] {
                x += (b - a) * s / total;
                points.push(x);
            }
            points.push(b);
            a = b;
        }
        Ok(Axis { points })
    }

    pub fn n_cells(&self) -> usize {
        self.points.len() - 1
    }

    /// Parameter value of a doubled-grid index: even indices are cell boundaries, odd ones
    /// cell midpoints (the mid-edge nodes of quadratic elements).
    fn doubled(&self, d: usize) -> f64 {
        if d % 2 == 0 {
            self.points[d / 2]
        } else {
            0.5 * (self.points[d / 2] + self.points[d / 2 + 1])
        }
    }
}

fn segment_sizes(n: usize, grading: Grading) -> Result<Vec<f64>> {
    let ratio = match grading {
        Grading::Uniform => 1.0,
        Grading::FineAtStart(r) | Grading::FineAtEnd(r) | Grading::FineAtBoth(r) => r,
    };
    if !(ratio >= 1.0) || !ratio.is_finite() {
        return Err(ThermalError::InvalidMesh(format!(
            "grading ratio must be >= 1, got {ratio}"
        )));
    }
    let geometric = |steps: usize| -> Vec<f64> {
        if steps <= 1 {
            return vec![1.0; steps.max(1)];
        }
        let q = ratio.powf(1.0 / (steps as f64 - 1.0));
        (0..steps).map(|i| q.powi(i as i32)).collect()
    };
    Ok(match grading {
        Grading::Uniform => vec![1.0; n],
        Grading::FineAtStart(_) => geometric(n),
        Grading::FineAtEnd(_) => {
            let mut s = geometric(n);
            s.reverse();
            s
        }
        Grading::FineAtBoth(_) => {
            let half = n.div_ceil(2);
            let up = geometric(half);
            (0..n).map(|i| up[i.min(n - 1 - i)]).collect()
        }
    })
}

/// A structured mesh over the tensor grid of three parameter axes: the cells for which `include`
/// holds (given the cell's parameter centre), nodes mapped to space by `map`, and every boundary
/// face put in the face set that `classify` names (given the parameter coordinates of the face's
/// four corners). Mid-edge nodes of quadratic elements sit at parameter midpoints, so a curved
/// map puts them on the curve.
pub fn structured_mesh(
    axes: [&Axis; 3],
    scales: [f64; 3],
    kind: ElementKind,
    include: impl Fn([f64; 3]) -> bool,
    map: impl Fn([f64; 3]) -> [f64; 3],
    classify: impl Fn(&[[f64; 3]; 4]) -> String,
) -> Result<Mesh> {
    let nc = [axes[0].n_cells(), axes[1].n_cells(), axes[2].n_cells()];
    let cell_index = |c: [usize; 3]| (c[0] * nc[1] + c[1]) * nc[2] + c[2];
    let mut included = vec![false; nc[0] * nc[1] * nc[2]];
    for i in 0..nc[0] {
        for j in 0..nc[1] {
            for k in 0..nc[2] {
                let centre = [
                    0.5 * (axes[0].points[i] + axes[0].points[i + 1]),
                    0.5 * (axes[1].points[j] + axes[1].points[j + 1]),
                    0.5 * (axes[2].points[k] + axes[2].points[k + 1]),
                ];
                included[cell_index([i, j, k])] = include(centre);
            }
        }
    }
    let nd = [2 * nc[0] + 1, 2 * nc[1] + 1, 2 * nc[2] + 1];
    let mut node_of = vec![usize::MAX; nd[0] * nd[1] * nd[2]];
    let mut nodes: Vec<[f64; 3]> = Vec::new();
    let mut params: Vec<[f64; 3]> = Vec::new();
    let mut doubled: Vec<[usize; 3]> = Vec::new();
    let mut elements = Vec::new();
    let mut cells = Vec::new();
    let nn = kind.n_nodes();
    for i in 0..nc[0] {
        for j in 0..nc[1] {
            for k in 0..nc[2] {
                if !included[cell_index([i, j, k])] {
                    continue;
                }
                cells.push([i, j, k]);
                for p in &NODE_NATURAL[..nn] {
                    let d = [
                        (2 * i as i64 + 1 + p[0] as i64) as usize,
                        (2 * j as i64 + 1 + p[1] as i64) as usize,
                        (2 * k as i64 + 1 + p[2] as i64) as usize,
                    ];
                    let key = (d[0] * nd[1] + d[1]) * nd[2] + d[2];
                    if node_of[key] == usize::MAX {
                        let param = [
                            axes[0].doubled(d[0]),
                            axes[1].doubled(d[1]),
                            axes[2].doubled(d[2]),
                        ];
                        node_of[key] = nodes.len();
                        nodes.push(map(param));
                        params.push(param);
                        doubled.push(d);
                    }
                    elements.push(node_of[key]);
                }
            }
        }
    }
    if cells.is_empty() {
        return Err(ThermalError::InvalidMesh(
            "no cell is inside the geometry".into(),
        ));
    }
    let mut sets: BTreeMap<String, Vec<(usize, usize)>> = BTreeMap::new();
    let mut order: Vec<String> = Vec::new();
    for (e, c) in cells.iter().enumerate() {
        for (f, (axis, side, corners)) in FACE_CORNERS.iter().enumerate() {
            let mut nb = [c[0] as i64, c[1] as i64, c[2] as i64];
            nb[*axis] += *side as i64;
            let inside = nb[*axis] >= 0
                && (nb[*axis] as usize) < nc[*axis]
                && included[cell_index([nb[0] as usize, nb[1] as usize, nb[2] as usize])];
            if inside {
                continue;
            }
            let conn = &elements[e * nn..(e + 1) * nn];
            let corner_params = [
                params[conn[corners[0]]],
                params[conn[corners[1]]],
                params[conn[corners[2]]],
                params[conn[corners[3]]],
            ];
            let name = classify(&corner_params);
            if !sets.contains_key(&name) {
                order.push(name.clone());
            }
            sets.entry(name).or_default().push((e, f));
        }
    }
    let face_sets = order
        .into_iter()
        .map(|name| {
            let faces = sets.remove(&name).unwrap_or_default();
            FaceSet { name, faces }
        })
        .collect();
    let extents: [Vec<f64>; 3] = [0, 1, 2].map(|d| {
        axes[d]
            .points
            .windows(2)
            .map(|w| (w[1] - w[0]) * scales[d])
            .collect()
    });
    let ordering = Some(nested_dissection(&doubled, &extents));
    let mesh = Mesh {
        kind,
        nodes,
        elements,
        face_sets,
        ordering,
    };
    mesh.check_jacobians()?;
    Ok(mesh)
}

/// Nested dissection of a structured mesh in index space: split the region of cells along its
/// physically longest direction at an element boundary; the nodes on that plane form the
/// separator, ordered after both halves. `doubled[i]` is node i's doubled-grid index and
/// `cell_sizes[d]` the physical size of each cell along direction d.
fn nested_dissection(doubled: &[[usize; 3]], cell_sizes: &[Vec<f64>; 3]) -> Vec<usize> {
    let mut order = Vec::with_capacity(doubled.len());
    let all: Vec<usize> = (0..doubled.len()).collect();
    let full = [0, 1, 2].map(|d| (0, cell_sizes[d].len()));
    dissect(doubled, cell_sizes, all, full, &mut order);
    order
}

fn dissect(
    doubled: &[[usize; 3]],
    cell_sizes: &[Vec<f64>; 3],
    nodes: Vec<usize>,
    region: [(usize, usize); 3],
    order: &mut Vec<usize>,
) {
    if nodes.is_empty() {
        return;
    }
    let extent = |d: usize| -> f64 { cell_sizes[d][region[d].0..region[d].1].iter().sum() };
    // the cell boundary closest to the physical middle of direction d
    let middle = |d: usize| -> usize {
        let (lo, hi) = region[d];
        let half = 0.5 * extent(d);
        let mut acc = 0.0;
        let mut mid = lo + 1;
        for (c, size) in cell_sizes[d].iter().enumerate().take(hi - 1).skip(lo) {
            acc += size;
            mid = c + 1;
            if acc >= half {
                break;
            }
        }
        mid
    };
    // split where the separator is smallest (fewest nodes on the middle plane)
    let candidates: Vec<(usize, usize, usize)> = (0..3)
        .filter(|&d| region[d].1 - region[d].0 >= 2)
        .map(|d| {
            let mid = middle(d);
            let size = nodes.iter().filter(|&&i| doubled[i][d] == 2 * mid).count();
            (size, d, mid)
        })
        .collect();
    let Some(&(_, axis, mid)) = candidates.iter().min_by_key(|c| (c.0, c.1)) else {
        order.extend(nodes);
        return;
    };
    let (lo, hi) = region[axis];
    let plane = 2 * mid;
    let (mut left, mut right, mut separator) = (Vec::new(), Vec::new(), Vec::new());
    for i in nodes {
        match doubled[i][axis].cmp(&plane) {
            std::cmp::Ordering::Less => left.push(i),
            std::cmp::Ordering::Greater => right.push(i),
            std::cmp::Ordering::Equal => separator.push(i),
        }
    }
    let mut left_region = region;
    left_region[axis] = (lo, mid);
    let mut right_region = region;
    right_region[axis] = (mid, hi);
    dissect(doubled, cell_sizes, left, left_region, order);
    dissect(doubled, cell_sizes, right, right_region, order);
    order.extend(separator);
}

/// A rectangular box [0, lx] x [0, ly] x [0, lz] with `n` cells per direction (uniform), faces
/// named `x0`, `x1`, `y0`, `y1`, `z0`, `z1`.
pub fn box_mesh(lengths_m: [f64; 3], cells: [usize; 3], kind: ElementKind) -> Result<Mesh> {
    for (d, l) in lengths_m.iter().enumerate() {
        check_positive(&format!("box length {d}"), *l)?;
    }
    let axes = [
        Axis::uniform(0.0, lengths_m[0], cells[0])?,
        Axis::uniform(0.0, lengths_m[1], cells[1])?,
        Axis::uniform(0.0, lengths_m[2], cells[2])?,
    ];
    let tol = 1e-12 * lengths_m.iter().fold(0.0f64, |a, b| a.max(*b));
    structured_mesh(
        [&axes[0], &axes[1], &axes[2]],
        [1.0; 3],
        kind,
        |_| true,
        |p| p,
        |c| {
            for (d, name) in ["x", "y", "z"].iter().enumerate() {
                if c.iter().all(|p| p[d].abs() <= tol) {
                    return format!("{name}0");
                }
                if c.iter().all(|p| (p[d] - lengths_m[d]).abs() <= tol) {
                    return format!("{name}1");
                }
            }
            "interior".to_string()
        },
    )
}

/// Dimensions of a block insert (see `shared/spec/block-model.md`), metres and degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlockGeometry {
    pub wheel_radius_m: f64,
    pub contact_angle_deg: f64,
    pub block_width_m: f64,
    pub body_thickness_m: f64,
    pub lug_height_m: f64,
    pub lug_angle_deg: f64,
    pub lug_width_m: f64,
}

impl Default for BlockGeometry {
    fn default() -> Self {
        BlockGeometry {
            wheel_radius_m: 0.460,
            contact_angle_deg: 29.4,
            block_width_m: 0.080,
            body_thickness_m: 0.045,
            lug_height_m: 0.025,
            lug_angle_deg: 8.0,
            lug_width_m: 0.040,
        }
    }
}

impl BlockGeometry {
    pub fn validate(&self) -> Result<()> {
        check_positive("wheel_radius_m", self.wheel_radius_m)?;
        check_positive("contact_angle_deg", self.contact_angle_deg)?;
        check_positive("block_width_m", self.block_width_m)?;
        check_positive("body_thickness_m", self.body_thickness_m)?;
        check_positive("lug_height_m", self.lug_height_m)?;
        check_positive("lug_angle_deg", self.lug_angle_deg)?;
        check_positive("lug_width_m", self.lug_width_m)?;
        let bad = |name: &str, value: f64, reason: &str| {
            Err(ThermalError::InvalidParameter {
                name: name.into(),
                value,
                reason: reason.into(),
            })
        };
        if self.contact_angle_deg >= 180.0 {
            return bad(
                "contact_angle_deg",
                self.contact_angle_deg,
                "must be below 180",
            );
        }
        if self.lug_angle_deg >= self.contact_angle_deg {
            return bad(
                "lug_angle_deg",
                self.lug_angle_deg,
                "must be below contact_angle_deg",
            );
        }
        if self.lug_width_m >= self.block_width_m {
            return bad(
                "lug_width_m",
                self.lug_width_m,
                "must be below block_width_m",
            );
        }
        Ok(())
    }

    /// Cylindrical parameters (theta rad, r, z) of a Cartesian point.
    pub fn to_param(&self, p: [f64; 3]) -> [f64; 3] {
        [p[0].atan2(p[1]), p[0].hypot(p[1]), p[2]]
    }

    /// Whether parameter coordinates (theta rad, r, z) lie in the body or the lug (closed).
    pub fn contains_param(&self, q: [f64; 3], tol: f64) -> bool {
        let half_c = 0.5 * self.contact_angle_deg.to_radians();
        let half_l = 0.5 * self.lug_angle_deg.to_radians();
        let r0 = self.wheel_radius_m;
        let r1 = r0 + self.body_thickness_m;
        let r2 = r1 + self.lug_height_m;
        let in_body = q[0].abs() <= half_c + tol / r0
            && q[1] >= r0 - tol
            && q[1] <= r1 + tol
            && q[2].abs() <= 0.5 * self.block_width_m + tol;
        let in_lug = q[0].abs() <= half_l + tol / r0
            && q[1] >= r1 - tol
            && q[1] <= r2 + tol
            && q[2].abs() <= 0.5 * self.lug_width_m + tol;
        in_body || in_lug
    }
}

/// Resolution of the block mesh.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlockMeshSpec {
    pub kind: ElementKind,
    /// Multiplies the cell count along every direction (1.0: about 21,000 nodes with Hex20).
    pub refinement: f64,
    /// Point towards which the mesh is graded (the sensor seat), Cartesian metres.
    pub focus_m: Option<[f64; 3]>,
    /// Largest over smallest cell next to the friction face and the focus point.
    pub grading_ratio: f64,
}

impl Default for BlockMeshSpec {
    fn default() -> Self {
        BlockMeshSpec {
            kind: ElementKind::Hex20,
            refinement: 1.0,
            focus_m: None,
            grading_ratio: 3.0,
        }
    }
}

/// Base cell sizes at refinement 1: arc length along theta, radial, axial (metres).
const BASE_CELL_M: [f64; 3] = [0.0076, 0.0038, 0.0061];

/// Build one graded axis over [lo, hi] through the breakpoints (geometry edges and focus points):
/// segments next to a focus point (or a fine end) get their smallest cells there.
fn graded_axis(
    breaks: &[f64],
    fine_points: &[f64],
    cell: f64,
    refinement: f64,
    ratio: f64,
) -> Result<Axis> {
    let mut b: Vec<f64> = breaks.to_vec();
    b.sort_by(f64::total_cmp);
    let span = b[b.len() - 1] - b[0];
    b.dedup_by(|x, y| (*x - *y).abs() < 1e-9 * span);
    let is_fine = |x: f64| fine_points.iter().any(|f| (f - x).abs() < 1e-9 * span);
    let mut segments = Vec::new();
    for w in b.windows(2) {
        let len = w[1] - w[0];
        let n = ((len / cell * refinement).round() as usize).max(1);
        let grading = match (is_fine(w[0]), is_fine(w[1])) {
            (true, true) => Grading::FineAtBoth(ratio),
            (true, false) => Grading::FineAtStart(ratio),
            (false, true) => Grading::FineAtEnd(ratio),
            (false, false) => Grading::Uniform,
        };
        segments.push((w[1], n, grading));
    }
    Axis::from_segments(b[0], &segments)
}

/// Mesh of the block: body (ring sector) and lug, graded towards the friction face and the
/// focus point, with face sets `friction` (r = R_w), `holder` (the back face and the lug, where
/// the holder touches) and `air` (the remaining free surfaces).
pub fn block_mesh(geometry: &BlockGeometry, spec: &BlockMeshSpec) -> Result<Mesh> {
    geometry.validate()?;
    check_positive("refinement", spec.refinement)?;
    if !(spec.grading_ratio >= 1.0) || !spec.grading_ratio.is_finite() {
        return Err(ThermalError::InvalidParameter {
            name: "grading_ratio".into(),
            value: spec.grading_ratio,
            reason: "must be at least 1".into(),
        });
    }
    let g = geometry;
    let r0 = g.wheel_radius_m;
    let r1 = r0 + g.body_thickness_m;
    let r2 = r1 + g.lug_height_m;
    let half_c = 0.5 * g.contact_angle_deg.to_radians();
    let half_l = 0.5 * g.lug_angle_deg.to_radians();
    let half_w = 0.5 * g.block_width_m;
    let half_lw = 0.5 * g.lug_width_m;

    let mut theta_breaks = vec![-half_c, -half_l, half_l, half_c];
    let mut r_breaks = vec![r0, r1, r2];
    let mut z_breaks = vec![-half_w, -half_lw, half_lw, half_w];
    let mut theta_fine = vec![];
    let mut r_fine = vec![r0];
    let mut z_fine = vec![];
    if let Some(p) = spec.focus_m {
        let q = g.to_param(p);
        if !g.contains_param(q, 1e-9) {
            return Err(ThermalError::ProbeOutside {
                index: 0,
                x: p[0],
                y: p[1],
                z: p[2],
            });
        }
        let tol = 1e-6;
        let inner = |x: f64, lo: f64, hi: f64| x > lo + tol * (hi - lo) && x < hi - tol * (hi - lo);
        if inner(q[0], -half_c, half_c) {
            theta_breaks.push(q[0]);
        }
        theta_fine.push(q[0]);
        if inner(q[1], r0, r2) {
            r_breaks.push(q[1]);
        }
        r_fine.push(q[1]);
        if inner(q[2], -half_w, half_w) {
            z_breaks.push(q[2]);
        }
        z_fine.push(q[2]);
    }
    let ratio = spec.grading_ratio;
    let theta_cell = BASE_CELL_M[0] / r0;
    let axes = [
        graded_axis(
            &theta_breaks,
            &theta_fine,
            theta_cell,
            spec.refinement,
            ratio,
        )?,
        graded_axis(&r_breaks, &r_fine, BASE_CELL_M[1], spec.refinement, ratio)?,
        graded_axis(&z_breaks, &z_fine, BASE_CELL_M[2], spec.refinement, ratio)?,
    ];
    let geom = *g;
    let tol_r = 1e-9 * r2;
    structured_mesh(
        [&axes[0], &axes[1], &axes[2]],
        [r0, 1.0, 1.0],
        spec.kind,
        |c| geom.contains_param(c, 0.0),
        |q| [q[1] * q[0].sin(), q[1] * q[0].cos(), q[2]],
        |c| {
            if c.iter().all(|q| (q[1] - r0).abs() <= tol_r) {
                "friction".to_string()
            } else if c.iter().all(|q| q[1] >= r1 - tol_r) {
                "holder".to_string()
            } else {
                "air".to_string()
            }
        },
    )
}

/// The reference block (default geometry) at half the default resolution, for tests.
#[cfg(test)]
pub(crate) fn coarse_block_mesh() -> (BlockGeometry, Mesh) {
    let g = BlockGeometry::default();
    let spec = BlockMeshSpec {
        refinement: 0.5,
        ..Default::default()
    };
    let m = block_mesh(&g, &spec).expect("the default block meshes");
    (g, m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_grading_is_monotone_and_hits_the_ends() {
        let a = Axis::from_segments(
            0.0,
            &[
                (1.0, 5, Grading::FineAtStart(4.0)),
                (3.0, 6, Grading::FineAtBoth(3.0)),
            ],
        )
        .unwrap();
        assert_eq!(a.n_cells(), 11);
        assert_eq!(a.points[0], 0.0);
        assert_eq!(a.points[5], 1.0);
        assert_eq!(a.points[11], 3.0);
        let sizes: Vec<f64> = a.points.windows(2).map(|w| w[1] - w[0]).collect();
        assert!(sizes.iter().all(|s| *s > 0.0));
        assert!((sizes[4] / sizes[0] - 4.0).abs() < 1e-9);
        assert!(sizes[0] < sizes[1]);
    }

    #[test]
    fn box_mesh_counts_and_face_sets() {
        let m = box_mesh([1.0, 0.5, 0.25], [4, 2, 1], ElementKind::Hex20).unwrap();
        assert_eq!(m.n_elements(), 8);
        // serendipity nodes: corners + one per edge of the grid
        let corners = 5 * 3 * 2;
        let edges = 4 * 3 * 2 + 5 * 2 * 2 + 5 * 3;
        assert_eq!(m.n_nodes(), corners + edges);
        for name in ["x0", "x1", "y0", "y1", "z0", "z1"] {
            assert!(m.face_set(name).is_ok(), "{name}");
        }
        assert_eq!(m.face_set("x0").unwrap().faces.len(), 2);
        assert_eq!(m.face_set("z1").unwrap().faces.len(), 8);
        assert!(m.face_set("interior").is_err());
        // the proposed ordering is a permutation
        let mut ord = m.ordering.clone().unwrap();
        ord.sort_unstable();
        assert!(ord.iter().enumerate().all(|(i, v)| i == *v));
    }

    #[test]
    fn default_block_mesh_has_about_the_papers_node_count() {
        let g = BlockGeometry::default();
        let spec = BlockMeshSpec {
            focus_m: Some([0.0, g.wheel_radius_m + 0.055, 0.0]),
            ..Default::default()
        };
        let m = block_mesh(&g, &spec).unwrap();
        let n = m.n_nodes();
        assert!((19_000..=23_000).contains(&n), "{n} nodes");
        let names = m.face_set_names();
        for name in ["friction", "air", "holder"] {
            assert!(names.contains(&name.to_string()), "{names:?}");
        }
        // every friction-face node lies on the wheel radius
        for i in m.face_set_nodes("friction").unwrap() {
            let p = m.nodes[i];
            assert!((p[0].hypot(p[1]) - g.wheel_radius_m).abs() < 1e-12);
        }
    }

    #[test]
    fn focus_outside_the_block_is_an_error() {
        let g = BlockGeometry::default();
        let spec = BlockMeshSpec {
            focus_m: Some([0.0, 0.3, 0.0]),
            ..Default::default()
        };
        assert!(matches!(
            block_mesh(&g, &spec),
            Err(ThermalError::ProbeOutside { .. })
        ));
    }
}
