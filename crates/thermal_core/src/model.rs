//! The thermal model: mesh, operators, symbolic factorisation and a cache of numeric factors,
//! behind one object that simulates loadings.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use faer::Par;

use crate::assembly::{assemble, LowerPattern, Material, Operators};
use crate::error::{Result, ThermalError};
use crate::mesh::{block_mesh, BlockGeometry, BlockMeshSpec, Mesh};
use crate::probe::{build_probes, Probes};
use crate::solver::{relative_residual, CholeskyFactor, CholeskyKind, SymbolicAnalysis};
use crate::transient::{Initial, Loading, Outputs, Precision, Scheme};

/// Most numeric factors kept at once (each is the size of L).
const CACHE_CAPACITY: usize = 16;

/// A factorised step matrix `S = M/τ + K` with the stiffness `K = K_cond + Σ h_s H_s` its
/// steps' residuals need (stored negated), and `S 1` for the correction of their uniform
/// part. A theta step of `dt` solves with `θ S`, `τ = θ dt`: Crank–Nicolson's steps and the
/// backward-Euler half steps of its damped start (`τ = dt/2` both) share one factor.
#[derive(Debug)]
pub struct StepSystem {
    pub factor: CholeskyFactor,
    /// `−K`, its lower triangle (on [`ThermalModel::lower`]).
    pub neg_stiffness: Vec<f64>,
    /// `S 1` and its sum `1ᵀ S 1`.
    pub row_sums: Vec<f64>,
    pub total: f64,
    pub residual: f64,
}

type CacheKey = Vec<u64>;

/// The assembled model of one mesh and material.
#[derive(Debug)]
pub struct ThermalModel {
    pub mesh: Mesh,
    pub material: Material,
    pub ops: Operators,
    /// The pattern's lower triangle, for the steps' mat-vecs.
    pub lower: LowerPattern,
    pub analysis: SymbolicAnalysis,
    /// Face operator that takes the heat flux and whose mean and maximum are reported.
    pub flux_face: usize,
    /// Fill-reducing ordering in use: "amd" or "nested-dissection".
    pub ordering: &'static str,
    /// `M 1`: the heat capacity attached to each node (J/K).
    pub nodal_capacity: Vec<f64>,
    flux_face_nodes: Vec<usize>,
    cache: Mutex<HashMap<CacheKey, Arc<StepSystem>>>,
    par: Par,
}

impl ThermalModel {
    /// Assemble the model of a mesh; `flux_face` names the face set that takes the heat flux.
    pub fn new(
        mesh: Mesh,
        material: Material,
        cholesky: CholeskyKind,
        flux_face: &str,
    ) -> Result<Self> {
        let ops = assemble(&mesh, &material)?;
        let flux = ops.face_index(flux_face)?;
        // fill-reducing order: faer's AMD, or the mesher's nested dissection where it has
        // one, whichever leaves the smaller factor (the two analyses side by side)
        let (amd, nd) = rayon::join(
            || SymbolicAnalysis::new(&ops.pattern, cholesky),
            || {
                mesh.ordering
                    .as_deref()
                    .map(|order| {
                        SymbolicAnalysis::with_ordering(&ops.pattern, cholesky, Some(order))
                    })
                    .transpose()
            },
        );
        let (mut analysis, mut ordering) = (amd?, "amd");
        if let Some(nd) = nd? {
            if nd.factor_nnz() < analysis.factor_nnz() {
                analysis = nd;
                ordering = "nested-dissection";
            }
        }
        let mut nodal_capacity = vec![0.0; mesh.n_nodes()];
        ops.pattern.matvec(
            &ops.capacity,
            &vec![1.0; mesh.n_nodes()],
            &mut nodal_capacity,
        );
        let flux_face_nodes = mesh.face_set_nodes(flux_face)?;
        let threads = rayon::current_num_threads().max(1);
        Ok(ThermalModel {
            mesh,
            material,
            lower: LowerPattern::new(&ops.pattern)?,
            ops,
            analysis,
            flux_face: flux,
            ordering,
            nodal_capacity,
            flux_face_nodes,
            cache: Mutex::new(HashMap::new()),
            par: if threads > 1 {
                Par::rayon(threads)
            } else {
                Par::Seq
            },
        })
    }

    /// The reference block (or any other block geometry) meshed and assembled.
    pub fn block(
        geometry: &BlockGeometry,
        spec: &BlockMeshSpec,
        material: Material,
        cholesky: CholeskyKind,
    ) -> Result<Self> {
        ThermalModel::new(block_mesh(geometry, spec)?, material, cholesky, "friction")
    }

