//! Time stepping of a reduced model in modal form, for many events at once.
//!
//! Each mode i evolves exactly for inputs held over a step:
//! `ξ_i ← e_i ξ_i + g_i (b_q,i q_n + b_a,i a_n)`, with `e_i = exp(−λ_i dt)`,
//! `g_i = (1 − e_i)/λ_i`, `q` the flux and `a` the air drive `T_amb − T_ref` (the nominal
//! convection folded into `b_a`). Outputs `y = C ξ + T_ref`: the probes, the friction-face
//! mean, and the maximum over the friction-face nodes that stand for the face.

use rayon::prelude::*;

use crate::error::{Result, ThermalError};
use crate::simd::{has_avx2_fma, madd};

/// The exact one-step propagator of modes `dξ/dt = −λ ξ + u` with `u` held over the step:
/// `e = exp(−λ dt)`, `g = (1 − e)/λ` (`dt` where `λ dt` vanishes), computed without
/// cancellation. The one place it is computed: the batch stepper uses it, and Python's
/// reduced model calls it (`rom_exact_propagator`) for its switching propagators.
pub fn exact_propagator(lam: &[f64], dt_s: f64) -> (Vec<f64>, Vec<f64>) {
    lam.iter()
        .map(|&l| {
            let x = l * dt_s;
            let g = if x.abs() > 1e-12 {
                -(-x).exp_m1() / l
            } else {
                dt_s
            };
            ((-x).exp(), g)
        })
        .unzip()
}

/// A reduced model in modal form at one time step.
#[derive(Debug, Clone, PartialEq)]
pub struct ModalStepper {
    pub e: Vec<f64>,
    pub g_bq: Vec<f64>,
    pub g_ba: Vec<f64>,
    /// Row-major (n_outputs x r): probes, then the face mean, then face-max nodes.
    pub c: Vec<f64>,
    pub n_probes: usize,
}

/// Outputs of a batch, row-major: `probe_c` (E, S+1, P), `face_mean_c` and `face_max_c`
/// (E, S+1).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BatchOutputs {
    pub probe_c: Vec<f64>,
    pub face_mean_c: Vec<f64>,
    pub face_max_c: Vec<f64>,
}

impl ModalStepper {
    pub fn new(
        lam: &[f64],
        b_q: &[f64],
        b_a: &[f64],
        c: Vec<f64>,
        n_probes: usize,
        dt_s: f64,
    ) -> Result<Self> {
        let r = lam.len();
        if !(dt_s.is_finite() && dt_s > 0.0) {
            return Err(ThermalError::InvalidTimeStep(dt_s));
        }
        if b_q.len() != r || b_a.len() != r || r == 0 || c.len() % r != 0 {
            return Err(ThermalError::LengthMismatch {
                name: "modal arrays".into(),
                expected: r,
                got: b_q.len(),
            });
        }
        let n_out = c.len() / r;
        if n_out < n_probes + 2 {
            return Err(ThermalError::LengthMismatch {
                name: "output rows (probes, mean, at least one face node)".into(),
                expected: n_probes + 2,
                got: n_out,
            });
        }
        let (e, g) = exact_propagator(lam, dt_s);
        let g_bq = g.iter().zip(b_q).map(|(gi, b)| gi * b).collect();
        let g_ba = g.iter().zip(b_a).map(|(gi, b)| gi * b).collect();
        Ok(ModalStepper {
            e,
            g_bq,
            g_ba,
            c,
            n_probes,
        })
    }

    pub fn order(&self) -> usize {
        self.e.len()
    }

    pub fn n_outputs(&self) -> usize {
        self.c.len() / self.order()
    }

