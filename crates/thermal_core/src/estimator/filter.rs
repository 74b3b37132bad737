//! The forward pass: the Kalman filter over every second, its innovation test between the
//! power's noise modes, the steady states and recorded excursions it meets, and the
//! checkpoints it leaves for the smoother.

use super::basis::rotate_vec;
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
// `t` indexes the readings, the modes, the outputs and the steps alike
#[allow(clippy::needless_range_loop)]
#[inline(always)]
pub(super) fn forward<const FMA: bool>(
    k: &Kernel,
    settings: &Settings,
    forced: Option<&[bool]>,
    from: Option<(Forward, usize)>,
) -> Forward {
    let p = k.p;
    let (r, n) = (k.d.r, k.d.n);
    let n_t = p.reading_c.len();
    let block = settings.checkpoint_steps.max(1);
    let mut out = Outputs::default();
    if settings.outputs {
        out.filtered = Estimates::nan(n_t);
        out.innovation_k = vec![f64::NAN; n_t];
        out.innovation_var_k2 = vec![f64::NAN; n_t];
        out.predicted_reading_c = vec![f64::NAN; n_t];
    }
    let mut modes = vec![FULL; n_t];
    let mut caches: Vec<Steady> = Vec::new();
    let mut checkpoints = Vec::new();
    let mut x = p.x0.clone();
    let mut x_prior = vec![0.0; n];
    // `cov`: the filtered covariance of the last full step (during a steady stretch the
    // cache was made from it); `prev`: the one before
    let mut cov = k.prior_cov();
    let mut prev = cov.clone();
    let mut gain = vec![0.0; n];
    let mut acc_mean = vec![0.0; n];
    let mut acc_node = vec![0.0; n];
    let mut node_values = vec![0.0; k.m.next_multiple_of(4)];
    let mut w = Work::new(n);
    let mut steady: Option<usize> = None;
    let mut last = Last::Buf;
    let mut memo = Memo::new(n, settings.replay);
    let mut memo_of = vec![FULL; n_t];
    let mut prev_key: Option<Key> = None;
    let mut manoeuvre_of = vec![false; n_t];
    // the innovation test: the normalised innovations' weighted mean, its standard deviation
    let mut manoeuvre = k.first_mode();
    let mut m_z = 0.0f64;
    let (beta, m_sd) = k.switching.map_or((0.0, 1.0), |s| {
        let b = (1.0 / s.window_steps).min(1.0);
        (b, (b / (2.0 - b)).sqrt())
    });
    let mut start = 0;
    if let Some((f, b)) = from {
        // the state after step t0 = b block (the innovation test's is not needed: the modes
        // are forced)
        debug_assert!(forced.is_some() && !settings.outputs && settings.smooth);
        let t0 = b * block;
        start = t0 + 1;
        let (n_caches, n_nodes) = (f.checkpoints[b].n_caches, f.checkpoints[b].n_nodes);
        (modes, memo_of, manoeuvre_of) = (f.modes, f.memo_of, f.manoeuvre);
        modes[start..].fill(FULL);
        memo_of[start..].fill(FULL);
        (caches, memo, checkpoints) = (f.caches, f.memo, f.checkpoints);
        caches.truncate(n_caches);
        memo.truncate(n_nodes, n_caches);
        checkpoints.truncate(b + 1);
        let cp = &checkpoints[b];
        x.copy_from_slice(&cp.x);
        gain.copy_from_slice(&cp.gain);
        if cp.last == Last::Buf {
            cov.copy_from_slice(&cp.cov);
        }
        (last, steady) = (cp.last, cp.steady);
        prev_key = k.key(t0, manoeuvre_of[t0]);
    }
    for t in start..n_t {
        if let Some(f) = forced {
            manoeuvre = f[t];
        }
        let key = k.key(t, manoeuvre);
        let rows = k.rows_at(t);
        manoeuvre_of[t] = manoeuvre;
        if manoeuvre {
            out.manoeuvre_steps += 1;
        }
        if t > 0 {
            k.predict_mean::<FMA>(t, &x, &mut x_prior);
        } else {
            x_prior.copy_from_slice(&x);
        }
        let measured = p.reading_c[t].is_finite();
        let frozen = steady.filter(|&c| Some(caches[c].key) == key);
        let hit = match (frozen, key) {
            (None, Some(kk)) => memo.child(last, kk),
            _ => None,
        };
        let s_var = match (frozen, hit) {
            (Some(c), _) => {
                out.frozen_steps += 1;
                modes[t] = c as u32;
                gain.copy_from_slice(&caches[c].gain);
                caches[c].s_var
            }
            (None, Some(u)) => {
                out.memo_steps += 1;
                memo_of[t] = u as u32;
                gain.copy_from_slice(&memo.nodes[u].gain);
                memo.nodes[u].s_var
            }
            (None, None) => {
                if last == Last::Buf {
                    std::mem::swap(&mut prev, &mut cov);
                }
                let src: &[f64] = match last {
                    Last::Buf => &prev,
                    Last::Cache(c) => &caches[c].cov,
                    Last::Node(u) => &memo.nodes[u].cov,
                };
                let s_var = k.predict_cov::<FMA>(t, manoeuvre, src, &mut cov, &mut gain, &mut w);
                // `gain` holds Σh: keep it for the update, then scale it into K
                w.b.copy_from_slice(&gain);
                if measured {
                    let inv = 1.0 / s_var;
                    gain.iter_mut().for_each(|v| *v *= inv);
                } else {
                    gain.fill(0.0);
                }
                s_var
            }
        };
        let predicted = dot::<FMA>(&rows.h, &x_prior) + p.t_ref_c;
        let mut nu = f64::NAN;
        if measured {
            nu = p.reading_c[t] - predicted;
            for ((xi, &pi), &gi) in x.iter_mut().zip(&x_prior).zip(&gain) {
                *xi = madd::<FMA>(gi, nu, pi);
            }
            out.log_likelihood -=
                0.5 * ((2.0 * std::f64::consts::PI * s_var).ln() + nu * nu / s_var);
            out.updates += 1;
            m_z = madd::<FMA>(beta, nu / s_var.sqrt() - m_z, m_z);
        } else {
            x.copy_from_slice(&x_prior);
        }
        let (top, j) = if settings.outputs {
            k.nodes_max::<FMA>(rows, &x, None, &mut node_values)
        } else {
            (0.0, 0)
        };
        let (mean_var, node_var, power_var, hold_var) = match (frozen, hit) {
            (Some(c), _) => {
                last = Last::Cache(c);
                let s = &caches[c];
                (s.mean_var, s.node_var[j], s.power_var, s.hold_var)
            }
            (None, Some(u)) => {
                last = Last::Node(u);
                steady = memo.nodes[u].steady;
                if settings.outputs && memo.nodes[u].node_var[j].is_nan() {
                    let c = rows.node_row(j);
                    k.times::<FMA>(&memo.nodes[u].cov, c, &mut w.a);
                    memo.nodes[u].node_var[j] = dot::<FMA>(c, &w.a[..r]);
                }
                let node = &memo.nodes[u];
                (
                    node.mean_var,
                    node.node_var[j],
                    node.power_var,
                    node.hold_var,
                )
            }
            (None, None) => {
                steady = None;
                let ph = std::mem::take(&mut w.b);
                if settings.outputs {
                    let accs = [
                        (&rows.cm[..], &mut acc_mean[..]),
                        (rows.node_row(j), &mut acc_node[..]),
                    ];
                    k.filter_cov::<FMA>(&mut cov, &gain, &ph, measured, Some(accs));
                } else {
                    k.filter_cov::<FMA>(&mut cov, &gain, &ph, measured, None);
                }
                w.b = ph;
                let vars = (
                    dot::<FMA>(&rows.cm, &acc_mean[..r]),
                    dot::<FMA>(rows.node_row(j), &acc_node[..r]),
                    k.power_var_of(&cov),
                    cov[r * n + r],
                );
                if let Some(key_now) = key {
                    let src: &[f64] = match last {
                        Last::Buf => &prev,
                        Last::Cache(c) => &caches[c].cov,
                        Last::Node(u) => &memo.nodes[u].cov,
                    };
                    let tol = k.tols_of(key_now).0;
                    let b = k.basis[key_now.0 as usize];
                    if key == prev_key && k.converged_own::<FMA>(b, &cov, src, tol, &mut w) {
                        // a steady state met before for this key, within the tolerance, is
                        // taken again (so excursions from it are recorded once)
                        let again = caches.iter().position(|c| {
                            c.key == key_now && k.converged_own::<FMA>(b, &cov, &c.cov, tol, &mut w)
                        });
                        steady = Some(again.unwrap_or_else(|| {
                            caches.push(k.make_steady::<FMA>(
                                key_now,
                                &cov,
                                &gain,
                                s_var,
                                settings.smooth,
                            ));
                            caches.len() - 1
                        }));
                    }
                    // a node only where it can be recorded (the copies cost as much as
                    // a fused step's pass)
                    last = if memo.can_record(last) {
                        let mut node_var = vec![f64::NAN; k.m];
                        if settings.outputs {
                            node_var[j] = vars.1;
                        }
                        let node = MemoNode {
                            cov: cov.clone(),
                            gain: gain.clone(),
                            s_var,
                            mean_var: vars.0,
                            power_var: vars.2,
                            hold_var: vars.3,
                            node_var,
                            children: Vec::new(),
                            steady,
                        };
                        match memo.record(last, key_now, node) {
                            Some(u) => Last::Node(u),
                            None => Last::Buf,
                        }
                    } else {
                        Last::Buf
                    };
                } else {
                    last = Last::Buf;
                }
                vars
            }
        };
        if let Some(sw) = k.switching {
            // the mode of the next step
            let z = m_z.abs() / m_sd;
            manoeuvre = if manoeuvre {
                // P's own (the mode sets P's noise, not P_b's)
                z > sw.off_sigma || x[r].abs() > sw.hold_power_sigma * hold_var.max(0.0).sqrt()
            } else {
                z > sw.on_sigma
            };
        }
        if settings.outputs {
            let f = &mut out.filtered;
            f.mean_c[t] = dot::<FMA>(&rows.cm, &x[..r]) + p.t_ref_c;
            f.mean_sd_k[t] = mean_var.max(0.0).sqrt();
            f.max_c[t] = top + p.t_ref_c;
            f.max_sd_k[t] = node_var.max(0.0).sqrt();
            f.power_w[t] = k.power_of(&x);
            f.power_sd_w[t] = power_var.max(0.0).sqrt();
            out.innovation_k[t] = nu;
            out.innovation_var_k2[t] = s_var;
            out.predicted_reading_c[t] = predicted;
        }
        if settings.smooth && t % block == 0 {
            checkpoints.push(Checkpoint {
                x: x.clone(),
                cov: match last {
                    Last::Buf => cov.clone(),
                    Last::Cache(_) => Vec::new(),
                    Last::Node(u) => memo.nodes[u].cov.clone(),
                },
                gain: gain.clone(),
                nu,
                s_var,
                last,
                steady,
                n_caches: caches.len(),
                n_nodes: memo.nodes.len(),
            });
        }
        prev_key = key;
    }
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