    pub fn n_nodes(&self) -> usize {
        self.mesh.n_nodes()
    }

    pub fn probes(&self, points: &[[f64; 3]]) -> Result<Probes> {
        build_probes(&self.mesh, points)
    }

    /// Area of the flux face (m²).
    pub fn flux_area_m2(&self) -> f64 {
        self.ops.faces[self.flux_face].area_m2
    }

    /// Number of numeric factors currently cached.
    pub fn cached_factorizations(&self) -> usize {
        self.cache.lock().map(|c| c.len()).unwrap_or(0)
    }

    /// The system matrix values `M/dt + θ (K_cond + Σ h_s H_s)`.
    pub fn system_values(&self, dt_s: f64, theta: f64, h_by_face: &[f64]) -> Vec<f64> {
        let mut terms: Vec<(f64, &[f64])> = vec![
            (1.0 / dt_s, &self.ops.capacity),
            (theta, &self.ops.conduction),
        ];
        for (face, h) in self.ops.faces.iter().zip(h_by_face) {
            terms.push((theta * h, &face.mass));
        }
        self.ops.pattern.combine(&terms)
    }

    /// The factorised step system `M/τ + K` for (τ, h per face operator), from the cache or
    /// built and checked (‖Ax − b‖/‖b‖ on a probe vector; refactorised sequentially if the
    /// parallel factor fails the check).
    pub fn step_system(&self, tau_s: f64, h_by_face: &[f64]) -> Result<(Arc<StepSystem>, bool)> {
        let mut key: CacheKey = vec![tau_s.to_bits()];
        key.extend(h_by_face.iter().map(|h| h.to_bits()));
        if let Some(sys) = self.cache.lock().ok().and_then(|c| c.get(&key).cloned()) {
            return Ok((sys, false));
        }
        let values = self.system_values(tau_s, 1.0, h_by_face);
        let (factor, residual) = self.factorize_checked(&values)?;
        let mut row_sums = vec![0.0; self.n_nodes()];
        self.ops
            .pattern
            .matvec(&values, &vec![1.0; self.n_nodes()], &mut row_sums);
        let sys = Arc::new(StepSystem {
            factor,
            neg_stiffness: self
                .lower
                .values(&self.system_values(f64::INFINITY, -1.0, h_by_face)),
            total: row_sums.iter().sum(),
            row_sums,
            residual,
        });
        if let Ok(mut cache) = self.cache.lock() {
            if cache.len() >= CACHE_CAPACITY {
                cache.clear();
            }
            cache.insert(key, sys.clone());
        }
        Ok((sys, true))
    }

    /// Solve `(s M + K_cond + Σ_s h_s H_s) X = B` for the columns of `rhs` (column-major,
    /// n rows), with the factor cached like a step system's (`s` = 1/dt, θ = 1). `s` = 0 is
    /// the steady operator, definite when some face has h > 0.
    pub fn solve_shifted(&self, shift: f64, h_by_face: &[f64], rhs: &mut [f64]) -> Result<()> {
        crate::error::check_non_negative("shift", shift)?;
        if h_by_face.len() != self.ops.faces.len() {
            return Err(ThermalError::LengthMismatch {
                name: "h_by_face".into(),
                expected: self.ops.faces.len(),
                got: h_by_face.len(),
            });
        }
        let n = self.n_nodes();
        if n == 0 || rhs.len() % n != 0 {
            return Err(ThermalError::LengthMismatch {
                name: "right-hand sides".into(),
                expected: n,
                got: rhs.len(),
            });
        }
        let dt = if shift == 0.0 {
            f64::INFINITY
        } else {
            1.0 / shift
        };
        let (sys, _) = self.step_system(dt, h_by_face)?;
        let k = rhs.len() / n;
        let mut scratch = sys.factor.scratch(k);
        sys.factor.solve_mat_in_place(
            faer::MatMut::from_column_major_slice_mut(rhs, n, k),
            &mut scratch,
        );
        Ok(())
    }

    /// `y = (a_m M + a_k K_cond + Σ_s h_s H_s) x` for the columns of `x` (column-major).
    pub fn apply(&self, a_m: f64, a_k: f64, h_by_face: &[f64], x: &[f64]) -> Result<Vec<f64>> {
        let n = self.n_nodes();
        if h_by_face.len() != self.ops.faces.len() || n == 0 || x.len() % n != 0 {
            return Err(ThermalError::LengthMismatch {
                name: "apply arguments".into(),
                expected: n,
                got: x.len(),
            });
        }
        let mut terms: Vec<(f64, &[f64])> =
            vec![(a_m, &self.ops.capacity), (a_k, &self.ops.conduction)];
        for (face, h) in self.ops.faces.iter().zip(h_by_face) {
            terms.push((*h, &face.mass));
        }
        let values = self.ops.pattern.combine(&terms);
        let mut y = vec![0.0; x.len()];
        for (xc, yc) in x.chunks(n).zip(y.chunks_mut(n)) {
            self.ops.pattern.matvec(&values, xc, yc);
        }
        Ok(y)
    }