    /// Simulate `n_events` events of `n_steps` steps each from rest (θ = 0): `flux` and
    /// `drive` row-major (E, S), or (E) when each event's air drive is constant, `t_ref`
    /// (E). Events run in parallel.
    pub fn simulate_batch(
        &self,
        flux: &[f64],
        drive: &[f64],
        t_ref: &[f64],
        n_steps: usize,
    ) -> Result<BatchOutputs> {
        let n_events = t_ref.len();
        if flux.len() != n_events * n_steps {
            return Err(ThermalError::LengthMismatch {
                name: "flux".into(),
                expected: n_events * n_steps,
                got: flux.len(),
            });
        }
        let drive_steps = if drive.len() == n_events && n_steps != 1 {
            1
        } else {
            n_steps
        };
        if drive.len() != n_events * drive_steps {
            return Err(ThermalError::LengthMismatch {
                name: "drive".into(),
                expected: n_events * n_steps,
                got: drive.len(),
            });
        }
        let p = self.n_probes;
        let rows = n_steps + 1;
        let mut out = BatchOutputs {
            probe_c: vec![0.0; n_events * rows * p],
            face_mean_c: vec![0.0; n_events * rows],
            face_max_c: vec![0.0; n_events * rows],
        };
        // blocks of LANES events advance together, one event per SIMD lane
        out.probe_c
            .par_chunks_mut((LANES * rows * p).max(1))
            .zip(out.face_mean_c.par_chunks_mut(LANES * rows))
            .zip(out.face_max_c.par_chunks_mut(LANES * rows))
            .enumerate()
            .for_each(|(block, ((probe, mean), fmax))| {
                let first = block * LANES;
                let lanes = (n_events - first).min(LANES);
                let inputs = BlockInputs {
                    flux: &flux[first * n_steps..(first + lanes) * n_steps],
                    drive: &drive[first * drive_steps..(first + lanes) * drive_steps],
                    t_ref: &t_ref[first..first + lanes],
                    n_steps,
                    drive_steps,
                };
                self.run_block(&inputs, probe, mean, fmax);
            });
        Ok(out)
    }

    fn run_block(
        &self,
        inputs: &BlockInputs,
        probe: &mut [f64],
        mean: &mut [f64],
        fmax: &mut [f64],
    ) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            // SAFETY: the CPU has the features the function is compiled for.
            unsafe { self.run_block_avx2(inputs, probe, mean, fmax) };
            return;
        }
        self.run_block_generic::<false>(inputs, probe, mean, fmax);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn run_block_avx2(
        &self,
        inputs: &BlockInputs,
        probe: &mut [f64],
        mean: &mut [f64],
        fmax: &mut [f64],
    ) {
        self.run_block_generic::<true>(inputs, probe, mean, fmax);
    }

    /// Up to LANES events, one per SIMD lane: the loops over lanes vectorise. `FMA`: fused
    /// multiply-adds (only where the caller enables the CPU feature: without it `mul_add`
    /// is a call into libm).
    #[inline(always)]
    fn run_block_generic<const FMA: bool>(
        &self,
        inputs: &BlockInputs,
        probe: &mut [f64],
        mean: &mut [f64],
        fmax: &mut [f64],
    ) {
        let r = self.order();
        let p = self.n_probes;
        let n_out = self.n_outputs();
        let s = inputs.n_steps;
        let ds = inputs.drive_steps;
        let rows = s + 1;
        let lanes = inputs.t_ref.len();
        let mut xi = vec![[0.0f64; LANES]; r];
        let blocks = self.row_blocks();
        let mut y = vec![[0.0f64; LANES]; n_out.div_ceil(ROW_BLOCK) * ROW_BLOCK];
        let mut ql = [0.0f64; LANES];
        let mut al = [0.0f64; LANES];
        for k in 0..rows {
            if k > 0 {
                let kd = if ds == 1 { 0 } else { k - 1 };
                for l in 0..lanes {
                    ql[l] = inputs.flux[l * s + k - 1];
                    al[l] = inputs.drive[l * ds + kd];
                }
                for (((x, &e), &gq), &ga) in
                    xi.iter_mut().zip(&self.e).zip(&self.g_bq).zip(&self.g_ba)
                {
                    for l in 0..LANES {
                        x[l] = madd::<FMA>(e, x[l], madd::<FMA>(gq, ql[l], ga * al[l]));
                    }
                }
            }
            Self::outputs::<FMA>(&blocks, r, &xi, &mut y);
            let mut m = [f64::NEG_INFINITY; LANES];
            for yo in &y[p + 1..n_out] {
                for l in 0..LANES {
                    m[l] = if yo[l] > m[l] { yo[l] } else { m[l] };
                }
            }
            for l in 0..lanes {
                let t = inputs.t_ref[l];
                for j in 0..p {
                    probe[(l * rows + k) * p + j] = y[j][l] + t;
                }
                mean[l * rows + k] = y[p][l] + t;
                fmax[l * rows + k] = m[l] + t;
            }
        }
    }

    /// `y = C ξ` for a block of events, from the row blocks of `C` laid out for it
    /// ([`ModalStepper::row_blocks`]). Output rows go `ROW_BLOCK` at a time: independent
    /// accumulator vectors keep the FMA units busy (one row at a time waits on the latency
    /// of its own chain of sums).
    #[inline(always)]
    fn outputs<const FMA: bool>(
        blocks: &[[f64; ROW_BLOCK]],
        r: usize,
        xi: &[[f64; LANES]],
        y: &mut [[f64; LANES]],
    ) {
        for (block, out) in blocks.chunks_exact(r).zip(y.chunks_exact_mut(ROW_BLOCK)) {
            let mut acc = [[0.0f64; LANES]; ROW_BLOCK];
            for (cb, x) in block.iter().zip(xi) {
                for j in 0..ROW_BLOCK {
                    for l in 0..LANES {
                        acc[j][l] = madd::<FMA>(cb[j], x[l], acc[j][l]);
                    }
                }
            }
            out.copy_from_slice(&acc);
        }
    }

    /// `C` in blocks of `ROW_BLOCK` rows, each stored mode by mode (rows padded with zeros
    /// to a whole number of blocks).
    fn row_blocks(&self) -> Vec<[f64; ROW_BLOCK]> {
        let r = self.order();
        let n_out = self.n_outputs();
        let n_blocks = n_out.div_ceil(ROW_BLOCK);
        let mut out = vec![[0.0f64; ROW_BLOCK]; n_blocks * r];
        for (o, row) in self.c.chunks_exact(r).enumerate() {
            for (i, &v) in row.iter().enumerate() {
                out[(o / ROW_BLOCK) * r + i][o % ROW_BLOCK] = v;
            }
        }
        out
    }
}

