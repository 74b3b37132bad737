//! Sparse Cholesky factorisation with faer: symbolic analysis (AMD ordering, simplicial or
//! supernodal) once per pattern, numeric factorisation once per matrix, solves reused.

use std::sync::{Arc, OnceLock};

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltParams;
use faer::mat::MatMut;
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, LltRef, SymbolicCholesky,
    SymbolicCholeskyRaw, SymmetricOrdering,
};
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, Par, Side, Spec};

use crate::assembly::Pattern;
use crate::error::{Result, ThermalError};
use crate::trisolve::{FactorValue, SupernodePlan};

/// Which Cholesky variant faer uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CholeskyKind {
    /// faer decides from the flop count of the symbolic analysis.
    Auto,
    /// Column by column (sparse triangular solves, no dense blocks).
    Simplicial,
    /// Dense supernodes (BLAS-3 kernels).
    Supernodal,
}

impl CholeskyKind {
    pub fn from_name(name: &str) -> Option<Self> {
        match name.to_ascii_lowercase().as_str() {
            "auto" => Some(CholeskyKind::Auto),
            "simplicial" => Some(CholeskyKind::Simplicial),
            "supernodal" => Some(CholeskyKind::Supernodal),
            _ => None,
        }
    }
}

/// The symbolic factorisation of a pattern (ordering, elimination tree, structure of L).
#[derive(Debug, Clone)]
pub struct SymbolicAnalysis {
    symbolic: Arc<SymbolicCholesky<usize>>,
    /// The layout the one-right-hand-side solves stream (supernodal factors only).
    plan: Option<Arc<SupernodePlan>>,
}

impl SymbolicAnalysis {
    /// Symbolic factorisation with faer's AMD ordering.
    pub fn new(pattern: &Pattern, kind: CholeskyKind) -> Result<Self> {
        SymbolicAnalysis::with_ordering(pattern, kind, None)
    }

    /// Symbolic factorisation with a given elimination order (`order[k]` = the node
    /// eliminated k-th), or AMD when `None`.
    pub fn with_ordering(
        pattern: &Pattern,
        kind: CholeskyKind,
        order: Option<&[usize]>,
    ) -> Result<Self> {
        let threshold = match kind {
            CholeskyKind::Auto => SupernodalThreshold::AUTO,
            CholeskyKind::Simplicial => SupernodalThreshold::FORCE_SIMPLICIAL,
            CholeskyKind::Supernodal => SupernodalThreshold::FORCE_SUPERNODAL,
        };
        let structure = symbolic_view(pattern)?;
        let inverse: Vec<usize>;
        let ordering = match order {
            None => SymmetricOrdering::Amd,
            Some(fwd) => {
                let n = pattern.n;
                let mut inv = vec![usize::MAX; n];
                for (k, &i) in fwd.iter().enumerate() {
                    if i >= n || inv[i] != usize::MAX {
                        return Err(ThermalError::LinearAlgebra(
                            "ordering is not a permutation".into(),
                        ));
                    }
                    inv[i] = k;
                }
                if fwd.len() != n {
                    return Err(ThermalError::LinearAlgebra(
                        "ordering is not a permutation".into(),
                    ));
                }
                inverse = inv;
                SymmetricOrdering::Custom(PermRef::new_checked(fwd, &inverse, n))
            }
        };
        let symbolic = factorize_symbolic_cholesky(
            structure,
            Side::Lower,
            ordering,
            CholeskySymbolicParams {
                supernodal_flop_ratio_threshold: threshold,
                ..Default::default()
            },
        )
        .map_err(|e| ThermalError::LinearAlgebra(format!("symbolic Cholesky: {e:?}")))?;
        let plan = match symbolic.raw() {
            SymbolicCholeskyRaw::Supernodal(sn) => Some(Arc::new(SupernodePlan::new(sn))),
            SymbolicCholeskyRaw::Simplicial(_) => None,
        };
        Ok(SymbolicAnalysis {
            symbolic: Arc::new(symbolic),
            plan,
        })
    }