    /// Factorise and verify with one solve; returns the factor and its relative residual.
    pub fn factorize_checked(&self, values: &[f64]) -> Result<(CholeskyFactor, f64)> {
        let pattern = &self.ops.pattern;
        let n = pattern.n;
        let x_true: Vec<f64> = (0..n)
            .map(|i| 1.0 + ((i * 7919) % 101) as f64 / 101.0)
            .collect();
        let mut b = vec![0.0; n];
        pattern.matvec(values, &x_true, &mut b);
        let check = |factor: &CholeskyFactor| {
            let mut x = b.clone();
            let mut scratch = factor.scratch(1);
            factor.solve_in_place(&mut x, &mut scratch);
            relative_residual(pattern, values, &x, &b)
        };
        let factor = self.analysis.factorize(pattern, values, self.par)?;
        let residual = check(&factor);
        if residual <= 1e-10 {
            return Ok((factor, residual));
        }
        let factor = self.analysis.factorize(pattern, values, Par::Seq)?;
        let residual = check(&factor);
        if residual <= 1e-10 {
            Ok((factor, residual))
        } else {
            Err(ThermalError::LinearAlgebra(format!(
                "Cholesky factor fails its residual check: ||Ax-b||/||b|| = {residual:e}"
            )))
        }
    }

    /// Run a loading from its initial state; probe values, flux-face mean and maximum at every
    /// step, fields every `field_every` steps (0: none), and the energy ledger.
    pub fn simulate(
        &self,
        loading: &Loading,
        scheme: Scheme,
        probes: &Probes,
        field_every: usize,
    ) -> Result<Outputs> {
        scheme.validate()?;
        let n = self.n_nodes();
        let n_faces = self.ops.faces.len();
        loading.validate(n, n_faces)?;
        let mut t: Vec<f64> = match loading.initial {
            Initial::Uniform(v) => vec![v; n],
            Initial::Field(f) => f.to_vec(),
        };
        let t0 = t.clone();
        let n_out = loading.n_steps + 1;
        let mut out = Outputs {
            time_s: (0..n_out).map(|k| k as f64 * loading.dt_s).collect(),
            probe_c: Vec::with_capacity(n_out * probes.len()),
            n_probes: probes.len(),
            face_mean_c: Vec::with_capacity(n_out),
            face_max_c: Vec::with_capacity(n_out),
            ..Default::default()
        };
        let flux_op = &self.ops.faces[self.flux_face];
        let flux_area = flux_op.area_m2;
        // face loads touch only their face's nodes: sparse, for the per-step products
        let loads: Vec<SparseLoad> = self
            .ops
            .faces
            .iter()
            .map(|f| SparseLoad::new(&f.load))
            .collect();
        let flux_load = &loads[self.flux_face];
        let record = |out: &mut Outputs, t: &[f64], step: usize| {
            let start = out.probe_c.len();
            out.probe_c.resize(start + probes.len(), 0.0);
            probes.interpolate(t, &mut out.probe_c[start..]);
            let mean = flux_load.dot(t) / flux_area;
            out.face_mean_c.push(mean);
            let max = self
                .flux_face_nodes
                .iter()
                .map(|&i| t[i])
                .fold(f64::NEG_INFINITY, f64::max);
            out.face_max_c.push(max);
            if field_every > 0 && step % field_every == 0 {
                out.fields_c.extend_from_slice(t);
                out.field_steps.push(step);
            }
        };
        record(&mut out, &t, 0);
        let mut h = vec![0.0; n_faces];
        let mut delta = vec![0.0; n];
        let mut scratch = None;
        let damped_mask = scheme.damped_mask(loading);
        let stepping_start = Instant::now();
        let mut seconds_factorization = 0.0;
        for (step, &damped) in damped_mask.iter().enumerate() {
            h.iter_mut().for_each(|v| *v = 0.0);
            for c in &loading.convection {
                h[c.face] += c.h_w_m2k.at(step);
            }
            let q = loading.flux_w_m2.at(step);
            let t_amb = loading.ambient_c.at(step);
            let (substeps, dt, theta) = if damped {
                (2, 0.5 * loading.dt_s, 1.0)
            } else {
                (1, loading.dt_s, scheme.theta)
            };
            let fetch_start = Instant::now();
            let (sys, built) = self.step_system(theta * dt, &h)?;
            if built {
                out.factorizations += 1;
                seconds_factorization += fetch_start.elapsed().as_secs_f64();
            }
            let scratch = scratch.get_or_insert_with(|| sys.factor.scratch(1));
            for _ in 0..substeps {
                // convected heat uses G_s · T_theta with G_s = H_s 1
                let g_old: Vec<f64> = loads.iter().map(|l| l.dot(&t)).collect();
                // the residual f − K T_n, then the increment
                self.lower.matvec(&sys.neg_stiffness, &t, &mut delta);
                if q != 0.0 {
                    flux_load.add_to(q, &mut delta);
                }
                for (load, hs) in loads.iter().zip(&h) {
                    if *hs != 0.0 {
                        load.add_to(hs * t_amb, &mut delta);
                    }
                }
                // θ S ΔT = r: solve S ΔT = r / θ
                let inv_theta = 1.0 / theta;
                delta.iter_mut().for_each(|v| *v *= inv_theta);
                let balance: f64 = delta.iter().sum();
                match scheme.precision {
                    Precision::Double => sys.factor.solve_in_place(&mut delta, scratch),
                    Precision::Mixed => sys.factor.solve_in_place_mixed(&mut delta, scratch),
                }
                // the uniform shift that makes 1ᵀ S ΔT = 1ᵀ (f − K T_n) / θ exact
                let solved: f64 = sys.row_sums.iter().zip(&delta).map(|(a, d)| a * d).sum();
                let shift = (balance - solved) / sys.total;
                for (ti, di) in t.iter_mut().zip(&delta) {
                    *ti += di + shift;
                }
                out.energy.flux_in_j += dt * q * flux_area;
                for (((face, load), hs), go) in
                    self.ops.faces.iter().zip(&loads).zip(&h).zip(&g_old)
                {
                    if *hs != 0.0 {
                        let g_new = load.dot(&t);
                        let g_theta = theta * g_new + (1.0 - theta) * go;
                        out.energy.convected_out_j += dt * hs * (g_theta - t_amb * face.area_m2);
                    }
                }
            }
            record(&mut out, &t, step + 1);
        }
        out.energy.stored_j = self
            .nodal_capacity
            .iter()
            .zip(t.iter().zip(&t0))
            .map(|(c, (a, b))| c * (a - b))
            .sum();
        out.seconds_factorization = seconds_factorization;
        out.seconds_stepping = stepping_start.elapsed().as_secs_f64() - seconds_factorization;
        out.final_c = t;
        Ok(out)
    }
}