/// Propagators of a reduced model in modal coordinates ξ, one per distinct step system
/// (time step, scheme, convection): `ξ ← Q [e ⊙ (Qᵀ ξ) + g ⊙ (Qᵀ u)]`, `Q` the eigenbasis of
/// the reduced operator at that convection (the identity for the nominal one, whose modes
/// are the coordinates themselves).
#[derive(Debug, Clone, PartialEq)]
pub struct Propagators {
    order: usize,
    /// (K, r) each.
    e: Vec<f64>,
    g: Vec<f64>,
    /// (K, r, r) row-major, `q[(k r + i) r + j] = Q_k[i, j]`; ignored where not `rotated`.
    q: Vec<f64>,
    rotated: Vec<bool>,
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

    /// One step of propagator `k` under input `u` (modal, length r); `w`, `v`: scratch.
    fn apply(&self, k: usize, xi: &mut [f64], u: &[f64], w: &mut [f64], v: &mut [f64]) {
        let r = self.order;
        let e = &self.e[k * r..(k + 1) * r];
        let g = &self.g[k * r..(k + 1) * r];
        if !self.rotated[k] {
            for i in 0..r {
                xi[i] = e[i] * xi[i] + g[i] * u[i];
            }
            return;
        }
        let q = &self.q[k * r * r..(k + 1) * r * r];
        // w = Qᵀ ξ, v = Qᵀ u (Q row-major: accumulate row by row)
        w.fill(0.0);
        v.fill(0.0);
        for (row, (&x, &ui)) in q.chunks_exact(r).zip(xi.iter().zip(u)) {
            for j in 0..r {
                w[j] += row[j] * x;
                v[j] += row[j] * ui;
            }
        }
        for j in 0..r {
            w[j] = e[j] * w[j] + g[j] * v[j];
        }
        // ξ = Q w
        for (row, x) in q.chunks_exact(r).zip(xi.iter_mut()) {
            *x = row.iter().zip(w.iter()).map(|(a, b)| a * b).sum();
        }
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
        let mut xi = xi0.to_vec();
        let (mut w, mut v) = (vec![0.0; r], vec![0.0; r]);
        let outputs = |xi: &[f64], y: &mut [f64]| {
            for (yo, row) in y.iter_mut().zip(c.chunks_exact(r)) {
                *yo = row.iter().zip(xi).map(|(a, b)| a * b).sum();
            }
        };
        outputs(&xi, &mut y[..n_out]);
        for step in 0..s {
            let uk = &u[step * r..(step + 1) * r];
            for _ in 0..repeats[step] {
                self.apply(index[step], &mut xi, uk, &mut w, &mut v);
            }
            outputs(&xi, &mut y[(step + 1) * n_out..(step + 2) * n_out]);
        }
        Ok((y, xi))
    }
}

