//! The smoother: the mode sequence it runs on (the filter's, or led), the filter's blocks
//! replayed from their checkpoints, and the modified Bryson-Frazier recursion backwards over
//! them.

use super::basis::rotate_vec;
use super::basis::Rows;
use super::covariance::{Checkpoint, Steady, FULL};
use super::filter::Forward;
use super::kernel::{Kernel, Work};
use super::linalg::{dot, dot4, gemv_rows3};
use super::outputs::Estimates;
use super::problem::Settings;
use crate::simd::madd;

/// The filter's mode sequence with the manoeuvre mode begun `lead` steps before each
/// switch-on (never at the prior, index 0); None when that changes nothing.
pub fn led_modes(manoeuvre: &[bool], lead: usize) -> Option<Vec<bool>> {
    if lead == 0 {
        return None;
    }
    let mut led = manoeuvre.to_vec();
    let mut changed = false;
    for t in 1..manoeuvre.len() {
        if manoeuvre[t] && !manoeuvre[t - 1] {
            for v in &mut led[t.saturating_sub(lead).max(1)..t] {
                changed |= !*v;
                *v = true;
            }
        }
    }
    changed.then_some(led)
}

/// The smoothed variances while the smoother's information matrix is steady inside one
/// steady stretch of the filter.
pub(super) struct BackSteady {
    pub(super) cache: u32,
    pub(super) mean_var: f64,
    pub(super) node_var: Vec<f64>,
    pub(super) power_var: f64,
}

/// One block of the filter replayed from its checkpoint: filtered state, covariance (full
/// steps), gain, innovation and its variance, per step.
pub(super) struct Replay {
    pub(super) xs: Vec<f64>,
    pub(super) covs: Vec<f64>,
    pub(super) gains: Vec<f64>,
    pub(super) nus: Vec<f64>,
    pub(super) s_vars: Vec<f64>,
    pub(super) x_prior: Vec<f64>,
    pub(super) ph: Vec<f64>,
    pub(super) work: Work,
}

impl Replay {
    pub(super) fn new(block: usize, n: usize) -> Self {
        Replay {
            xs: vec![0.0; block * n],
            covs: vec![0.0; block * n * n],
            gains: vec![0.0; block * n],
            nus: vec![0.0; block],
            s_vars: vec![0.0; block],
            x_prior: vec![0.0; n],
            ph: vec![0.0; n],
            work: Work::new(n),
        }
    }

    /// Steps `t0 .. t1` as the forward pass computed them (the same operations).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(super) fn run<const FMA: bool>(
        &mut self,
        k: &Kernel,
        pass: &Forward,
        cp: &Checkpoint,
        t0: usize,
        t1: usize,
    ) {
        let (modes, manoeuvre, caches) = (&pass.modes, &pass.manoeuvre, &pass.caches);
        let n = k.d.n;
        let nn = n * n;
        self.xs[..n].copy_from_slice(&cp.x);
        self.gains[..n].copy_from_slice(&cp.gain);
        if modes[t0] == FULL {
            self.covs[..nn].copy_from_slice(&cp.cov);
        }
        self.nus[0] = cp.nu;
        self.s_vars[0] = cp.s_var;
        for t in t0 + 1..t1 {
            let i = t - t0;
            let (done, rest) = self.xs.split_at_mut(i * n);
            k.predict_mean::<FMA>(t, &done[(i - 1) * n..], &mut self.x_prior);
            let gain = &mut self.gains[i * n..(i + 1) * n];
            let measured = k.p.reading_c[t].is_finite();
            let s_var = if modes[t] != FULL {
                let c = &caches[modes[t] as usize];
                gain.copy_from_slice(&c.gain);
                c.s_var
            } else if pass.memo_of[t] != FULL {
                // a recorded excursion's step: what computing it again would give
                let node = &pass.memo.nodes[pass.memo_of[t] as usize];
                self.covs[i * nn..(i + 1) * nn].copy_from_slice(&node.cov);
                gain.copy_from_slice(&node.gain);
                node.s_var
            } else {
                let (before, after) = self.covs.split_at_mut(i * nn);
                let prev: &[f64] = if modes[t - 1] == FULL {
                    &before[(i - 1) * nn..]
                } else {
                    &caches[modes[t - 1] as usize].cov
                };
                let cov = &mut after[..nn];
                let s_var =
                    k.predict_cov::<FMA>(t, manoeuvre[t], prev, cov, &mut self.ph, &mut self.work);
                if measured {
                    let inv = 1.0 / s_var;
                    for (g, v) in gain.iter_mut().zip(&self.ph) {
                        *g = v * inv;
                    }
                } else {
                    gain.fill(0.0);
                }
                k.filter_cov::<FMA>(cov, gain, &self.ph, measured, None);
                s_var
            };
            let predicted = dot::<FMA>(&k.rows_at(t).h, &self.x_prior) + k.p.t_ref_c;
            let x = &mut rest[..n];
            let mut nu = f64::NAN;
            if measured {
                nu = k.p.reading_c[t] - predicted;
                for ((xi, &pi), &gi) in x.iter_mut().zip(&self.x_prior).zip(gain.iter()) {
                    *xi = madd::<FMA>(gi, nu, pi);
                }
            } else {
                x.copy_from_slice(&self.x_prior);
            }
            self.nus[i] = nu;
            self.s_vars[i] = s_var;
        }
    }
}