    /// Stored entries of the factor L.
    pub fn factor_nnz(&self) -> usize {
        self.symbolic.len_val()
    }

    /// Whether faer chose (or was told) the supernodal variant.
    pub fn is_supernodal(&self) -> bool {
        matches!(self.symbolic.raw(), SymbolicCholeskyRaw::Supernodal(_))
    }

    /// Numeric factorisation of the matrix with these values on `pattern`.
    pub fn factorize(&self, pattern: &Pattern, values: &[f64], par: Par) -> Result<CholeskyFactor> {
        if values.len() != pattern.nnz() {
            return Err(ThermalError::LengthMismatch {
                name: "matrix values".into(),
                expected: pattern.nnz(),
                got: values.len(),
            });
        }
        if let Some(bad) = values.iter().find(|v| !v.is_finite()) {
            return Err(ThermalError::NotPositiveDefinite(format!(
                "matrix holds {bad}"
            )));
        }
        let structure = symbolic_view(pattern)?;
        let matrix = SparseColMatRef::new(structure, values);
        let mut l_values = vec![0.0f64; self.symbolic.len_val()];
        let mut buffer = MemBuffer::new(
            self.symbolic
                .factorize_numeric_llt_scratch::<f64>(par, Spec::<LltParams, f64>::default()),
        );
        self.symbolic
            .factorize_numeric_llt(
                &mut l_values,
                matrix,
                Side::Lower,
                Default::default(),
                par,
                MemStack::new(&mut buffer),
                Spec::<LltParams, f64>::default(),
            )
            .map_err(|e| ThermalError::NotPositiveDefinite(format!("{e:?}")))?;
        Ok(CholeskyFactor {
            symbolic: self.symbolic.clone(),
            plan: self.plan.clone(),
            values: l_values,
            single: OnceLock::new(),
        })
    }
}

/// A view of the pattern for faer. `Pattern` is built sorted and in range, which is what
/// `new_checked` verifies.
fn symbolic_view(pattern: &Pattern) -> Result<SymbolicSparseColMatRef<'_, usize>> {
    if pattern.col_ptr.len() != pattern.n + 1
        || pattern.col_ptr.last() != Some(&pattern.row_idx.len())
    {
        return Err(ThermalError::LinearAlgebra(
            "inconsistent sparsity pattern".into(),
        ));
    }
    Ok(SymbolicSparseColMatRef::new_checked(
        pattern.n,
        pattern.n,
        &pattern.col_ptr,
        None,
        &pattern.row_idx,
    ))
}

/// Factors with fewer values are solved on one thread.
const PARALLEL_SOLVE_MIN_VALUES: usize = 4_000_000;

/// A numeric Cholesky factor `A = L Lᵀ` (with its fill-reducing permutation).
#[derive(Debug, Clone)]
pub struct CholeskyFactor {
    symbolic: Arc<SymbolicCholesky<usize>>,
    plan: Option<Arc<SupernodePlan>>,
    values: Vec<f64>,
    /// The values rounded to single precision, made on the first mixed-precision solve.
    single: OnceLock<Vec<f32>>,
}

impl CholeskyFactor {
    pub fn n(&self) -> usize {
        self.symbolic.nrows()
    }

    /// Scratch a solve with `ncols` right-hand sides needs.
    pub fn scratch(&self, ncols: usize) -> MemBuffer {
        MemBuffer::new(self.symbolic.solve_in_place_scratch::<f64>(ncols, Par::Seq))
    }

    /// Solve `A X = B` in place for the columns of `rhs`.
    pub fn solve_mat_in_place(&self, rhs: MatMut<'_, f64>, scratch: &mut MemBuffer) {
        self.solve_mat_in_place_par(rhs, scratch, Par::Seq);
    }

    /// Solve `A X = B` in place, letting faer use `par` threads inside the solve.
    pub fn solve_mat_in_place_par(&self, rhs: MatMut<'_, f64>, scratch: &mut MemBuffer, par: Par) {
        let llt = LltRef::<'_, usize, f64>::new(&self.symbolic, &self.values);
        llt.solve_in_place_with_conj(Conj::No, rhs, par, MemStack::new(scratch));
    }

