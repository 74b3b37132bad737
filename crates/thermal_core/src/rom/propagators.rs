//! Propagators of a reduced model in modal coordinates, one per distinct step system, and one
//! run through them from a given state.

use super::basis_run::{transpose_times, BasisRun, MODAL};
use crate::error::{Result, ThermalError};

/// Propagators of a reduced model in modal coordinates ξ, one per distinct step system
/// (time step, scheme, convection): `ξ ← Q [e ⊙ (Qᵀ ξ) + g ⊙ (Qᵀ u)]`, `Q` the eigenbasis of
/// the reduced operator at that convection (the identity for the nominal one, whose modes
/// are the coordinates themselves).
#[derive(Debug, Clone, PartialEq)]
pub struct Propagators {
    pub(super) order: usize,
    /// (K, r) each.
    pub(super) e: Vec<f64>,
    pub(super) g: Vec<f64>,
    /// (K, r, r) row-major, `q[(k r + i) r + j] = Q_k[i, j]`; ignored where not `rotated`.
    pub(super) q: Vec<f64>,
    pub(super) rotated: Vec<bool>,
}

impl Propagators {
    pub fn new(
        order: usize,
        e: Vec<f64>,
        g: Vec<f64>,
        q: Vec<f64>,
        rotated: Vec<bool>,
    ) -> Result<Self> {
        let k = rotated.len();
        for (name, len, expected) in [
            ("propagator e", e.len(), k * order),
            ("propagator g", g.len(), k * order),
            ("propagator Q", q.len(), k * order * order),
        ] {
            if len != expected || order == 0 {
                return Err(ThermalError::LengthMismatch {
                    name: name.into(),
                    expected,
                    got: len,
                });
            }
        }
        Ok(Propagators {
            order,
            e,
            g,
            q,
            rotated,
        })
    }

    pub fn len(&self) -> usize {
        self.rotated.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rotated.is_empty()
    }

    /// Propagator `k`'s `e` and `g` (r each).
    pub(super) fn rates(&self, k: usize) -> (&[f64], &[f64]) {
        let r = self.order;
        (&self.e[k * r..(k + 1) * r], &self.g[k * r..(k + 1) * r])
    }

    /// Propagator `k`'s eigenbasis `Q` (r, r) row-major (meaningful where `rotated`).
    pub(super) fn basis_matrix(&self, k: usize) -> &[f64] {
        let r = self.order;
        &self.q[k * r * r..(k + 1) * r * r]
    }

    /// One run from `xi0` (length r): step `s` applies propagator `index[s]` `repeats[s]`
    /// times under the modal input `u[s]` (row-major (S, r)); after each step the outputs
    /// `C ξ` (`c` row-major (n_out, r)). Returns (outputs (S+1, n_out), final ξ).
    pub fn simulate(
        &self,
        index: &[usize],
        repeats: &[u32],
        u: &[f64],
        xi0: &[f64],
        c: &[f64],
    ) -> Result<(Vec<f64>, Vec<f64>)> {
        let r = self.order;
        let s = index.len();
        for (name, len, expected) in [
            ("repeats", repeats.len(), s),
            ("modal input", u.len(), s * r),
            ("initial state", xi0.len(), r),
        ] {
            if len != expected {
                return Err(ThermalError::LengthMismatch {
                    name: name.into(),
                    expected,
                    got: len,
                });
            }
        }
        if c.is_empty() || c.len() % r != 0 {
            return Err(ThermalError::LengthMismatch {
                name: "output rows".into(),
                expected: r,
                got: c.len(),
            });
        }
        if let Some(&bad) = index.iter().find(|&&k| k >= self.len()) {
            return Err(ThermalError::InvalidParameter {
                name: "propagator index".into(),
                value: bad as f64,
                reason: format!("only {} propagators", self.len()),
            });
        }
        let n_out = c.len() / r;
        let mut y = vec![0.0; (s + 1) * n_out];
        let mut run = BasisRun::new(self, Vec::new(), c);
        run.start(xi0);
        run.outputs();
        y[..n_out].copy_from_slice(&run.y[..n_out]);
        for step in 0..s {
            let k = index[step];
            run.enter(k);
            let uk = &u[step * r..(step + 1) * r];
            if run.at == MODAL {
                run.u.copy_from_slice(uk);
            } else {
                transpose_times(self.basis_matrix(k), uk, &mut run.u);
            }
            let (e, g) = self.rates(k);
            for _ in 0..repeats[step] {
                for (((w, &ei), &gi), &ui) in run.w.iter_mut().zip(e).zip(g).zip(&run.u) {
                    *w = ei * *w + gi * ui;
                }
            }
            run.outputs();
            y[(step + 1) * n_out..(step + 2) * n_out].copy_from_slice(&run.y[..n_out]);
        }
        let mut xi = vec![0.0; r];
        run.state(&mut xi);
        Ok((y, xi))
    }
}

