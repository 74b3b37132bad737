//! The model as the kernel steps it: the transitions (a dense one in its own basis), the
//! rows of each basis and the rotations between them, the noise of each step; the mean's
//! and the covariance's prediction and the covariance's update.

use super::basis::{in_own_basis, rotate_vec, Rotation, Rows};
use super::linalg::{axpy, dot, gemv_rows, padded};
use super::problem::{Noise, Problem, Settings, Switching, Transition};
use super::transition::{DenseF, Dims};
use crate::simd::madd;

/// Scratch vectors of a covariance step.
pub(super) struct Work {
    pub(super) a: Vec<f64>,
    pub(super) b: Vec<f64>,
    pub(super) d: Vec<f64>,
    pub(super) big: Vec<f64>,
    pub(super) four: [Vec<f64>; 4],
    /// The dense products' padded matrices (`DenseF`).
    pub(super) pad: [Vec<f64>; 3],
    /// A covariance rotated into a transition's basis (n x n).
    pub(super) rot: Vec<f64>,
    /// Two matrices in the problem's own basis (the steady tests', n x n).
    pub(super) own: [Vec<f64>; 2],
    /// The element of the problem's own basis that failed the last steady test made there
    /// (tried first the next time: it is usually the same one until the test passes).
    pub(super) fail: (usize, usize),
}

impl Work {
    pub(super) fn new(n: usize) -> Self {
        Work {
            a: vec![0.0; n],
            b: vec![0.0; n],
            d: vec![0.0; n],
            big: vec![0.0; n * n],
            four: [vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]],
            pad: std::array::from_fn(|_| vec![0.0; padded(n) * padded(n)]),
            rot: vec![0.0; n * n],
            own: [vec![0.0; n * n], vec![0.0; n * n]],
            fail: (0, 0),
        }
    }
}

pub(super) struct Kernel<'a> {
    pub(super) p: &'a Problem<'a>,
    pub(super) d: Dims,
    pub(super) m: usize,
    pub(super) var_v: f64,
    /// σ_w² of the quiet and the manoeuvre mode, and of the quiet mode with the cylinder
    /// applied.
    pub(super) sw2: [f64; 3],
    pub(super) switching: Option<Switching>,
    /// The steady tests' tolerances, (the filter's, the smoother's), in the quiet mode and in
    /// the manoeuvre mode (indexed by the key's mode).
    pub(super) tols: [(f64, f64); 2],
    /// The transitions as stepped: a dense one as a diagonal one in its own basis (module
    /// docs), the others as given.
    pub(super) trs: Vec<Transition>,
    /// The basis of each transition's result (0: the problem's own; `rows`).
    pub(super) basis: Vec<u32>,
    /// The reading's and the outputs' rows in each basis.
    pub(super) rows: Vec<Rows>,
    /// The rotation between two bases met in a row (`R = Q_newᵀ Q_old` and `Rᵀ`), by
    /// (old, new).
    pub(super) rotations: std::collections::HashMap<(u32, u32), Rotation>,
    /// Each transition's mode noise in its basis where it is not diagonal (r x r; empty: it
    /// is, `q_modes`).
    pub(super) noise_rot: Vec<Vec<f64>>,
    /// Each transition's dense F (None: diagonal, stepped by its structure).
    pub(super) dense: Vec<Option<DenseF>>,
    /// Whether each transition adds noise to a mode (`q_modes` not all zero).
    pub(super) mode_noise: Vec<bool>,
}