/// The modified Bryson-Frazier smoother, backwards over the blocks of the checkpoints:
/// `x_t|N = x_t|t - Σ_t|t λ_t`, `Σ_t|N = Σ_t|t - Σ_t|t Λ_t Σ_t|t`; at a reading
/// `λ̃ = Ĉᵀ λ - h ν/S`, `Λ̃ = Ĉᵀ Λ Ĉ + h hᵀ/S` (`Ĉ = I - K hᵀ`); then `λ_t-1 = Fᵀ λ̃`,
/// `Λ_t-1 = Fᵀ Λ̃ F`. Returns the estimates and the number of steady steps.
#[inline(always)]
pub(super) fn smooth<const FMA: bool>(
    k: &Kernel,
    pass: &Forward,
    settings: &Settings,
) -> (Estimates, usize) {
    let (modes, caches, checkpoints) = (&pass.modes, &pass.caches, &pass.checkpoints);
    let p = k.p;
    let (r, n) = (k.d.r, k.d.n);
    let nn = n * n;
    let n_t = p.reading_c.len();
    let block = settings.checkpoint_steps.max(1);
    let mut est = Estimates::nan(n_t);
    let mut rep = Replay::new(block.min(n_t), n);
    let mut lam = vec![0.0; n];
    let mut lam_t = vec![0.0; n];
    let mut info = Information {
        big: vec![0.0; nn],
        big_new: vec![0.0; nn],
        work: Work::new(n),
        back: None,
    };
    let mut xs_t = vec![0.0; n];
    let mut sc_mean = vec![0.0; n];
    let mut sc_node = vec![0.0; n];
    let mut sc_power = vec![0.0; n];
    let mut q = [vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]];
    let mut node_values = vec![0.0; k.m.next_multiple_of(4)];
    let mut frozen_steps = 0;
    // the largest smoothed face node of the second after (the guess of the fused pass)
    let mut j_next = 0;
    for (b, cp) in checkpoints.iter().enumerate().rev() {
        let t0 = b * block;
        let t1 = (t0 + block).min(n_t);
        rep.run::<FMA>(k, pass, cp, t0, t1);
        for t in (t0..t1).rev() {
            let i = t - t0;
            let mode = modes[t];
            let measured = p.reading_c[t].is_finite();
            let gain = &rep.gains[i * n..(i + 1) * n];
            let x = &rep.xs[i * n..(i + 1) * n];
            let frozen = mode != FULL && info.back.as_ref().is_some_and(|bs| bs.cache == mode);
            let rows = k.rows_at(t);
            // the smoothed state's outputs: c x - (Σ c)·λ
            let (top, j, mean, power);
            let (sig_mean, sig_node, sig_power): (&[f64], &[f64], &[f64]);
            if mode != FULL {
                let c = &caches[mode as usize];
                mean = dot::<FMA>(&rows.cm, &x[..r]) - dot::<FMA>(&c.sig_mean, &lam);
                power = k.power_of(x) - dot::<FMA>(&c.sig_power, &lam);
                (top, j) =
                    k.nodes_max::<FMA>(rows, x, Some((&c.sig_nodes_t, &lam)), &mut node_values);
                sig_mean = &c.sig_mean;
                sig_node = &c.sig_nodes[j * n..(j + 1) * n];
                sig_power = &c.sig_power;
            } else {
                let cov = &rep.covs[i * nn..(i + 1) * nn];
                // one pass: Σλ, Σ c_mean and Σ c_node of the face node that was the largest
                // one second later (usually the largest now: else `times` again, the same bits)
                xs_t.fill(0.0);
                sc_mean.fill(0.0);
                sc_node.fill(0.0);
                gemv_rows3::<FMA>(
                    &lam,
                    &rows.cm[..r],
                    rows.node_row(j_next),
                    cov,
                    n,
                    &mut xs_t,
                    &mut sc_mean,
                    &mut sc_node,
                );
                for (v, xi) in xs_t.iter_mut().zip(x) {
                    *v = xi - *v;
                }
                mean = dot::<FMA>(&rows.cm, &xs_t[..r]);
                power = k.power_of(&xs_t);
                (top, j) = k.nodes_max::<FMA>(rows, &xs_t, None, &mut node_values);
                if j != j_next {
                    k.times::<FMA>(cov, rows.node_row(j), &mut sc_node);
                }
                sig_mean = &sc_mean;
                sig_node = &sc_node;
                sig_power = if k.d.brake {
                    k.sig_power_into(cov, &mut sc_power);
                    &sc_power
                } else {
                    &cov[r * n..(r + 1) * n]
                };
            }
            let (mean_var, node_var, power_var) = match info.back.as_ref().filter(|_| frozen) {
                Some(bs) => {
                    frozen_steps += 1;
                    (bs.mean_var, bs.node_var[j], bs.power_var)
                }
                None => {
                    let sig = [sig_mean, sig_node, sig_power];
                    info.variances::<FMA>(k, rows, j, sig, gain, &mut q[3])
                }
            };
            j_next = j;
            est.mean_c[t] = mean + p.t_ref_c;
            est.mean_sd_k[t] = mean_var.max(0.0).sqrt();
            est.max_c[t] = top + p.t_ref_c;
            est.max_sd_k[t] = node_var.max(0.0).sqrt();
            est.power_w[t] = power;
            est.power_sd_w[t] = power_var.max(0.0).sqrt();
            if t == 0 {
                break;
            }
            // the reading at t, then back through the transition into t
            if measured {
                let s_var = rep.s_vars[i];
                let shift = dot::<FMA>(gain, &lam) + rep.nus[i] / s_var;
                for ((lt, &l), &hi) in lam_t.iter_mut().zip(&lam).zip(&rows.h) {
                    *lt = madd::<FMA>(-hi, shift, l);
                }
            } else {
                lam_t.copy_from_slice(&lam);
            }
            let tr = &k.trs[p.index[t - 1] as usize];
            tr.apply_t::<FMA>(&k.d, &lam_t, &mut lam);
            // back from the transition's basis into the one of the state at t - 1: Tᵀ λ
            let change = k.change(t);
            if let Some(rot) = change {
                rotate_vec::<FMA>(&rot.rt, r, &mut lam, &mut lam_t);
            }
            let update = measured.then(|| (gain, &q[3][..], rep.s_vars[i]));
            info.step_back::<FMA>(k, caches, t, mode, frozen, update);
        }
    }
    (est, frozen_steps)
}

