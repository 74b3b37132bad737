//! The forward pass: the Kalman filter over every second, its innovation test between the
//! power's noise modes, the steady states and recorded excursions it meets, and the
//! checkpoints it leaves for the smoother.

use super::basis::{rotate_vec, Rows};
use super::covariance::{Checkpoint, Key, Last, Memo, MemoNode, Steady, FULL};
use super::kernel::{Kernel, Work};
use super::linalg::dot;
use super::outputs::{Estimates, Outputs};
use super::problem::Settings;
use crate::simd::madd;

pub(super) struct Forward {
    pub(super) outputs: Outputs,
    pub(super) modes: Vec<u32>,
    /// The power-noise mode of the step into each second (the smoother replays it).
    pub(super) manoeuvre: Vec<bool>,
    pub(super) caches: Vec<Steady>,
    pub(super) checkpoints: Vec<Checkpoint>,
    pub(super) memo: Memo,
    /// The recorded node whose covariance step t replayed (FULL: none).
    pub(super) memo_of: Vec<u32>,
}

/// The forward pass (`forced`: the power noise's mode of each step instead of the test's).
/// `from`: a pass with the same settings and the same modes up to and including the step of
/// its checkpoint `b`, whose checkpoints, caches and recorded excursions are taken and which
/// this pass resumes after that step (only without outputs: those before it are not made).
#[inline(always)]
pub(super) fn forward<const FMA: bool>(
    k: &Kernel,
    settings: &Settings,
    forced: Option<&[bool]>,
    from: Option<(Forward, usize)>,
) -> Forward {
    let n_t = k.p.reading_c.len();
    let block = settings.checkpoint_steps.max(1);
    let mut pass = Pass::new(k, settings);
    let mut start = 0;
    if let Some((f, b)) = from {
        // the state after step t0 = b block (the innovation test's is not needed: the modes
        // are forced)
        debug_assert!(forced.is_some() && !settings.outputs && settings.smooth);
        start = pass.resume(k, f, b, b * block);
    }
    for t in start..n_t {
        if let Some(f) = forced {
            pass.manoeuvre = f[t];
        }
        pass.step::<FMA>(k, settings, t, block);
    }
    pass.finish::<FMA>(k, settings)
}

/// The forward pass's state from one step to the next.
struct Pass {
    out: Outputs,
    modes: Vec<u32>,
    memo_of: Vec<u32>,
    manoeuvre_of: Vec<bool>,
    caches: Vec<Steady>,
    checkpoints: Vec<Checkpoint>,
    memo: Memo,
    x: Vec<f64>,
    x_prior: Vec<f64>,
    /// The filtered covariance of the last full step (during a steady stretch the cache was
    /// made from it); `prev`: the one before.
    cov: Vec<f64>,
    prev: Vec<f64>,
    gain: Vec<f64>,
    acc_mean: Vec<f64>,
    acc_node: Vec<f64>,
    node_values: Vec<f64>,
    w: Work,
    /// The steady cache in force, where the last filtered covariance is, and the last step's
    /// key.
    steady: Option<usize>,
    last: Last,
    prev_key: Option<Key>,
    /// The innovation test: the power noise's mode of the next step, the normalised
    /// innovations' weighted mean, its weight β and its standard deviation.
    manoeuvre: bool,
    m_z: f64,
    beta: f64,
    m_sd: f64,
}

/// A step's filtered variances: the face mean's, the largest face node's, the reported
/// power's, and `P`'s own.
type Vars = (f64, f64, f64, f64);