/// A nodal load vector by its nonzero entries.
struct SparseLoad {
    index: Vec<usize>,
    value: Vec<f64>,
}

impl SparseLoad {
    fn new(dense: &[f64]) -> Self {
        let (index, value) = dense
            .iter()
            .enumerate()
            .filter(|(_, v)| **v != 0.0)
            .map(|(i, v)| (i, *v))
            .unzip();
        SparseLoad { index, value }
    }

    /// `loadᵀ x`.
    fn dot(&self, x: &[f64]) -> f64 {
        self.index
            .iter()
            .zip(&self.value)
            .map(|(&i, g)| g * x[i])
            .sum()
    }

    /// `y += c load`.
    fn add_to(&self, c: f64, y: &mut [f64]) {
        for (&i, g) in self.index.iter().zip(&self.value) {
            y[i] += c * g;
        }
    }
}

/// The reference block and its default mesh (graded towards the friction face and the
/// sensor seat).
pub fn default_block_spec(kind: crate::element::ElementKind) -> (BlockGeometry, BlockMeshSpec) {
    let geometry = BlockGeometry::default();
    let spec = BlockMeshSpec {
        kind,
        focus_m: Some([0.0, geometry.wheel_radius_m + 0.055, 0.0]),
        ..Default::default()
    };
    (geometry, spec)
}

/// Build the default block model.
pub fn default_block_model(kind: crate::element::ElementKind) -> Result<ThermalModel> {
    let (geometry, spec) = default_block_spec(kind);
    ThermalModel::block(&geometry, &spec, Material::CAST_IRON, CholeskyKind::Auto)
}

/// The convection of the benchmarks and tests: `h_w_m2k` on every face set but the friction
/// face.
pub fn convection_off_friction(model: &ThermalModel, h_w_m2k: f64) -> Vec<f64> {
    model
        .ops
        .faces
        .iter()
        .map(|f| if f.name == "friction" { 0.0 } else { h_w_m2k })
        .collect()
}
