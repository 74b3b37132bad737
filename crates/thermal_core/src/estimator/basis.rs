//! Dense transitions in their own basis: a symmetric propagator `A = Q diag(e) Qᵀ` stepped
//! as a diagonal one in the basis of its eigenvectors, with the reading's and the outputs'
//! rows in each basis (`Rows`) and the change of basis between consecutive steps
//! (`Rotation`).

use super::linalg::{dot, padded, transpose};
use super::problem::{Eigen, Problem, Transition};
use super::transition::{DenseF, Dims};

/// The reading's row, the outputs' rows and the gap's direction in one basis of the modal
/// coordinates: `q` (r x r row-major, its columns the basis vectors in the problem's
/// coordinates; empty: the problem's own basis). A row `c` on the modes is `Qᵀ c` in it.
pub(super) struct Rows {
    pub(super) r: usize,
    pub(super) q: Vec<f64>,
    pub(super) h: Vec<f64>,
    pub(super) cm: Vec<f64>,
    /// (m, r) row-major.
    pub(super) c_nodes: Vec<f64>,
    /// The face nodes' rows transposed (r x m, m padded to a multiple of 4): node values as a
    /// sum of r scaled rows.
    pub(super) cn_t: Vec<f64>,
    pub(super) gap_dir: Vec<f64>,
}

impl Rows {
    pub(super) fn new(p: &Problem<'_>, q: Vec<f64>) -> Self {
        let (r, n, m) = (p.order, p.n_state(), p.n_nodes());
        let mut h = vec![0.0; n];
        if p.lag {
            h[r + 1] = 1.0;
        } else {
            h[..r].copy_from_slice(&p.c_probe);
        }
        let mut rows = Rows {
            r,
            q,
            h,
            cm: p.c_mean.clone(),
            c_nodes: p.c_nodes.clone(),
            cn_t: Vec::new(),
            gap_dir: p.gap_dir.clone(),
        };
        if !rows.q.is_empty() {
            let mut tmp = vec![0.0; r];
            for v in [&mut rows.h, &mut rows.cm, &mut rows.gap_dir] {
                rotate_t(&rows.q, r, &mut v[..r], &mut tmp);
            }
            for c in rows.c_nodes.chunks_exact_mut(r) {
                rotate_t(&rows.q, r, c, &mut tmp);
            }
        }
        rows.cn_t = transpose(&rows.c_nodes, m, r, m.next_multiple_of(4));
        rows
    }

    #[inline(always)]
    pub(super) fn node_row(&self, j: usize) -> &[f64] {
        &self.c_nodes[j * self.r..(j + 1) * self.r]
    }
}

/// `v = Qᵀ v` (Q r x r row-major; `tmp`: r scratch).
pub(super) fn rotate_t(q: &[f64], r: usize, v: &mut [f64], tmp: &mut [f64]) {
    tmp.fill(0.0);
    for (row, &vi) in q.chunks_exact(r).zip(v.iter()) {
        for (t, &qij) in tmp.iter_mut().zip(row) {
            *t += qij * vi;
        }
    }
    v.copy_from_slice(tmp);
}

/// A dense transition as a diagonal one in the basis of its propagator's eigenvectors
/// (`tr.eigen`: `a = Q diag(e) Qᵀ` as its maker computed it; a Q that leaves a coordinate
/// alone, the seat's error, keeps its noise diagonal): Q (r x r row-major), the transition in
/// that basis (`e`, `Qᵀγ`, `Qᵀℓ`) and its mode noise `Qᵀ diag(q_modes) Q` when that is not
/// diagonal (r x r; empty: it is, and is the transition's `q_modes`). None where the
/// transition has no decomposition: it is then stepped dense (`DenseF`). (`Problem::validate`
/// checked its sizes and that it is finite.)
pub(super) fn in_own_basis(tr: &Transition, r: usize) -> Option<(Vec<f64>, Transition, Vec<f64>)> {
    let Eigen { q, e } = tr.eigen.as_ref()?;
    let mut tmp = vec![0.0; r];
    let mut out = tr.clone();
    out.diagonal = true;
    out.eigen = None;
    out.a = (0..r * r)
        .map(|ij| if ij / r == ij % r { e[ij / r] } else { 0.0 })
        .collect();
    out.e = e.clone();
    rotate_t(q, r, &mut out.gamma, &mut tmp);
    rotate_t(q, r, &mut out.lag_row, &mut tmp);
    let mut noise = Vec::new();
    if tr.q_modes.iter().any(|&v| v != 0.0) {
        // Qᵀ diag(q) Q
        let mut m = vec![0.0; r * r];
        for (k, &qk) in tr.q_modes.iter().enumerate().filter(|(_, v)| **v != 0.0) {
            let row = &q[k * r..(k + 1) * r];
            for i in 0..r {
                for j in 0..r {
                    m[i * r + j] += qk * row[i] * row[j];
                }
            }
        }
        let off = (0..r * r).any(|ij| ij / r != ij % r && m[ij] != 0.0);
        if off {
            out.q_modes = vec![0.0; r];
            noise = m;
        } else {
            out.q_modes = (0..r).map(|i| m[i * r + i]).collect();
        }
    }
    Some((q.clone(), out, noise))
}