impl Pass {
    /// At the prior, before the first step.
    fn new(k: &Kernel, settings: &Settings) -> Self {
        let p = k.p;
        let n = k.d.n;
        let n_t = p.reading_c.len();
        let mut out = Outputs::default();
        if settings.outputs {
            out.filtered = Estimates::nan(n_t);
            out.innovation_k = vec![f64::NAN; n_t];
            out.innovation_var_k2 = vec![f64::NAN; n_t];
            out.predicted_reading_c = vec![f64::NAN; n_t];
        }
        let cov = k.prior_cov();
        let (beta, m_sd) = k.switching.map_or((0.0, 1.0), |s| {
            let b = (1.0 / s.window_steps).min(1.0);
            (b, (b / (2.0 - b)).sqrt())
        });
        Pass {
            out,
            modes: vec![FULL; n_t],
            memo_of: vec![FULL; n_t],
            manoeuvre_of: vec![false; n_t],
            caches: Vec::new(),
            checkpoints: Vec::new(),
            memo: Memo::new(n, settings.replay),
            x: p.x0.clone(),
            x_prior: vec![0.0; n],
            prev: cov.clone(),
            cov,
            gain: vec![0.0; n],
            acc_mean: vec![0.0; n],
            acc_node: vec![0.0; n],
            node_values: vec![0.0; k.m.next_multiple_of(4)],
            w: Work::new(n),
            steady: None,
            last: Last::Buf,
            prev_key: None,
            manoeuvre: k.first_mode(),
            m_z: 0.0,
            beta,
            m_sd,
        }
    }

    /// The state of pass `f` after step `t0` (its checkpoint `b`), with its modes, caches and
    /// recorded excursions as they stood there; returns the first step to take.
    fn resume(&mut self, k: &Kernel, f: Forward, b: usize, t0: usize) -> usize {
        let start = t0 + 1;
        let (n_caches, n_nodes) = (f.checkpoints[b].n_caches, f.checkpoints[b].n_nodes);
        (self.modes, self.memo_of, self.manoeuvre_of) = (f.modes, f.memo_of, f.manoeuvre);
        self.modes[start..].fill(FULL);
        self.memo_of[start..].fill(FULL);
        (self.caches, self.memo, self.checkpoints) = (f.caches, f.memo, f.checkpoints);
        self.caches.truncate(n_caches);
        self.memo.truncate(n_nodes, n_caches);
        self.checkpoints.truncate(b + 1);
        let cp = &self.checkpoints[b];
        self.x.copy_from_slice(&cp.x);
        self.gain.copy_from_slice(&cp.gain);
        if cp.last == Last::Buf {
            self.cov.copy_from_slice(&cp.cov);
        }
        (self.last, self.steady) = (cp.last, cp.steady);
        self.prev_key = k.key(t0, self.manoeuvre_of[t0]);
        start
    }

    /// Step `t`: the prediction, the update, the filtered variances, the next step's mode, the
    /// outputs and the checkpoint.
    #[inline(always)]
    fn step<const FMA: bool>(&mut self, k: &Kernel, settings: &Settings, t: usize, block: usize) {
        let p = k.p;
        let r = k.d.r;
        let key = k.key(t, self.manoeuvre);
        let rows = k.rows_at(t);
        self.manoeuvre_of[t] = self.manoeuvre;
        if self.manoeuvre {
            self.out.manoeuvre_steps += 1;
        }
        if t > 0 {
            k.predict_mean::<FMA>(t, &self.x, &mut self.x_prior);
        } else {
            self.x_prior.copy_from_slice(&self.x);
        }
        let measured = p.reading_c[t].is_finite();
        let frozen = self.steady.filter(|&c| Some(self.caches[c].key) == key);
        let hit = match (frozen, key) {
            (None, Some(kk)) => self.memo.child(self.last, kk),
            _ => None,
        };
        let s_var = self.predict::<FMA>(k, t, measured, frozen, hit);
        let (nu, predicted) = self.update::<FMA>(k, rows, t, measured, s_var);
        let (top, j) = if settings.outputs {
            k.nodes_max::<FMA>(rows, &self.x, None, &mut self.node_values)
        } else {
            (0.0, 0)
        };
        let (mean_var, node_var, power_var, hold_var) = match (frozen, hit) {
            (Some(c), _) => {
                self.last = Last::Cache(c);
                let s = &self.caches[c];
                (s.mean_var, s.node_var[j], s.power_var, s.hold_var)
            }
            (None, Some(u)) => {
                self.last = Last::Node(u);
                self.steady = self.memo.nodes[u].steady;
                if settings.outputs && self.memo.nodes[u].node_var[j].is_nan() {
                    let c = rows.node_row(j);
                    k.times::<FMA>(&self.memo.nodes[u].cov, c, &mut self.w.a);
                    self.memo.nodes[u].node_var[j] = dot::<FMA>(c, &self.w.a[..r]);
                }
                let node = &self.memo.nodes[u];
                (
                    node.mean_var,
                    node.node_var[j],
                    node.power_var,
                    node.hold_var,
                )
            }
            (None, None) => self.filter_full::<FMA>(k, settings, rows, j, measured, key, s_var),
        };
        self.next_mode(k, hold_var);
        if settings.outputs {
            let out = &mut self.out;
            let f = &mut out.filtered;
            f.mean_c[t] = dot::<FMA>(&rows.cm, &self.x[..r]) + p.t_ref_c;
            f.mean_sd_k[t] = mean_var.max(0.0).sqrt();
            f.max_c[t] = top + p.t_ref_c;
            f.max_sd_k[t] = node_var.max(0.0).sqrt();
            f.power_w[t] = k.power_of(&self.x);
            f.power_sd_w[t] = power_var.max(0.0).sqrt();
            out.innovation_k[t] = nu;
            out.innovation_var_k2[t] = s_var;
            out.predicted_reading_c[t] = predicted;
        }
        if settings.smooth && t % block == 0 {
            let cp = self.checkpoint(nu, s_var);
            self.checkpoints.push(cp);
        }
        self.prev_key = key;
    }