/// Output rows computed together in [`ModalStepper::outputs`].
const ROW_BLOCK: usize = 6;

/// Events per SIMD block.
const LANES: usize = 8;

/// The inputs of one block of events, row-major (lanes, steps).
struct BlockInputs<'a> {
    flux: &'a [f64],
    drive: &'a [f64],
    t_ref: &'a [f64],
    n_steps: usize,
    /// `n_steps`, or 1 for an air drive constant over each event.
    drive_steps: usize,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exact_propagator_has_its_limits() {
        let dt = 2.0;
        let (e, g) = exact_propagator(&[0.0, 1e-15, 0.3, 1e6], dt);
        // no decay: e = 1, g = dt (the limit of (1 - e)/λ), also just above zero
        assert_eq!((e[0], g[0]), (1.0, dt));
        assert!((g[1] - dt).abs() <= 1e-12 * dt && e[1] <= 1.0);
        // the middle: the formula itself
        assert!((e[2] - (-0.6f64).exp()).abs() < 1e-15);
        assert!((g[2] - (1.0 - (-0.6f64).exp()) / 0.3).abs() < 1e-14);
        // fast modes: gone in one step, g = 1/λ (the steady response)
        assert_eq!(e[3], 0.0);
        assert!((g[3] - 1e-6).abs() < 1e-20);
    }

    #[test]
    fn one_mode_matches_the_exact_exponential_response() {
        // θ' = −λ θ + b q: from rest under constant q, θ(t) = b q (1 − e^{−λ t}) / λ
        let (lam, b, q) = (0.05, 2.0, 3.0);
        let c = vec![1.0, 1.0, 1.0]; // probe, mean, one face node: all read the mode
        let s = ModalStepper::new(&[lam], &[b], &[0.0], c, 1, 1.0).unwrap();
        let n = 50;
        let out = s
            .simulate_batch(&vec![q; n], &vec![0.0; n], &[20.0], n)
            .unwrap();
        for k in 0..=n {
            let exact = 20.0 + b * q * (1.0 - (-lam * k as f64).exp()) / lam;
            assert!((out.probe_c[k] - exact).abs() < 1e-12);
            assert!((out.face_max_c[k] - exact).abs() < 1e-12);
        }
    }

    #[test]
    fn a_constant_drive_per_event_is_the_same_as_a_series() {
        let c = vec![1.0, 0.5, 1.0, 0.2, -0.3, 0.7, 0.1, 0.9, 0.4];
        let s = ModalStepper::new(
            &[0.01, 0.2, 1.5],
            &[1.0, 2.0, 0.5],
            &[0.3, -0.2, 0.1],
            c,
            1,
            1.0,
        )
        .unwrap();
        let n = 30;
        let flux: Vec<f64> = (0..3 * n).map(|k| (k % 7) as f64).collect();
        let drive = [-5.0, 2.0, 0.5];
        let series: Vec<f64> = drive.iter().flat_map(|&d| vec![d; n]).collect();
        let t_ref = [20.0, 30.0, 40.0];
        let a = s.simulate_batch(&flux, &drive, &t_ref, n).unwrap();
        let b = s.simulate_batch(&flux, &series, &t_ref, n).unwrap();
        assert_eq!(a, b);
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

    #[test]
    fn bad_lengths_are_errors() {
        let s = ModalStepper::new(&[1.0], &[1.0], &[1.0], vec![1.0, 1.0, 1.0], 1, 1.0).unwrap();
        assert!(s.simulate_batch(&[1.0; 5], &[0.0; 4], &[0.0], 5).is_err());
        assert!(ModalStepper::new(&[1.0], &[1.0], &[1.0], vec![1.0], 1, 1.0).is_err());
        assert!(ModalStepper::new(&[1.0], &[1.0], &[1.0], vec![1.0; 3], 1, 0.0).is_err());
    }
}