impl<'a> Kernel<'a> {
    pub(super) fn new(p: &'a Problem<'a>, noise: Noise, settings: &Settings) -> Self {
        let (r, n) = (p.order, p.n_state());
        let d = Dims {
            r,
            n,
            lag: p.lag,
            brake: p.brake,
        };
        // a dense transition in the basis of its eigenvectors where it has one
        let mut rows = vec![Rows::new(p, Vec::new())];
        let mut trs = Vec::with_capacity(p.transitions.len());
        let mut basis = Vec::with_capacity(p.transitions.len());
        let mut noise_rot = Vec::with_capacity(p.transitions.len());
        for tr in &p.transitions {
            match (!tr.diagonal).then(|| in_own_basis(tr, r)).flatten() {
                Some((q, rotated, noise)) => {
                    basis.push(rows.len() as u32);
                    rows.push(Rows::new(p, q));
                    trs.push(rotated);
                    noise_rot.push(noise);
                }
                None => {
                    basis.push(0);
                    trs.push(tr.clone());
                    noise_rot.push(Vec::new());
                }
            }
        }
        // the rotations between the bases of consecutive steps (and back to the problem's
        // own at the end)
        let mut rotations = std::collections::HashMap::new();
        let mut before = 0u32;
        // (and from each basis to the problem's own: the steady tests')
        let back = (1..rows.len() as u32).map(|b| (b, 0));
        let pairs = p.index.iter().map(|&k| {
            let now = basis[k as usize];
            (std::mem::replace(&mut before, now), now)
        });
        for (before, now) in pairs.chain(back) {
            if now != before {
                rotations.entry((before, now)).or_insert_with(|| {
                    let (qo, qn) = (&rows[before as usize].q, &rows[now as usize].q);
                    // R = Q_newᵀ Q_old (Q empty: the identity)
                    let at = |q: &Vec<f64>, i: usize, j: usize| {
                        if q.is_empty() {
                            f64::from(u8::from(i == j))
                        } else {
                            q[i * r + j]
                        }
                    };
                    let mut rm = vec![0.0; r * r];
                    for i in 0..r {
                        for j in 0..r {
                            rm[i * r + j] = (0..r).map(|l| at(qn, l, i) * at(qo, l, j)).sum();
                        }
                    }
                    Rotation::new(rm, &d)
                });
            }
        }
        let dense = trs
            .iter()
            .map(|tr| (!tr.diagonal).then(|| DenseF::new(tr, &d)))
            .collect();
        Kernel {
            p,
            d,
            m: p.n_nodes(),
            var_v: noise.measurement_k * noise.measurement_k,
            sw2: [
                noise
                    .switching
                    .map_or(noise.power_w_per_sqrt_s, |s| s.quiet_w_per_sqrt_s)
                    .powi(2),
                noise.power_w_per_sqrt_s.powi(2),
                noise
                    .switching
                    .map_or(noise.power_w_per_sqrt_s, |s| s.applied_w_per_sqrt_s)
                    .powi(2),
            ],
            switching: noise.switching,
            tols: {
                let quiet = (settings.steady_tolerance, settings.smoother_tolerance);
                [quiet, settings.manoeuvre_tolerances.unwrap_or(quiet)]
            },
            mode_noise: trs
                .iter()
                .zip(&noise_rot)
                .map(|(tr, m)| !m.is_empty() || tr.q_modes.iter().any(|&q| q != 0.0))
                .collect(),
            trs,
            basis,
            rows,
            rotations,
            noise_rot,
            dense,
        }
    }

    /// The basis of the state at second `t` (its step's transition's; 0 at the prior).
    #[inline(always)]
    pub(super) fn basis_at(&self, t: usize) -> u32 {
        if t == 0 {
            0
        } else {
            self.basis[self.p.index[t - 1] as usize]
        }
    }

    /// The rows in the basis of the state at second `t`.
    #[inline(always)]
    pub(super) fn rows_at(&self, t: usize) -> &Rows {
        &self.rows[self.basis_at(t) as usize]
    }

    /// The rotation from the basis `from` to the basis `to`; None where they are the same.
    #[inline(always)]
    pub(super) fn rotation(&self, from: u32, to: u32) -> Option<&Rotation> {
        (from != to).then(|| &self.rotations[&(from, to)])
    }

    /// The rotation into the basis of step `t`'s transition from the state's at `t - 1`.
    #[inline(always)]
    pub(super) fn change(&self, t: usize) -> Option<&Rotation> {
        self.rotation(self.basis_at(t - 1), self.basis_at(t))
    }