    /// The gain of step `t` (`frozen`: the steady cache's; `hit`: the recorded node's; else
    /// the predicted covariance computed into `cov`, `Σh` kept in `w.b`); returns the
    /// reading's predicted variance S.
    #[inline(always)]
    fn predict<const FMA: bool>(
        &mut self,
        k: &Kernel,
        t: usize,
        measured: bool,
        frozen: Option<usize>,
        hit: Option<usize>,
    ) -> f64 {
        match (frozen, hit) {
            (Some(c), _) => {
                self.out.frozen_steps += 1;
                self.modes[t] = c as u32;
                self.gain.copy_from_slice(&self.caches[c].gain);
                self.caches[c].s_var
            }
            (None, Some(u)) => {
                self.out.memo_steps += 1;
                self.memo_of[t] = u as u32;
                self.gain.copy_from_slice(&self.memo.nodes[u].gain);
                self.memo.nodes[u].s_var
            }
            (None, None) => {
                if self.last == Last::Buf {
                    std::mem::swap(&mut self.prev, &mut self.cov);
                }
                let src: &[f64] = match self.last {
                    Last::Buf => &self.prev,
                    Last::Cache(c) => &self.caches[c].cov,
                    Last::Node(u) => &self.memo.nodes[u].cov,
                };
                let (cov, gain, w) = (&mut self.cov, &mut self.gain, &mut self.w);
                let s_var = k.predict_cov::<FMA>(t, self.manoeuvre, src, cov, gain, w);
                // `gain` holds Σh: keep it for the update, then scale it into K
                w.b.copy_from_slice(gain);
                if measured {
                    let inv = 1.0 / s_var;
                    gain.iter_mut().for_each(|v| *v *= inv);
                } else {
                    gain.fill(0.0);
                }
                s_var
            }
        }
    }

    /// The mean's update at a reading (and the innovation test's weighted mean, the
    /// likelihood); returns the innovation (NaN: no reading) and the predicted reading.
    #[inline(always)]
    fn update<const FMA: bool>(
        &mut self,
        k: &Kernel,
        rows: &Rows,
        t: usize,
        measured: bool,
        s_var: f64,
    ) -> (f64, f64) {
        let p = k.p;
        let predicted = dot::<FMA>(&rows.h, &self.x_prior) + p.t_ref_c;
        let mut nu = f64::NAN;
        if measured {
            nu = p.reading_c[t] - predicted;
            for ((xi, &pi), &gi) in self.x.iter_mut().zip(&self.x_prior).zip(&self.gain) {
                *xi = madd::<FMA>(gi, nu, pi);
            }
            self.out.log_likelihood -=
                0.5 * ((2.0 * std::f64::consts::PI * s_var).ln() + nu * nu / s_var);
            self.out.updates += 1;
            self.m_z = madd::<FMA>(self.beta, nu / s_var.sqrt() - self.m_z, self.m_z);
        } else {
            self.x.copy_from_slice(&self.x_prior);
        }
        (nu, predicted)
    }