#[cfg(test)]
// the reference implementations index as the textbook writes them
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use crate::rom::testing::*;

    #[test]
    fn a_switched_run_kept_in_its_rotated_bases_equals_stepping_by_the_formula() {
        let props = switching_propagators();
        let r = 4;
        let c = [1.0, 0.6, 0.3, -0.2, 0.9, 0.4, 0.1, 0.2, 1.1, 0.8, -0.3, 0.5];
        let s = 60;
        let index: Vec<usize> = (0..s)
            .map(|k| [1, 1, 2, 0, 0, 2, 2, 5, 3, 1][(k / 2) % 10])
            .collect();
        let repeats: Vec<u32> = (0..s).map(|k| 1 + (k % 3) as u32).collect();
        let u: Vec<f64> = (0..s * r).map(|k| ((k * 13) % 7) as f64 - 2.5).collect();
        let xi0 = [3.0, -1.0, 0.5, 2.0];
        let (y, xi) = props.simulate(&index, &repeats, &u, &xi0, &c).unwrap();
        let mut x = xi0.to_vec();
        let (mut w, mut v) = (vec![0.0; r], vec![0.0; r]);
        let outputs = |x: &[f64]| -> Vec<f64> {
            c.chunks_exact(r)
                .map(|row| row.iter().zip(x).map(|(a, b)| a * b).sum())
                .collect()
        };
        let mut expected = outputs(&x);
        for k in 0..s {
            for _ in 0..repeats[k] {
                apply_step_by_step(
                    &props,
                    index[k],
                    &mut x,
                    &u[k * r..(k + 1) * r],
                    &mut w,
                    &mut v,
                );
            }
            expected.extend(outputs(&x));
        }
        assert!(max_difference(&y, &expected) <= 1e-10);
        assert!(max_difference(&xi, &x) <= 1e-10);
        assert!(x.iter().any(|v| v.abs() > 1.0));
    }

    #[test]
    fn a_rotated_propagator_is_its_matrix_exponential() {
        // two modes coupled by a symmetric operator A = Q diag(λ) Qᵀ; exact step for held u:
        // ξ ← Q [e ⊙ Qᵀξ + g ⊙ Qᵀu]; checked against the nominal (unrotated) form in Q's basis
        let (c30, s30) = (3f64.sqrt() / 2.0, 0.5);
        let q = vec![c30, -s30, s30, c30];
        let (lam, dt) = ([0.1, 0.7], 1.0);
        let e: Vec<f64> = lam.iter().map(|l: &f64| (-l * dt).exp()).collect();
        let g: Vec<f64> = lam.iter().map(|l: &f64| -(-l * dt).exp_m1() / l).collect();
        let rotated = Propagators::new(2, e.clone(), g.clone(), q.clone(), vec![true]).unwrap();
        let plain = Propagators::new(2, e, g, vec![0.0; 4], vec![false]).unwrap();
        let to_q = |x: &[f64]| vec![q[0] * x[0] + q[2] * x[1], q[1] * x[0] + q[3] * x[1]];
        let n = 20;
        let u: Vec<f64> = (0..2 * n).map(|k| ((k * 7) % 5) as f64 - 2.0).collect();
        let uq: Vec<f64> = u.chunks(2).flat_map(to_q).collect();
        let xi0 = [1.0, -0.5];
        let c = vec![1.0, 0.0, 0.0, 1.0];
        let (ya, xa) = rotated
            .simulate(&vec![0; n], &vec![1; n], &u, &xi0, &c)
            .unwrap();
        let (_, xb) = plain
            .simulate(&vec![0; n], &vec![1; n], &uq, &to_q(&xi0), &c)
            .unwrap();
        let back = [q[0] * xb[0] + q[1] * xb[1], q[2] * xb[0] + q[3] * xb[1]];
        assert!((xa[0] - back[0]).abs() < 1e-12 && (xa[1] - back[1]).abs() < 1e-12);
        assert_eq!(ya.len(), (n + 1) * 2);
        assert_eq!(&ya[2 * n..], &xa[..]);
        // repeats apply the step again; a bad index is an error, not a panic
        let (_, twice) = plain
            .simulate(&[0], &[2], &uq[..2], &[0.0, 0.0], &c)
            .unwrap();
        let (_, one) = plain
            .simulate(
                &[0, 0],
                &[1, 1],
                &[uq[0], uq[1], uq[0], uq[1]],
                &[0.0, 0.0],
                &c,
            )
            .unwrap();
        assert_eq!(twice, one);
        assert!(plain
            .simulate(&[1], &[1], &uq[..2], &[0.0, 0.0], &c)
            .is_err());
    }
}