    /// `(g P_declared)²` of the step into `t` (t > 0), W²/s.
    #[inline(always)]
    pub(super) fn power_noise(&self, t: usize) -> f64 {
        self.p.power_noise.get(t - 1).copied().unwrap_or(0.0)
    }

    /// The mode at the start: the manoeuvre mode only without switching.
    pub(super) fn first_mode(&self) -> bool {
        self.switching.is_none()
    }

    pub(super) fn prior_cov(&self) -> Vec<f64> {
        let (r, n) = (self.d.r, self.d.n);
        let mut cov = self.p.cov0.clone();
        cov[r * n + r] += self.sw2[usize::from(self.first_mode())] * self.p.p_prior_unit;
        cov
    }

    /// The mean's prediction into step `t` (t > 0): `x_prior = F x + w`.
    #[inline(always)]
    pub(super) fn predict_mean<const FMA: bool>(&self, t: usize, x: &[f64], out: &mut [f64]) {
        let r = self.d.r;
        let idx = self.p.index[t - 1] as usize;
        let tr = &self.trs[idx];
        match self.change(t) {
            Some(rot) => {
                // the state into the transition's basis first
                let mut xr = x.to_vec();
                rotate_vec::<FMA>(&rot.r, r, &mut xr, &mut out[..r]);
                tr.apply::<FMA>(&self.d, &xr, out);
            }
            None => tr.apply::<FMA>(&self.d, x, out),
        }
        let w = &self.p.w[(t - 1) * r..t * r];
        let q = &self.rows[self.basis[idx] as usize].q;
        if q.is_empty() {
            for (o, wi) in out[..r].iter_mut().zip(w) {
                *o += wi;
            }
        } else {
            // Qᵀ w
            for (row, &wi) in q.chunks_exact(r).zip(w) {
                axpy::<FMA>(wi, row, &mut out[..r]);
            }
        }
        if self.d.lag {
            out[r + 1] = madd::<FMA>(tr.lag_b1, dot::<FMA>(&self.p.c_probe, w), out[r + 1]);
        }
    }