    /// A computed step's filtered covariance (in place in `cov`) and its variances; then the
    /// steady test for its key (a steady state met before for the key taken again, else a
    /// new cache) and the step recorded as a child of the last one where it can be.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn filter_full<const FMA: bool>(
        &mut self,
        k: &Kernel,
        settings: &Settings,
        rows: &Rows,
        j: usize,
        measured: bool,
        key: Option<Key>,
        s_var: f64,
    ) -> Vars {
        let (r, n) = (k.d.r, k.d.n);
        self.steady = None;
        let ph = std::mem::take(&mut self.w.b);
        if settings.outputs {
            let accs = [
                (&rows.cm[..], &mut self.acc_mean[..]),
                (rows.node_row(j), &mut self.acc_node[..]),
            ];
            k.filter_cov::<FMA>(&mut self.cov, &self.gain, &ph, measured, Some(accs));
        } else {
            k.filter_cov::<FMA>(&mut self.cov, &self.gain, &ph, measured, None);
        }
        self.w.b = ph;
        let vars = (
            dot::<FMA>(&rows.cm, &self.acc_mean[..r]),
            dot::<FMA>(rows.node_row(j), &self.acc_node[..r]),
            k.power_var_of(&self.cov),
            self.cov[r * n + r],
        );
        let Some(key_now) = key else {
            self.last = Last::Buf;
            return vars;
        };
        let src: &[f64] = match self.last {
            Last::Buf => &self.prev,
            Last::Cache(c) => &self.caches[c].cov,
            Last::Node(u) => &self.memo.nodes[u].cov,
        };
        let tol = k.tols_of(key_now).0;
        let b = k.basis[key_now.0 as usize];
        let (cov, w) = (&self.cov, &mut self.w);
        if key == self.prev_key && k.converged_own::<FMA>(b, cov, src, tol, w) {
            // a steady state met before for this key, within the tolerance, is taken again
            // (so excursions from it are recorded once)
            let again = self
                .caches
                .iter()
                .position(|c| c.key == key_now && k.converged_own::<FMA>(b, cov, &c.cov, tol, w));
            let caches = &mut self.caches;
            self.steady = Some(again.unwrap_or_else(|| {
                caches.push(k.make_steady::<FMA>(key_now, cov, &self.gain, s_var, settings.smooth));
                caches.len() - 1
            }));
        }
        // a node only where it can be recorded (the copies cost as much as a fused step's
        // pass)
        self.last = if self.memo.can_record(self.last) {
            let mut node_var = vec![f64::NAN; k.m];
            if settings.outputs {
                node_var[j] = vars.1;
            }
            let node = MemoNode {
                cov: self.cov.clone(),
                gain: self.gain.clone(),
                s_var,
                mean_var: vars.0,
                power_var: vars.2,
                hold_var: vars.3,
                node_var,
                children: Vec::new(),
                steady: self.steady,
            };
            match self.memo.record(self.last, key_now, node) {
                Some(u) => Last::Node(u),
                None => Last::Buf,
            }
        } else {
            Last::Buf
        };
        vars
    }

    /// The innovation test: the power noise's mode of the next step.
    #[inline(always)]
    fn next_mode(&mut self, k: &Kernel, hold_var: f64) {
        if let Some(sw) = k.switching {
            let r = k.d.r;
            let z = self.m_z.abs() / self.m_sd;
            self.manoeuvre = if self.manoeuvre {
                // P's own (the mode sets P's noise, not P_b's)
                z > sw.off_sigma || self.x[r].abs() > sw.hold_power_sigma * hold_var.max(0.0).sqrt()
            } else {
                z > sw.on_sigma
            };
        }
    }

    /// The checkpoint after the step just taken.
    fn checkpoint(&self, nu: f64, s_var: f64) -> Checkpoint {
        Checkpoint {
            x: self.x.clone(),
            cov: match self.last {
                Last::Buf => self.cov.clone(),
                Last::Cache(_) => Vec::new(),
                Last::Node(u) => self.memo.nodes[u].cov.clone(),
            },
            gain: self.gain.clone(),
            nu,
            s_var,
            last: self.last,
            steady: self.steady,
            n_caches: self.caches.len(),
            n_nodes: self.memo.nodes.len(),
        }
    }

    /// The pass after its last step: the final state and covariance in the problem's own
    /// basis, the modes, caches, checkpoints and recorded excursions.
    #[inline(always)]
    fn finish<const FMA: bool>(self, k: &Kernel, settings: &Settings) -> Forward {
        let Pass {
            mut out,
            modes,
            memo_of,
            manoeuvre_of,
            caches,
            checkpoints,
            memo,
            x,
            cov,
            mut w,
            last,
            ..
        } = self;
        let (r, n) = (k.d.r, k.d.n);
        let n_t = k.p.reading_c.len();
        out.final_state = x;
        out.final_cov = match last {
            Last::Buf => cov,
            Last::Cache(c) => caches[c].cov.clone(),
            Last::Node(u) => memo.nodes[u].cov.clone(),
        };
        if let Some(rot) = k.rotation(k.basis_at(n_t.saturating_sub(1)), 0) {
            // in the problem's own basis
            rotate_vec::<FMA>(&rot.r, r, &mut out.final_state, &mut w.a);
            let mut cov = vec![0.0; n * n];
            rot.forward_cov::<FMA>(&k.d, &out.final_cov, &mut cov, &mut w.pad);
            out.final_cov = cov;
        }
        if settings.outputs {
            out.manoeuvre.clone_from(&manoeuvre_of);
        }
        Forward {
            outputs: out,
            modes,
            manoeuvre: manoeuvre_of,
            caches,
            checkpoints,
            memo,
            memo_of,
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::estimator::run;
    use crate::estimator::testing::*;

    #[test]
    fn switching_modes_are_the_textbook_filter_and_smoother_with_that_q_sequence() {
        for lag in [false, true] {
            let p = problem(lag, 400, 7);
            for tol in [0.0, 1e-7] {
                let out = run(&p, SWITCHING, &settings(tol, 64)).unwrap();
                let switches = out.manoeuvre.windows(2).filter(|w| w[0] != w[1]).count();
                assert!(switches >= 2, "the test switched {switches} times");
                assert!(out.manoeuvre_steps > 0 && out.manoeuvre_steps < 400);
                let reference = naive_modes(&p, SWITCHING, Some(&out.manoeuvre));
                let tol_k = if tol == 0.0 { 1e-9 } else { 1e-5 };
                assert_estimates("filtered", &out.filtered, &reference.filtered, tol_k);
                assert_estimates(
                    "smoothed",
                    out.smoothed.as_ref().unwrap(),
                    &reference.smoothed,
                    10.0 * tol_k,
                );
                // the modes matter: σ_w everywhere is another filter
                let plain = naive(&p, SWITCHING);
                assert_differ(
                    "power_sd_w",
                    &plain.filtered.power_sd_w,
                    &out.filtered.power_sd_w,
                    1e-3,
                );
            }
        }
    }

    #[test]
    fn the_applied_cylinders_quiet_noise_is_the_textbook_filters() {
        let mut noise = SWITCHING;
        if let Some(sw) = noise.switching.as_mut() {
            sw.applied_w_per_sqrt_s = 0.2;
        }
        for lag in [false, true] {
            let mut p = problem(lag, 1000, 7);
            p.transitions[1].applied = true; // the dense stretches: "brakings"
            for tol in [0.0, 1e-7] {
                let out = run(&p, noise, &settings(tol, 64)).unwrap();
                let reference = naive_modes(&p, noise, Some(&out.manoeuvre));
                let tol_k = if tol == 0.0 { 1e-9 } else { 1e-5 };
                assert_estimates("filtered", &out.filtered, &reference.filtered, tol_k);
                assert_estimates(
                    "smoothed",
                    out.smoothed.as_ref().unwrap(),
                    &reference.smoothed,
                    10.0 * tol_k,
                );
                // and it is another filter than σ_q everywhere
                let plain = run(&p, SWITCHING, &settings(tol, 64)).unwrap();
                assert_differ(
                    "power_sd_w",
                    &plain.filtered.power_sd_w,
                    &out.filtered.power_sd_w,
                    1e-3,
                );
            }
        }
    }
}
