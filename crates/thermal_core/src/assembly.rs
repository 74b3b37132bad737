//! Assembly of the operators of the heat equation on one symmetric sparsity pattern:
//! capacity `M = ∫ ρc N Nᵀ dV`, conduction `K = ∫ k ∇N ∇Nᵀ dV`, and per face set the boundary
//! mass `H_s = ∫_s N Nᵀ dA` (convection: h H_s) and load `G_s = ∫_s N dA` (flux, h T_amb).

use rayon::prelude::*;

use crate::element::{cross, inv3, jacobian, ElementKind, ReferenceTable, FACE_CORNERS};
use crate::error::{check_positive, Result, ThermalError};
use crate::mesh::Mesh;
use crate::quadrature::{cube_rule, square_rule};

/// Isotropic, temperature-independent material.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    pub conductivity_w_mk: f64,
    pub density_kg_m3: f64,
    pub specific_heat_j_kgk: f64,
}

impl Material {
    /// Cast iron of the block (paper, Table 1).
    pub const CAST_IRON: Material = Material {
        conductivity_w_mk: 48.0,
        density_kg_m3: 7100.0,
        specific_heat_j_kgk: 520.0,
    };

    pub fn validate(&self) -> Result<()> {
        check_positive("conductivity_w_mk", self.conductivity_w_mk)?;
        check_positive("density_kg_m3", self.density_kg_m3)?;
        check_positive("specific_heat_j_kgk", self.specific_heat_j_kgk)
    }
}

/// The symmetric sparsity pattern of a mesh, both triangles stored, compressed sparse columns
/// with sorted row indices.
#[derive(Debug, Clone, PartialEq)]
pub struct Pattern {
    pub n: usize,
    pub col_ptr: Vec<usize>,
    pub row_idx: Vec<usize>,
}

impl Pattern {
    /// Two nodes are coupled when an element holds both.
    pub fn from_mesh(mesh: &Mesh) -> Pattern {
        let n = mesh.n_nodes();
        let mut neighbours: Vec<Vec<usize>> = vec![Vec::new(); n];
        for e in 0..mesh.n_elements() {
            let conn = mesh.element(e);
            for &a in conn {
                neighbours[a].extend_from_slice(conn);
            }
        }
        let mut col_ptr = Vec::with_capacity(n + 1);
        col_ptr.push(0);
        let mut row_idx = Vec::new();
        for list in &mut neighbours {
            list.sort_unstable();
            list.dedup();
            row_idx.extend_from_slice(list);
            col_ptr.push(row_idx.len());
        }
        Pattern {
            n,
            col_ptr,
            row_idx,
        }
    }

    pub fn nnz(&self) -> usize {
        self.row_idx.len()
    }

    /// Index into the value array of entry (row, col), if it is in the pattern.
    pub fn position(&self, row: usize, col: usize) -> Option<usize> {
        let start = self.col_ptr[col];
        let rows = &self.row_idx[start..self.col_ptr[col + 1]];
        rows.binary_search(&row).ok().map(|k| start + k)
    }

    /// `y = A x` for a matrix with these values.
    pub fn matvec(&self, values: &[f64], x: &[f64], y: &mut [f64]) {
        y.iter_mut().for_each(|v| *v = 0.0);
        self.matvec_add(values, x, y);
    }

    /// `y += A x`; the matrix is symmetric, so row j of A is column j: one dot product per
    /// row, rows in parallel (rayon) for matrices large enough to be worth it.
    pub fn matvec_add(&self, values: &[f64], x: &[f64], y: &mut [f64]) {
        let rows = |first: usize, y: &mut [f64]| {
            for (k, yj) in y.iter_mut().enumerate() {
                let range = self.col_ptr[first + k]..self.col_ptr[first + k + 1];
                *yj += sparse_dot(&values[range.clone()], &self.row_idx[range], x);
            }
        };
        if self.nnz() < PARALLEL_MATVEC_MIN_NNZ {
            rows(0, y);
        } else {
            y.par_chunks_mut(MATVEC_ROWS_PER_TASK)
                .enumerate()
                .for_each(|(c, chunk)| rows(c * MATVEC_ROWS_PER_TASK, chunk));
        }
    }