/// The smoother's information matrix `Λ` (`big`; `big_new`: the next one), the scratch of
/// its steps, and its steady state inside a steady stretch of the filter.
struct Information {
    big: Vec<f64>,
    big_new: Vec<f64>,
    work: Work,
    back: Option<BackSteady>,
}

impl Information {
    /// The smoothed variances `c Σ cᵀ - (Σc)ᵀ Λ (Σc)` of the face mean, face node `j` and the
    /// reported power (`sig`: their `Σc`), in one pass over Λ (symmetric): its rows dotted
    /// with Σc for the three outputs and with K (`gain`), the quadratic forms, and ΛK into
    /// `u`.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn variances<const FMA: bool>(
        &self,
        k: &Kernel,
        rows: &Rows,
        j: usize,
        sig: [&[f64]; 3],
        gain: &[f64],
        u: &mut [f64],
    ) -> (f64, f64, f64) {
        let (r, n) = (k.d.r, k.d.n);
        let [sig_mean, sig_node, sig_power] = sig;
        let mut quad = [0.0f64; 3];
        for (row_i, row) in self.big.chunks_exact(n).enumerate() {
            let [dm, dn, dp, du] = dot4::<FMA>(row, sig_mean, sig_node, sig_power, gain);
            quad[0] = madd::<FMA>(sig_mean[row_i], dm, quad[0]);
            quad[1] = madd::<FMA>(sig_node[row_i], dn, quad[1]);
            quad[2] = madd::<FMA>(sig_power[row_i], dp, quad[2]);
            u[row_i] = du;
        }
        (
            dot::<FMA>(&rows.cm, &sig_mean[..r]) - quad[0],
            dot::<FMA>(rows.node_row(j), &sig_node[..r]) - quad[1],
            k.power_of(sig_power) - quad[2],
        )
    }

    /// `Λ` back through the reading at `t` and the transition into `t`: `Λ̃ = Ĉᵀ Λ Ĉ + h hᵀ/S`
    /// (`update` = Some((K, ΛK, S)) at a reading), `Fᵀ Λ̃ F`, back into the basis of the state
    /// at `t - 1`; `frozen`: Λ stays the steady one. Where it stops changing inside a steady
    /// stretch of the filter (cache `mode`), its steady state is kept.
    #[inline(always)]
    fn step_back<const FMA: bool>(
        &mut self,
        k: &Kernel,
        caches: &[Steady],
        t: usize,
        mode: u32,
        frozen: bool,
        update: Option<(&[f64], &[f64], f64)>,
    ) {
        let p = k.p;
        let rows = k.rows_at(t);
        let tr = &k.trs[p.index[t - 1] as usize];
        let change = k.change(t);
        let Information {
            big,
            big_new,
            work,
            back,
        } = self;
        if frozen {
            if let Some(rot) = change {
                // (the steady stretch's first step) Λ stays the steady one: Tᵀ Λ T
                rot.back_cov::<FMA>(&k.d, big, big_new, &mut work.pad);
                std::mem::swap(big, big_new);
            }
            return; // Λ stays the steady one
        }
        *back = None;
        let corr = update.map(|(gain, u, s_var)| (u, dot::<FMA>(gain, u) + 1.0 / s_var));
        match &k.dense[p.index[t - 1] as usize] {
            Some(df) => df.back_cov::<FMA>(&k.d, big, &rows.h, corr, big_new, &mut work.pad),
            None => tr.back_cov::<FMA>(
                &k.d,
                big,
                &rows.h,
                corr,
                big_new,
                &mut work.four,
                &mut work.big,
            ),
        }
        if let Some(rot) = change {
            // Tᵀ Λ T
            rot.back_cov::<FMA>(&k.d, big_new, &mut work.big, &mut work.pad);
            std::mem::swap(big_new, &mut work.big);
        }
        if mode != FULL
            && change.is_none()
            && k.converged_own::<FMA>(
                k.basis_at(t),
                big_new,
                big,
                k.tols_of(caches[mode as usize].key).1,
                work,
            )
        {
            let c = &caches[mode as usize];
            *back = Some(BackSteady::new::<FMA>(
                k,
                c,
                mode,
                rows,
                big_new,
                &mut work.a,
            ));
        }
        std::mem::swap(big, big_new);
    }
}