    /// The predicted covariance into `t` (`pred`; t = 0: the prior) in the power-noise mode
    /// `manoeuvre`, `Σh` into `ph`; returns the reading's predicted variance S.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(super) fn predict_cov<const FMA: bool>(
        &self,
        t: usize,
        manoeuvre: bool,
        prev: &[f64],
        pred: &mut [f64],
        ph: &mut [f64],
        w: &mut Work,
    ) -> f64 {
        let (r, n) = (self.d.r, self.d.n);
        let fused = t > 0 && !self.d.lag;
        let rows = self.rows_at(t);
        if t > 0 {
            let idx = self.p.index[t - 1] as usize;
            let tr = &self.trs[idx];
            // the covariance into the transition's basis first
            let mut rotated = std::mem::take(&mut w.rot);
            let prev: &[f64] = match self.change(t) {
                Some(rot) => {
                    rot.forward_cov::<FMA>(&self.d, prev, &mut rotated, &mut w.pad);
                    &rotated
                }
                None => prev,
            };
            // without a lag, Σh (h on the modes) is summed while the rows are made
            let acc = fused.then(|| (&rows.h[..r], &mut *ph));
            // the mode rows' share of `q_gap u uᵀ` is added in the diagonal step's pass (the
            // same operations) where no mode noise comes between
            let gap_fused = self.dense[idx].is_none() && tr.q_gap > 0.0 && !self.mode_noise[idx];
            match &self.dense[idx] {
                Some(df) => df.predict_cov::<FMA>(&self.d, prev, pred, &mut w.pad, acc),
                None => tr.predict_cov::<FMA>(
                    &self.d,
                    prev,
                    pred,
                    &mut w.a,
                    &mut w.b,
                    &mut w.big,
                    acc,
                    gap_fused.then_some(&rows.gap_dir[..]),
                ),
            }
            w.rot = rotated;
            let sw2 = match (manoeuvre, tr.applied) {
                (true, _) => self.sw2[1],
                (false, true) => self.sw2[2],
                (false, false) => self.sw2[0],
            };
            let sw2 = sw2 + self.power_noise(t);
            pred[r * n + r] = madd::<FMA>(sw2, tr.q_unit, pred[r * n + r]);
            if self.d.brake {
                pred[n * n - 1] += tr.brake_q;
            }
            for (i, &q) in tr.q_modes.iter().enumerate() {
                if q != 0.0 {
                    // q e_i e_iᵀ (and its share e_i q h_i of Σh when that was summed above)
                    pred[i * n + i] += q;
                    if fused {
                        ph[i] = madd::<FMA>(q, rows.h[i], ph[i]);
                    }
                }
            }
            let noise = &self.noise_rot[idx];
            if !noise.is_empty() {
                // the mode noise in the transition's basis, Qᵀ diag(q) Q (and its Σh share)
                for (i, row) in noise.chunks_exact(r).enumerate() {
                    for (v, &m) in pred[i * n..i * n + r].iter_mut().zip(row) {
                        *v += m;
                    }
                    if fused {
                        ph[i] += dot::<FMA>(row, &rows.h[..r]);
                    }
                }
            }
            if tr.q_gap > 0.0 {
                // q_gap u uᵀ (and its share u (u·h) of Σh when that was summed above)
                let u = &rows.gap_dir;
                let done = if gap_fused { r } else { 0 };
                for (row, &ui) in pred.chunks_exact_mut(n).zip(u).skip(done) {
                    if ui != 0.0 {
                        axpy::<FMA>(tr.q_gap * ui, u, row);
                    }
                }
                if fused {
                    let hu = dot::<FMA>(&rows.h[..r], &u[..r]);
                    axpy::<FMA>(tr.q_gap * hu, u, ph);
                }
            }
        } else {
            pred.copy_from_slice(prev);
        }
        if self.d.lag {
            // Σh is the lag's column (its row: the matrix is symmetric to rounding)
            ph.copy_from_slice(&pred[(r + 1) * n..(r + 2) * n]);
        } else if !fused {
            ph.fill(0.0);
            for (row, &hi) in pred.chunks_exact(n).zip(&rows.h[..r]) {
                axpy::<FMA>(hi, row, ph);
            }
        }
        dot::<FMA>(&rows.h, ph) + self.var_v
    }

    /// In place: the predicted covariance becomes the filtered covariance `Σ - K (Σh)ᵀ`;
    /// `acc` (Some): adds `Σ c` for the first r entries of each `c` into its accumulator.
    #[inline(always)]
    pub(super) fn filter_cov<const FMA: bool>(
        &self,
        cov: &mut [f64],
        gain: &[f64],
        ph: &[f64],
        measured: bool,
        mut acc: Option<[(&[f64], &mut [f64]); 2]>,
    ) {
        let n = self.d.n;
        let r = self.d.r;
        if let Some(accs) = acc.as_mut() {
            for (_, a) in accs.iter_mut() {
                a.fill(0.0);
            }
        }
        for (i, row) in cov.chunks_exact_mut(n).enumerate() {
            let ki = if measured { gain[i] } else { 0.0 };
            match acc.as_mut() {
                Some([(c1, a1), (c2, a2)]) if i < r => {
                    // the row's update and its share of Σ c for both outputs, in one pass
                    let (w1, w2) = (c1[i], c2[i]);
                    for (((v, &pj), s1), s2) in
                        row.iter_mut().zip(ph).zip(a1.iter_mut()).zip(a2.iter_mut())
                    {
                        *v = madd::<FMA>(-ki, pj, *v);
                        *s1 = madd::<FMA>(w1, *v, *s1);
                        *s2 = madd::<FMA>(w2, *v, *s2);
                    }
                }
                _ => {
                    if measured {
                        axpy::<FMA>(-ki, ph, row);
                    }
                }
            }
        }
    }

    /// `M c` for a symmetric M and `c` on the first entries.
    #[inline(always)]
    pub(super) fn times<const FMA: bool>(&self, m: &[f64], c: &[f64], out: &mut [f64]) {
        let n = self.d.n;
        out.fill(0.0);
        gemv_rows::<FMA>(&c[..c.len().min(n)], 1.0, m, n, &mut out[..n]);
    }

    /// `sᵀ M s` for a symmetric M (`tmp`: n scratch).
    #[inline(always)]
    pub(super) fn quad<const FMA: bool>(&self, m: &[f64], s: &[f64], tmp: &mut [f64]) -> f64 {
        self.times::<FMA>(m, s, tmp);
        dot::<FMA>(s, tmp)
    }
}