    /// Sum of several value arrays with coefficients: Σ c_i A_i.
    pub fn combine(&self, terms: &[(f64, &[f64])]) -> Vec<f64> {
        let mut out = vec![0.0; self.nnz()];
        for (c, values) in terms {
            if *c == 0.0 {
                continue;
            }
            for (o, v) in out.iter_mut().zip(values.iter()) {
                *o += c * v;
            }
        }
        out
    }
}

/// `Σ_k values[k] x[index[k]]` in four partial sums: one running sum would make every
/// add wait for the one before (the compiler keeps the order of floating-point adds).
#[inline]
fn sparse_dot(values: &[f64], index: &[usize], x: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let vs = values.chunks_exact(4);
    let is = index.chunks_exact(4);
    let (v_rest, i_rest) = (vs.remainder(), is.remainder());
    for (v, i) in vs.zip(is) {
        acc[0] += v[0] * x[i[0]];
        acc[1] += v[1] * x[i[1]];
        acc[2] += v[2] * x[i[2]];
        acc[3] += v[3] * x[i[3]];
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (v, &i) in v_rest.iter().zip(i_rest) {
        s += v * x[i];
    }
    s
}

/// The lower triangle (diagonal first in each column) of a [`Pattern`], with 32-bit row
/// indices, for the time stepper's one mat-vec a step: a symmetric product reads half the
/// values and a third of the index bytes of the full pattern's.
#[derive(Debug, Clone, PartialEq)]
pub struct LowerPattern {
    pub n: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<u32>,
    /// Position of each lower entry in the full pattern's value array.
    source: Vec<usize>,
    /// First column of the second half (by stored entries) for two-thread products.
    middle: usize,
}

impl LowerPattern {
    /// The lower triangle of `pattern`; an error if a column lacks its diagonal entry or
    /// the nodes do not fit 32-bit indices.
    pub fn new(pattern: &Pattern) -> Result<Self> {
        let n = pattern.n;
        if u32::try_from(n).is_err() {
            return Err(ThermalError::InvalidMesh(format!(
                "{n} nodes do not fit 32-bit indices"
            )));
        }
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        let mut source = Vec::new();
        col_ptr.push(0);
        for j in 0..n {
            let range = pattern.col_ptr[j]..pattern.col_ptr[j + 1];
            let first = pattern.row_idx[range.clone()].partition_point(|&i| i < j);
            if pattern.row_idx.get(range.start + first) != Some(&j) {
                return Err(ThermalError::InvalidMesh(format!(
                    "column {j} of the pattern has no diagonal entry"
                )));
            }
            for k in range.start + first..range.end {
                row_idx.push(pattern.row_idx[k] as u32);
                source.push(k);
            }
            col_ptr.push(row_idx.len());
        }
        let half = row_idx.len() / 2;
        let middle = col_ptr.partition_point(|&p| p < half).min(n);
        Ok(LowerPattern {
            n,
            col_ptr,
            row_idx,
            source,
            middle,
        })
    }

    /// The lower-triangle values of a matrix given on the full pattern.
    pub fn values(&self, full: &[f64]) -> Vec<f64> {
        self.source.iter().map(|&k| full[k]).collect()
    }

    /// `y = A x` for the symmetric matrix with these lower-triangle values; two threads
    /// (each column range into its own copy of y, then summed) for large matrices.
    pub fn matvec(&self, values: &[f64], x: &[f64], y: &mut [f64]) {
        y.iter_mut().for_each(|v| *v = 0.0);
        if self.row_idx.len() < PARALLEL_MATVEC_MIN_NNZ || rayon::current_num_threads() < 2 {
            self.columns(values, x, y, 0..self.n);
            return;
        }
        let mut other = vec![0.0; self.n];
        rayon::join(
            || self.columns(values, x, y, 0..self.middle),
            || self.columns(values, x, &mut other, self.middle..self.n),
        );
        for (a, b) in y.iter_mut().zip(&other) {
            *a += b;
        }
    }

    /// Columns `cols`: each adds its diagonal and strict-lower dot product to `y[j]` and its
    /// strict-lower entries times `x[j]` to their rows.
    fn columns(&self, values: &[f64], x: &[f64], y: &mut [f64], cols: std::ops::Range<usize>) {
        for j in cols {
            let (start, end) = (self.col_ptr[j], self.col_ptr[j + 1]);
            let xj = x[j];
            let rows = &self.row_idx[start + 1..end];
            let vals = &values[start + 1..end];
            let mut acc = [values[start] * xj, 0.0];
            let pairs = rows.chunks_exact(2).zip(vals.chunks_exact(2));
            let tail = rows.len() - rows.len() % 2;
            for (i2, v2) in pairs {
                let (i0, i1) = (i2[0] as usize, i2[1] as usize);
                acc[0] += v2[0] * x[i0];
                acc[1] += v2[1] * x[i1];
                y[i0] += v2[0] * xj;
                y[i1] += v2[1] * xj;
            }
            for (&i, &v) in rows[tail..].iter().zip(&vals[tail..]) {
                acc[0] += v * x[i as usize];
                y[i as usize] += v * xj;
            }
            y[j] += acc[0] + acc[1];
        }
    }
}

/// Matrices with fewer stored entries are multiplied on one thread.
const PARALLEL_MATVEC_MIN_NNZ: usize = 500_000;
/// Rows per parallel task of a mat-vec.
const MATVEC_ROWS_PER_TASK: usize = 2048;

/// Boundary operators of one face set.
#[derive(Debug, Clone, PartialEq)]
pub struct FaceOperator {
    pub name: String,
    /// `∫_s N Nᵀ dA` on the pattern.
    pub mass: Vec<f64>,
    /// `∫_s N dA`, one entry per node.
    pub load: Vec<f64>,
    pub area_m2: f64,
}

/// Every operator of the model on one pattern.
#[derive(Debug, Clone, PartialEq)]
pub struct Operators {
    pub pattern: Pattern,
    /// Capacity `∫ ρc N Nᵀ dV` (J/K).
    pub capacity: Vec<f64>,
    /// Conduction `∫ k ∇N ∇Nᵀ dV` (W/K).
    pub conduction: Vec<f64>,
    pub faces: Vec<FaceOperator>,
    pub volume_m3: f64,
}

impl Operators {
    /// Index of the face operator called `name`.
    pub fn face_index(&self, name: &str) -> Result<usize> {
        self.faces
            .iter()
            .position(|f| f.name == name)
            .ok_or_else(|| ThermalError::UnknownFaceSet {
                name: name.to_string(),
                known: self
                    .faces
                    .iter()
                    .map(|f| f.name.clone())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    }
}

struct ElementMatrices {
    capacity: Vec<f64>,
    conduction: Vec<f64>,
    volume: f64,
}

/// Positions in the pattern's value array of an element's entries (a, b), row-major.
fn element_positions(pattern: &Pattern, conn: &[usize]) -> Result<Vec<usize>> {
    let mut out = Vec::with_capacity(conn.len() * conn.len());
    for &ia in conn {
        for &ib in conn {
            out.push(pattern.position(ia, ib).ok_or_else(|| {
                ThermalError::InvalidMesh(format!("entry ({ia}, {ib}) missing from the pattern"))
            })?);
        }
    }
    Ok(out)
}

/// Capacity and conduction matrices of one element (row-major, symmetric: the upper
/// triangle is summed over the points and mirrored).
fn element_matrices(
    table: &ReferenceTable,
    coords: &[[f64; 3]],
    material: &Material,
) -> Result<ElementMatrices> {
    let nn = table.nn;
    let mut gx = vec![[0.0; 3]; nn];
    let mut capacity = vec![0.0; nn * nn];
    let mut conduction = vec![0.0; nn * nn];
    let rho_c = material.density_kg_m3 * material.specific_heat_j_kgk;
    let k = material.conductivity_w_mk;
    let mut volume = 0.0;
    for p in &table.points {
        let (n, dn) = (&p.n, &p.dn);
        let j = jacobian(coords, dn);
        let (inv, det) = inv3(&j).filter(|(_, d)| *d > 0.0).ok_or_else(|| {
            ThermalError::InvalidMesh(format!("degenerate element at {:?}", p.xi))
        })?;
        let dv = p.weight * det;
        volume += dv;
        for (g, d) in gx.iter_mut().zip(dn) {
            for i in 0..3 {
                g[i] = inv[0][i] * d[0] + inv[1][i] * d[1] + inv[2][i] * d[2];
            }
        }
        let (c_dv, k_dv) = (rho_c * dv, k * dv);
        for a in 0..nn {
            let (na, ga) = (c_dv * n[a], gx[a].map(|v| v * k_dv));
            let row = a * nn;
            for b in a..nn {
                capacity[row + b] += na * n[b];
                conduction[row + b] += ga[0] * gx[b][0] + ga[1] * gx[b][1] + ga[2] * gx[b][2];
            }
        }
    }
    for a in 0..nn {
        for b in 0..a {
            capacity[a * nn + b] = capacity[b * nn + a];
            conduction[a * nn + b] = conduction[b * nn + a];
        }
    }
    Ok(ElementMatrices {
        capacity,
        conduction,
        volume,
    })
}

/// `∫_face N_a N_b dA` and `∫_face N_a dA` over local face `f` of an element.
fn face_matrices(kind: ElementKind, coords: &[[f64; 3]], f: usize) -> (Vec<f64>, Vec<f64>, f64) {
    let nn = kind.n_nodes();
    let (axis, side, _) = FACE_CORNERS[f];
    let (u, v) = match axis {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let mut n = vec![0.0; nn];
    let mut dn = vec![[0.0; 3]; nn];
    let mut mass = vec![0.0; nn * nn];
    let mut load = vec![0.0; nn];
    let mut area = 0.0;
    for (st, w) in square_rule(kind.volume_order()) {
        let mut xi = [0.0; 3];
        xi[axis] = side;
        xi[u] = st[0];
        xi[v] = st[1];
        kind.shape(xi, &mut n);
        kind.grad(xi, &mut dn);
        let j = jacobian(coords, &dn);
        let tu = [j[0][u], j[1][u], j[2][u]];
        let tv = [j[0][v], j[1][v], j[2][v]];
        let c = cross(tu, tv);
        let da = w * (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
        area += da;
        for a in 0..nn {
            load[a] += n[a] * da;
            for b in 0..nn {
                mass[a * nn + b] += n[a] * n[b] * da;
            }
        }
    }
    (mass, load, area)
}

/// Assemble every operator of the mesh.
pub fn assemble(mesh: &Mesh, material: &Material) -> Result<Operators> {
    material.validate()?;
    let pattern = Pattern::from_mesh(mesh);
    let kind = mesh.kind;
    let nn = kind.n_nodes();
    let table = ReferenceTable::new(kind, &cube_rule(kind.volume_order()));
    // element matrices and where their entries go, in parallel; the sums in element order
    let locals: Vec<(ElementMatrices, Vec<usize>)> = (0..mesh.n_elements())
        .into_par_iter()
        .map(|e| {
            let local = element_matrices(&table, &mesh.element_coords(e), material)?;
            Ok((local, element_positions(&pattern, mesh.element(e))?))
        })
        .collect::<Result<_>>()?;
    let mut capacity = vec![0.0; pattern.nnz()];
    let mut conduction = vec![0.0; pattern.nnz()];
    let mut volume_m3 = 0.0;
    for (local, positions) in &locals {
        volume_m3 += local.volume;
        for ((&pos, c), k) in positions.iter().zip(&local.capacity).zip(&local.conduction) {
            capacity[pos] += c;
            conduction[pos] += k;
        }
    }
    let mut faces = Vec::with_capacity(mesh.face_sets.len());
    for set in &mesh.face_sets {
        let mut mass = vec![0.0; pattern.nnz()];
        let mut load = vec![0.0; mesh.n_nodes()];
        let mut area_m2 = 0.0;
        for &(e, f) in &set.faces {
            let conn = mesh.element(e);
            let (m, l, area) = face_matrices(kind, &mesh.element_coords(e), f);
            area_m2 += area;
            let face_nodes = kind.face_nodes(f);
            for &a in &face_nodes {
                load[conn[a]] += l[a];
                for &b in &face_nodes {
                    let pos = pattern.position(conn[a], conn[b]).ok_or_else(|| {
                        ThermalError::InvalidMesh("face entry missing from the pattern".into())
                    })?;
                    mass[pos] += m[a * nn + b];
                }
            }
        }
        faces.push(FaceOperator {
            name: set.name.clone(),
            mass,
            load,
            area_m2,
        });
    }
    Ok(Operators {
        pattern,
        capacity,
        conduction,
        faces,
        volume_m3,
    })
}

/// `∫_s N g(x, n) dA` over face set `name`, for a load `g` that varies over the face (x the
/// point, n the outward unit normal): non-uniform fluxes, and exact boundary data in tests.
pub fn face_load_fn(
    mesh: &Mesh,
    name: &str,
    g: impl Fn([f64; 3], [f64; 3]) -> f64,
) -> Result<Vec<f64>> {
    let set = mesh.face_set(name)?;
    let kind = mesh.kind;
    let nn = kind.n_nodes();
    let mut n = vec![0.0; nn];
    let mut dn = vec![[0.0; 3]; nn];
    let mut load = vec![0.0; mesh.n_nodes()];
    for &(e, f) in &set.faces {
        let coords = mesh.element_coords(e);
        let conn = mesh.element(e);
        let (axis, side, _) = FACE_CORNERS[f];
        let (u, v) = match axis {
            0 => (1, 2),
            1 => (0, 2),
            _ => (0, 1),
        };
        for (st, w) in square_rule(kind.volume_order() + 1) {
            let mut xi = [0.0; 3];
            xi[axis] = side;
            xi[u] = st[0];
            xi[v] = st[1];
            kind.shape(xi, &mut n);
            kind.grad(xi, &mut dn);
            let j = jacobian(&coords, &dn);
            let c = cross([j[0][u], j[1][u], j[2][u]], [j[0][v], j[1][v], j[2][v]]);
            let norm = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
            // t_u x t_v points along +axis for axes 0 and 2 and along -axis for axis 1
            // (right-handed reference cube); the outward normal points along `side`
            let along_plus = axis != 1;
            let sign = if along_plus == (side > 0.0) {
                1.0
            } else {
                -1.0
            };
            let normal = [sign * c[0] / norm, sign * c[1] / norm, sign * c[2] / norm];
            let mut x = [0.0; 3];
            for (a, p) in coords.iter().enumerate() {
                for d in 0..3 {
                    x[d] += n[a] * p[d];
                }
            }
            let value = g(x, normal) * w * norm;
            for a in 0..nn {
                load[conn[a]] += n[a] * value;
            }
        }
    }
    Ok(load)
}

/// `‖T_h − u‖_L2` of a nodal field against an exact function, by quadrature one order above
/// the element's.
pub fn l2_error(mesh: &Mesh, field: &[f64], exact: impl Fn([f64; 3]) -> f64) -> f64 {
    let kind = mesh.kind;
    let nn = kind.n_nodes();
    let rule = cube_rule(kind.volume_order() + 1);
    let mut n = vec![0.0; nn];
    let mut dn = vec![[0.0; 3]; nn];
    let mut sum = 0.0;
    for e in 0..mesh.n_elements() {
        let coords = mesh.element_coords(e);
        let conn = mesh.element(e);
        for (xi, w) in &rule {
            kind.shape(*xi, &mut n);
            kind.grad(*xi, &mut dn);
            let det = crate::element::det3(&jacobian(&coords, &dn));
            let mut x = [0.0; 3];
            let mut th = 0.0;
            for a in 0..nn {
                th += n[a] * field[conn[a]];
                for d in 0..3 {
                    x[d] += n[a] * coords[a][d];
                }
            }
            let diff = th - exact(x);
            sum += diff * diff * w * det;
        }
    }
    sum.sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{block_mesh, box_mesh};

    fn unit_material() -> Material {
        Material {
            conductivity_w_mk: 1.0,
            density_kg_m3: 1.0,
            specific_heat_j_kgk: 1.0,
        }
    }

    #[test]
    fn box_volume_areas_and_exact_quadratic_energy() {
        for kind in [ElementKind::Hex8, ElementKind::Hex20] {
            let m = box_mesh([0.3, 0.2, 0.1], [3, 2, 2], kind).unwrap();
            let ops = assemble(&m, &unit_material()).unwrap();
            assert!((ops.volume_m3 - 0.006).abs() < 1e-15);
            let ones = vec![1.0; m.n_nodes()];
            let mut y = vec![0.0; m.n_nodes()];
            ops.pattern.matvec(&ops.capacity, &ones, &mut y);
            assert!(
                (y.iter().sum::<f64>() - 0.006).abs() < 1e-15,
                "1ᵀM1 = volume"
            );
            ops.pattern.matvec(&ops.conduction, &ones, &mut y);
            assert!(y.iter().all(|v| v.abs() < 1e-12), "K 1 = 0");
            let x0 = &ops.faces[ops.face_index("x0").unwrap()];
            assert!((x0.area_m2 - 0.02).abs() < 1e-15);
            assert!((x0.load.iter().sum::<f64>() - 0.02).abs() < 1e-15);
            // T = x: Tᵀ K T = ∫ |∇T|² = volume
            let t: Vec<f64> = m.nodes.iter().map(|p| p[0]).collect();
            ops.pattern.matvec(&ops.conduction, &t, &mut y);
            let e: f64 = t.iter().zip(&y).map(|(a, b)| a * b).sum();
            assert!((e - 0.006).abs() < 1e-14, "{kind:?}: {e}");
        }
    }

    #[test]
    fn block_volume_and_friction_area_match_the_geometry() {
        let (g, m) = crate::mesh::coarse_block_mesh();
        let ops = assemble(&m, &Material::CAST_IRON).unwrap();
        let half = 0.5 * g.contact_angle_deg.to_radians();
        let r0 = g.wheel_radius_m;
        let r1 = r0 + g.body_thickness_m;
        let r2 = r1 + g.lug_height_m;
        let body = half * (r1 * r1 - r0 * r0) * g.block_width_m;
        let lug = 0.5 * g.lug_angle_deg.to_radians() * (r2 * r2 - r1 * r1) * g.lug_width_m;
        // quadratic edges approximate the arcs with an error O(dtheta^4): ~1e-9 here
        let rel = (ops.volume_m3 - body - lug).abs() / (body + lug);
        assert!(rel < 1e-7, "volume off by {rel:e}");
        let friction = &ops.faces[ops.face_index("friction").unwrap()];
        let a = r0 * 2.0 * half * g.block_width_m;
        assert!(
            (friction.area_m2 - a).abs() / a < 1e-7,
            "{} vs {a}",
            friction.area_m2
        );
    }

    #[test]
    fn the_lower_triangle_product_is_the_full_product() {
        // the default hex20 mesh: large enough for the two-thread product
        let (g, spec) = crate::model::default_block_spec(ElementKind::Hex20);
        let ops = assemble(&block_mesh(&g, &spec).unwrap(), &Material::CAST_IRON).unwrap();
        let lower = LowerPattern::new(&ops.pattern).unwrap();
        assert!(lower.row_idx.len() >= PARALLEL_MATVEC_MIN_NNZ);
        assert!(lower.middle > 0 && lower.middle < lower.n);
        // conduction plus a little capacity and convection: the stepper's kind of matrix
        let full = ops.pattern.combine(&[
            (1.0, &ops.conduction),
            (-0.3, &ops.capacity),
            (25.0, &ops.faces[0].mass),
        ]);
        let values = lower.values(&full);
        let x: Vec<f64> = (0..lower.n)
            .map(|i| ((i * 7919) % 101) as f64 / 10.0 - 5.0)
            .collect();
        let mut want = vec![0.0; lower.n];
        ops.pattern.matvec(&full, &x, &mut want);
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut got = vec![f64::NAN; lower.n];
            pool.install(|| lower.matvec(&values, &x, &mut got));
            let diff = got
                .iter()
                .zip(&want)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(diff <= 1e-12 * scale, "{threads} threads: {diff:e}");
        }
    }

    #[test]
    fn a_pattern_without_its_diagonal_is_refused() {
        let p = Pattern {
            n: 2,
            col_ptr: vec![0, 1, 2],
            row_idx: vec![1, 0],
        };
        let err = LowerPattern::new(&p).unwrap_err().to_string();
        assert!(err.contains("column 0"), "{err}");
    }
}
