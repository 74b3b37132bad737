//! Many events of one reduced model at once: blocks of `LANES` events advance together, one
//! event per SIMD lane, from rest under per-step flux and air drive.

use rayon::prelude::*;

use super::exact_propagator;
use crate::error::{Result, ThermalError};
use crate::simd::{has_avx2_fma, madd};

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

/// Output rows computed together in [`ModalStepper::outputs`].
pub(super) const ROW_BLOCK: usize = 6;

/// Events per SIMD block.
pub(super) const LANES: usize = 8;

/// The inputs of one block of events, row-major (lanes, steps).
pub(super) struct BlockInputs<'a> {
    pub(super) flux: &'a [f64],
    pub(super) drive: &'a [f64],
    pub(super) t_ref: &'a [f64],
    pub(super) n_steps: usize,
    /// `n_steps`, or 1 for an air drive constant over each event.
    pub(super) drive_steps: usize,
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn bad_lengths_are_errors() {
        let s = ModalStepper::new(&[1.0], &[1.0], &[1.0], vec![1.0, 1.0, 1.0], 1, 1.0).unwrap();
        assert!(s.simulate_batch(&[1.0; 5], &[0.0; 4], &[0.0], 5).is_err());
        assert!(ModalStepper::new(&[1.0], &[1.0], &[1.0], vec![1.0], 1, 1.0).is_err());
        assert!(ModalStepper::new(&[1.0], &[1.0], &[1.0], vec![1.0; 3], 1, 0.0).is_err());
    }
}