impl BackSteady {
    /// The smoothed variances of filter cache `c` (its `Σc`) with the steady `Λ` (`lam`;
    /// `tmp`: n scratch).
    #[inline(always)]
    fn new<const FMA: bool>(
        k: &Kernel,
        c: &Steady,
        mode: u32,
        rows: &Rows,
        lam: &[f64],
        tmp: &mut [f64],
    ) -> Self {
        let (r, n) = (k.d.r, k.d.n);
        let mean_var =
            dot::<FMA>(&rows.cm, &c.sig_mean[..r]) - k.quad::<FMA>(lam, &c.sig_mean, tmp);
        let mut node_var = Vec::with_capacity(k.m);
        for jj in 0..k.m {
            let sn = &c.sig_nodes[jj * n..(jj + 1) * n];
            node_var.push(dot::<FMA>(rows.node_row(jj), &sn[..r]) - k.quad::<FMA>(lam, sn, tmp));
        }
        let power_var = k.power_of(&c.sig_power) - k.quad::<FMA>(lam, &c.sig_power, tmp);
        BackSteady {
            cache: mode,
            mean_var,
            node_var,
            power_var,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::filter::forward;
    use crate::estimator::testing::*;
    use crate::estimator::{run, run_led, Outputs};

    #[test]
    fn the_led_smoother_is_the_textbook_smoother_on_the_led_sequence() {
        let lead = 15;
        let mut noise = SWITCHING;
        if let Some(sw) = noise.switching.as_mut() {
            sw.smoother_lead_steps = lead;
        }
        for lag in [false, true] {
            let p = problem(lag, 400, 7);
            for tol in [0.0, 1e-7] {
                let plain = run(&p, SWITCHING, &settings(tol, 64)).unwrap();
                let out = run(&p, noise, &settings(tol, 64)).unwrap();
                // the filter and its reported modes are the filter's own
                assert_eq!(out.manoeuvre, plain.manoeuvre);
                assert_estimates("filtered", &out.filtered, &plain.filtered, 0.0);
                let led = led_modes(&out.manoeuvre, lead).expect("the lead changes the modes");
                let ons: Vec<usize> = (1..400)
                    .filter(|&t| out.manoeuvre[t] && !out.manoeuvre[t - 1])
                    .collect();
                for &t in &ons {
                    assert!(led[t.saturating_sub(lead).max(1)..t].iter().all(|&v| v));
                }
                assert_eq!(led[0], out.manoeuvre[0]);
                let reference = naive_modes(&p, noise, Some(&led));
                let tol_k = if tol == 0.0 { 1e-8 } else { 1e-4 };
                assert_estimates(
                    "smoothed",
                    out.smoothed.as_ref().unwrap(),
                    &reference.smoothed,
                    tol_k,
                );
                let before = plain.smoothed.as_ref().unwrap();
                assert_differ(
                    "the led smoother's power_w",
                    &before.power_w,
                    &out.smoothed.as_ref().unwrap().power_w,
                    1e-6,
                );
            }
        }
        assert_eq!(led_modes(&[false, false, true, true], 0), None);
        assert_eq!(led_modes(&[false, false, false], 5), None);
        assert_eq!(
            led_modes(&[false, false, false, true, false, true], 2),
            Some(vec![false, true, true, true, true, true])
        );
    }

    #[test]
    fn the_led_pass_resumed_from_the_filters_checkpoint_is_the_led_pass_from_the_start() {
        // to the bit, with steady stretches and recorded excursions (the 9,000-step problem
        // repeats its missing readings, dense stretch and gap), blocks before the first
        // changed second or none; resuming one checkpoint too late changes the results
        let lead = 15;
        let mut noise = SWITCHING;
        if let Some(sw) = noise.switching.as_mut() {
            sw.smoother_lead_steps = lead;
        }
        let mut skipped = 0;
        for (lag, n_t, seed, on) in [
            (false, 400, 7, 0),
            (true, 600, 7, 300),
            (false, 9000, 13, 4000),
            (false, 9000, 13, 0),
        ] {
            let p = problem_from(lag, n_t, seed, on);
            for (tol, block) in [
                (0.0, 16),
                (1e-7, 64),
                (1e-7, 16),
                (1e-12, 128),
                (1e-7, 100_000),
            ] {
                let s = settings(tol, block);
                let resumed = run_led::<false>(&p, noise, &s, true);
                let fresh = run_led::<false>(&p, noise, &s, false);
                let what = format!("lag {lag} n {n_t} tol {tol} block {block}");
                let (a, b) = (resumed.smoothed.unwrap(), fresh.smoothed.unwrap());
                for (name, x, y) in [
                    ("mean_c", &a.mean_c, &b.mean_c),
                    ("mean_sd_k", &a.mean_sd_k, &b.mean_sd_k),
                    ("max_c", &a.max_c, &b.max_c),
                    ("max_sd_k", &a.max_sd_k, &b.max_sd_k),
                    ("power_w", &a.power_w, &b.power_w),
                    ("power_sd_w", &a.power_sd_w, &b.power_sd_w),
                ] {
                    let bits = |v: &[f64]| v.iter().map(|z| z.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(x), bits(y), "{what}: smoothed {name}");
                }
                assert_eq!(resumed.smoother_frozen_steps, fresh.smoother_frozen_steps);
                let modes = &resumed.manoeuvre;
                let led = led_modes(modes, lead).expect("the lead changes the modes");
                let first = (1..n_t).find(|&t| led[t] != modes[t]).unwrap();
                skipped += (first - 1) / block;
                // a restart one checkpoint later than the first changed second's block is
                // not the led pass (this test would see it)
                if (first - 1) / block + 1 < n_t.div_ceil(block) && block == 16 {
                    let k = Kernel::new(&p, noise, &s);
                    let mut fwd = forward::<false>(&k, &s, None, None);
                    fwd.outputs = Outputs::default();
                    let quiet = Settings {
                        outputs: false,
                        ..s
                    };
                    let late = forward::<false>(
                        &k,
                        &quiet,
                        Some(&led),
                        Some((fwd, (first - 1) / block + 1)),
                    );
                    let (est, _) = smooth::<false>(&k, &late, &s);
                    assert_differ(
                        "a late restart's smoothed power",
                        &est.power_w,
                        &b.power_w,
                        1e-9,
                    );
                }
            }
        }
        assert!(skipped > 0, "no case resumed after its first block");
    }

    #[test]
    fn the_smoother_does_not_depend_on_its_blocks() {
        let p = problem(true, 700, 3);
        let one = run(&p, NOISE, &settings(1e-12, 700)).unwrap();
        for block in [1, 5, 64] {
            let other = run(&p, NOISE, &settings(1e-12, block)).unwrap();
            assert_eq!(one.smoothed, other.smoothed, "block {block}");
            assert_eq!(one.filtered, other.filtered);
        }
    }
}