/// `x[..r] = R x[..r]` (R r x r row-major; `tmp`: r scratch).
#[inline(always)]
pub(super) fn rotate_vec<const FMA: bool>(rm: &[f64], r: usize, x: &mut [f64], tmp: &mut [f64]) {
    for (t, row) in tmp.iter_mut().zip(rm.chunks_exact(r)) {
        *t = dot::<FMA>(row, &x[..r]);
    }
    x[..r].copy_from_slice(&tmp[..r]);
}

/// The change from one basis of the modal coordinates to another, `T = diag(R, I)` with
/// `R = Q_newᵀ Q_old` (r x r row-major), and `Rᵀ`; `f`: T for the covariance's products
/// (`T X Tᵀ` forwards, `Tᵀ Λ T` backwards, the blocked products of a dense transition).
pub(super) struct Rotation {
    pub(super) r: Vec<f64>,
    pub(super) rt: Vec<f64>,
    pub(super) f: DenseF,
}

impl Rotation {
    pub(super) fn new(rm: Vec<f64>, d: &Dims) -> Self {
        let (r, n, p) = (d.r, d.n, padded(d.n));
        let mut f = vec![0.0; p * p];
        let mut ft = vec![0.0; p * p];
        for i in 0..n {
            for j in 0..n {
                let v = match (i < r, j < r) {
                    (true, true) => rm[i * r + j],
                    (false, false) if i == j => 1.0,
                    _ => 0.0,
                };
                f[i * p + j] = v;
                ft[j * p + i] = v;
            }
        }
        Rotation {
            rt: transpose(&rm, r, r, r),
            r: rm,
            f: DenseF { f, ft },
        }
    }

    /// `out = T X Tᵀ` (out of line: it stays out of the code of the hot loops that call it).
    #[inline(never)]
    pub(super) fn forward_cov<const FMA: bool>(
        &self,
        d: &Dims,
        x: &[f64],
        out: &mut [f64],
        pad: &mut [Vec<f64>; 3],
    ) {
        self.f.predict_cov::<FMA>(d, x, out, pad, None);
    }

    /// `out = Tᵀ Λ T` (out of line).
    #[inline(never)]
    pub(super) fn back_cov<const FMA: bool>(
        &self,
        d: &Dims,
        l: &[f64],
        out: &mut [f64],
        pad: &mut [Vec<f64>; 3],
    ) {
        self.f.back_cov::<FMA>(d, l, &[], None, out, pad);
    }
}

#[cfg(test)]
mod tests {
    use crate::estimator::kernel::Kernel;
    use crate::estimator::run;
    use crate::estimator::testing::*;

    #[test]
    fn dense_transitions_stepped_in_their_own_basis_are_the_textbook_filter_and_smoother() {
        for lag in [false, true] {
            let p = dense_runs_problem(lag, 1600, 17);
            let k = Kernel::new(&p, NOISE, &settings(0.0, 64));
            // both dense transitions diagonal in bases of their own; the first one's mode
            // noise mixed by its basis (a dense noise), the second's not (the third
            // coordinate is its own)
            assert!(k.dense.iter().all(Option::is_none));
            assert_eq!(k.basis[0], 0);
            assert!(k.basis[1] != 0 && k.basis[3] != 0 && k.basis[1] != k.basis[3]);
            assert!(!k.noise_rot[1].is_empty() && k.noise_rot[3].is_empty());
            assert_eq!(k.trs[3].q_modes, vec![0.0, 0.0, 2e-4]);
            for pair in [
                (0, k.basis[1]),
                (k.basis[1], k.basis[3]),
                (k.basis[3], k.basis[1]),
            ] {
                assert!(k.rotations.contains_key(&pair), "{pair:?}");
            }
            let reference = naive(&p, NOISE);
            // without their decompositions the dense transitions are stepped dense, to the
            // same textbook results; one not finite or of the wrong size is an error
            let mut plain = p.clone();
            plain.transitions[1].eigen = None;
            plain.transitions[3].eigen = None;
            let mut bad = p.clone();
            bad.transitions[3].eigen.as_mut().unwrap().q[4] = f64::NAN;
            let err = run(&bad, NOISE, &settings(0.0, 64)).unwrap_err();
            assert!(err.to_string().contains("transition 3"), "{err}");
            bad.transitions[3].eigen.as_mut().unwrap().e.pop();
            let err = run(&bad, NOISE, &settings(0.0, 64)).unwrap_err();
            assert!(
                err.to_string().contains("eigenvalues of transition 3"),
                "{err}"
            );
            let k = Kernel::new(&plain, NOISE, &settings(0.0, 64));
            assert!(k.dense[1].is_some() && k.dense[3].is_some());
            assert!(k.basis.iter().all(|&b| b == 0) && k.rotations.is_empty());
            for q in [&p, &plain] {
                for (tol, block) in [(0.0, 64), (0.0, 1600), (1e-12, 128)] {
                    let out = run(q, NOISE, &settings(tol, block)).unwrap();
                    if tol > 0.0 {
                        assert!(out.frozen_steps > 300, "{} frozen", out.frozen_steps);
                    }
                    assert_textbook(&out, &reference);
                }
            }
        }
    }
}