#[cfg(test)]
mod tests {
    use std::borrow::Cow;

    use crate::estimator::run;
    use crate::estimator::testing::*;

    #[test]
    fn the_declared_power_noise_is_the_textbook_filters_and_keeps_the_fast_paths_exact() {
        for (lag, noise) in [(false, NOISE), (true, NOISE), (false, SWITCHING)] {
            let mut p = problem(lag, 9000, 13);
            // (g P)² on the dense stretches ("brakings"), 0 elsewhere
            let noise_of: Vec<f64> = p
                .index
                .iter()
                .enumerate()
                .map(|(t, &k)| {
                    if k == 1 {
                        0.04 * (1.0 + (t % 7) as f64)
                    } else {
                        0.0
                    }
                })
                .collect();
            assert!(noise_of.iter().any(|&q| q > 0.0));
            p.power_noise = Cow::Owned(noise_of);
            let exact = run(&p, noise, &settings(0.0, 64)).unwrap();
            let reference = naive_modes(&p, noise, Some(&exact.manoeuvre));
            assert_estimates("filtered", &exact.filtered, &reference.filtered, 1e-9);
            assert_estimates(
                "smoothed",
                exact.smoothed.as_ref().unwrap(),
                &reference.smoothed,
                1e-8,
            );
            // the steady states and the replayed excursions change no result with it on
            let fast = run(&p, noise, &settings(1e-12, 128)).unwrap();
            assert!(fast.frozen_steps > 1000, "{} frozen", fast.frozen_steps);
            assert!(fast.memo_steps > 100, "{} replayed", fast.memo_steps);
            assert_estimates("filtered", &fast.filtered, &exact.filtered, 1e-9);
            assert_estimates(
                "smoothed",
                fast.smoothed.as_ref().unwrap(),
                exact.smoothed.as_ref().unwrap(),
                1e-9,
            );
            let mut s = settings(1e-12, 128);
            s.replay = false;
            let computed = run(&p, noise, &s).unwrap();
            assert_eq!(computed.filtered.mean_c, fast.filtered.mean_c);
            // and it is another filter than without it
            p.power_noise = Cow::Owned(Vec::new());
            let plain = run(&p, noise, &settings(0.0, 64)).unwrap();
            assert_differ(
                "power_sd_w",
                &plain.filtered.power_sd_w,
                &exact.filtered.power_sd_w,
                1e-3,
            );
        }
    }

    #[test]
    fn the_braking_power_state_is_the_textbook_filter_and_smoother() {
        for lag in [false, true] {
            for noise in [NOISE, SWITCHING] {
                let p = brake_problem(lag, 400, 7);
                let out = run(&p, noise, &settings(0.0, 64)).unwrap();
                let manoeuvre = noise.switching.map(|_| &out.manoeuvre[..]);
                let naive = naive_modes(&p, noise, manoeuvre);
                assert_estimates("filtered", &out.filtered, &naive.filtered, 1e-9);
                assert_estimates(
                    "smoothed",
                    out.smoothed.as_ref().unwrap(),
                    &naive.smoothed,
                    1e-8,
                );
                assert_close("innovation", &out.innovation_k, &naive.innovation, 1e-9);
                assert!((out.log_likelihood - naive.loglik).abs() < 1e-8 * naive.loglik.abs());
                // the state did something: without it the power differs
                let mut plain = problem(lag, 400, 7);
                plain.reading_c = p.reading_c.clone();
                let without = run(&plain, noise, &settings(0.0, 64)).unwrap();
                assert_differ(
                    "power_w",
                    &without.filtered.power_w,
                    &out.filtered.power_w,
                    1e-3,
                );
            }
        }
    }
}