    /// Scratch for a solve with `ncols` right-hand sides using `par` threads.
    pub fn scratch_par(&self, ncols: usize, par: Par) -> MemBuffer {
        MemBuffer::new(self.symbolic.solve_in_place_scratch::<f64>(ncols, par))
    }

    /// Solve `A x = b` in place for one right-hand side: with a supernodal factor by the
    /// streaming kernels of [`crate::trisolve`], else by faer.
    pub fn solve_in_place(&self, rhs: &mut [f64], scratch: &mut MemBuffer) {
        match &self.plan {
            Some(plan) => self.solve_streaming(plan, &self.values, rhs),
            None => self.solve_in_place_faer(rhs, scratch),
        }
    }

    /// Solve `A x = b` in place with the factor's values rounded to single precision
    /// (accumulating in double): half the memory traffic of [`Self::solve_in_place`], a
    /// relative error of order 1e-7 times the condition of the scaled matrix. Meant for
    /// corrections whose size is small against the solution (the time stepper's
    /// increments). A simplicial factor is solved in double precision by faer.
    pub fn solve_in_place_mixed(&self, rhs: &mut [f64], scratch: &mut MemBuffer) {
        match &self.plan {
            Some(plan) => {
                let single = self
                    .single
                    .get_or_init(|| self.values.iter().map(|&v| v as f32).collect());
                self.solve_streaming(plan, single, rhs);
            }
            None => self.solve_in_place_faer(rhs, scratch),
        }
    }

    /// faer's own solve for one right-hand side (the reference the streaming one is
    /// tested and benchmarked against).
    pub fn solve_in_place_faer(&self, rhs: &mut [f64], scratch: &mut MemBuffer) {
        let n = rhs.len();
        let view = MatMut::from_column_major_slice_mut(rhs, n, 1);
        self.solve_mat_in_place(view, scratch);
    }

    /// The streaming solve's layout, when the factor is supernodal.
    pub fn plan(&self) -> Option<&SupernodePlan> {
        self.plan.as_deref()
    }

    /// The supernodal structure and values, when the factor is supernodal.
    pub fn supernodal_parts(
        &self,
    ) -> Option<(
        &faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky<usize>,
        &[f64],
    )> {
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Supernodal(sn) => Some((sn, &self.values)),
            SymbolicCholeskyRaw::Simplicial(_) => None,
        }
    }

    fn solve_streaming<V: FactorValue>(&self, plan: &SupernodePlan, values: &[V], rhs: &mut [f64]) {
        // two threads where the tree splits in two, rayon has them and the factor is too
        // large for the caches (below that the join costs more than it saves)
        let parallel =
            rayon::current_num_threads() > 1 && values.len() >= PARALLEL_SOLVE_MIN_VALUES;
        match self.symbolic.perm() {
            Some(perm) => {
                let (fwd, inv) = perm.arrays();
                let mut x: Vec<f64> = fwd.iter().map(|&i| rhs[i]).collect();
                plan.solve_permuted(values, &mut x, parallel);
                for (r, &i) in rhs.iter_mut().zip(inv) {
                    *r = x[i];
                }
            }
            None => plan.solve_permuted(values, rhs, parallel),
        }
    }
}

/// Relative residual ‖A x − b‖ / ‖b‖.
pub fn relative_residual(pattern: &Pattern, values: &[f64], x: &[f64], b: &[f64]) -> f64 {
    let mut ax = vec![0.0; x.len()];
    pattern.matvec(values, x, &mut ax);
    let num: f64 = ax
        .iter()
        .zip(b)
        .map(|(p, q)| (p - q) * (p - q))
        .sum::<f64>()
        .sqrt();
    let den: f64 = b.iter().map(|v| v * v).sum::<f64>().sqrt();
    if den == 0.0 {
        num
    } else {
        num / den
    }
}
