//! What the estimator's tests share: the textbook filter and smoother with dense matrices
//! (the oracle the kernel must equal), small problems with a simulated truth, and the
//! comparisons.

// the reference implementations index as the textbook writes them
#![allow(clippy::needless_range_loop)]

use std::borrow::Cow;

use super::outputs::{Estimates, Outputs};
use super::problem::{Eigen, Noise, Problem, Settings, Switching, Transition};
use super::transition::Dims;

pub(super) fn dot(a: &[f64], b: &[f64]) -> f64 {
    super::linalg::dot::<false>(a, b)
}

/// xorshift64*: reproducible numbers without a dependency.
pub(super) struct Rng(pub(super) u64);

impl Rng {
    pub(super) fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }

    pub(super) fn normal(&mut self) -> f64 {
        let (u, v) = (self.uniform().max(1e-300), self.uniform());
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }
}

pub(super) fn matmul(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
    let mut c = vec![0.0; n * n];
    for i in 0..n {
        for k in 0..n {
            for j in 0..n {
                c[i * n + j] += a[i * n + k] * b[k * n + j];
            }
        }
    }
    c
}

pub(super) fn transpose(a: &[f64], n: usize) -> Vec<f64> {
    (0..n * n).map(|ij| a[(ij % n) * n + ij / n]).collect()
}

pub(super) fn inverse(a: &[f64], n: usize) -> Vec<f64> {
    let mut m = a.to_vec();
    let mut inv: Vec<f64> = (0..n * n)
        .map(|ij| if ij / n == ij % n { 1.0 } else { 0.0 })
        .collect();
    for c in 0..n {
        let piv = (c..n)
            .max_by(|&x, &y| m[x * n + c].abs().total_cmp(&m[y * n + c].abs()))
            .unwrap();
        for j in 0..n {
            m.swap(c * n + j, piv * n + j);
            inv.swap(c * n + j, piv * n + j);
        }
        let d = m[c * n + c];
        for j in 0..n {
            m[c * n + j] /= d;
            inv[c * n + j] /= d;
        }
        for i in (0..n).filter(|&i| i != c) {
            let f = m[i * n + c];
            for j in 0..n {
                m[i * n + j] -= f * m[c * n + j];
                inv[i * n + j] -= f * inv[c * n + j];
            }
        }
    }
    inv
}

pub(super) fn dense_f(p: &Problem<'_>, k: usize) -> Vec<f64> {
    let d = Dims {
        r: p.order,
        n: p.n_state(),
        lag: p.lag,
        brake: p.brake,
    };
    f_matrix(&p.transitions[k], &d)
}

/// F of a transition written out from its parts (`a` r x r, γ, φ, the lag's row and
/// P_b's column), independently of `Transition::apply`.
pub(super) fn f_matrix(t: &Transition, d: &Dims) -> Vec<f64> {
    let (r, n) = (d.r, d.n);
    let mut f = vec![0.0; n * n];
    for i in 0..r {
        f[i * n..i * n + r].copy_from_slice(&t.a[i * r..(i + 1) * r]);
        f[i * n + r] = t.gamma[i];
    }
    f[r * n + r] = t.phi;
    if d.lag {
        f[(r + 1) * n..(r + 1) * n + r].copy_from_slice(&t.lag_row);
        f[(r + 1) * n + r] = t.lag_power;
        f[(r + 1) * n + r + 1] = t.lag_a;
    }
    if d.brake {
        // P_b: heats the modes (and the lag) as P does, decays by its own factor
        let ib = n - 1;
        for i in 0..r {
            f[i * n + ib] = t.gamma[i];
        }
        if d.lag {
            f[(r + 1) * n + ib] = t.lag_power;
        }
        f[ib * n + ib] = t.brake_phi;
    }
    f
}

/// `L̃ = L - h uᵀ - u hᵀ + c h hᵀ` (`corr` = Some((u, c))) or `L`: the smoother's
/// information before the transition, as the covariance steps' `back_cov` take it.
pub(super) fn l_tilde(l: &[f64], h: &[f64], corr: Option<(&[f64], f64)>, n: usize) -> Vec<f64> {
    let mut lt = l.to_vec();
    if let Some((u, c)) = corr {
        for i in 0..n {
            for j in 0..n {
                lt[i * n + j] += -h[i] * u[j] - u[i] * h[j] + c * h[i] * h[j];
            }
        }
    }
    lt
}

/// A small problem: three modes, a diagonal, a dense and a gap-like transition, readings
/// of a simulated truth with noise and missing stretches.
pub(super) fn problem(lag: bool, n_t: usize, seed: u64) -> Problem<'static> {
    problem_from(lag, n_t, seed, 0)
}

/// `problem` with the truth's unexplained power of 2 W from step `power_from` on.
pub(super) fn problem_from(
    lag: bool,
    n_t: usize,
    seed: u64,
    power_from: usize,
) -> Problem<'static> {
    let mut rng = Rng(seed);
    let r = 3;
    let lam = [0.004, 0.2, 1.5];
    let c_probe = vec![0.8, -0.3, 0.1];
    let lag_a = (-1.0f64 / 30.0).exp();
    let lag_c = 30.0 * (1.0 - lag_a) - lag_a;
    let lag_b1 = 1.0 - lag_a - lag_c;
    let make = |a: Vec<f64>, diagonal: bool, gamma: Vec<f64>, phi: f64| {
        let mut at_cp = vec![0.0; r];
        for i in 0..r {
            for kk in 0..r {
                at_cp[i] += a[kk * r + i] * c_probe[kk];
            }
        }
        let lag_row: Vec<f64> = if lag {
            (0..r)
                .map(|i| lag_b1 * at_cp[i] + lag_c * c_probe[i])
                .collect()
        } else {
            vec![0.0; r]
        };
        let lag_power = if lag {
            lag_b1 * dot(&c_probe, &gamma)
        } else {
            0.0
        };
        let e = (0..r).map(|i| a[i * r + i]).collect();
        Transition {
            diagonal,
            a,
            e,
            gamma,
            phi,
            q_unit: 0.5 * 600.0 * (1.0 - phi * phi),
            q_gap: 0.0,
            q_modes: Vec::new(),
            lag_a: if lag { lag_a } else { 0.0 },
            lag_b1: if lag { lag_b1 } else { 0.0 },
            lag_row,
            lag_power,
            applied: false,
            brake_phi: 1.0,
            brake_q: 0.0,
            eigen: None,
        }
    };
    let e: Vec<f64> = lam.iter().map(|l: &f64| (-l).exp()).collect();
    let mut diag = vec![0.0; r * r];
    for i in 0..r {
        diag[i * r + i] = e[i];
    }
    let (cs, sn) = (0.6f64, 0.8f64);
    let q = [cs, -sn, 0.0, sn, cs, 0.0, 0.0, 0.0, 1.0];
    let mut dense = vec![0.0; r * r];
    for i in 0..r {
        for j in 0..r {
            for kk in 0..r {
                dense[i * r + j] += q[i * r + kk] * e[kk] * 0.97 * q[j * r + kk];
            }
        }
    }
    let phi = (-1.0f64 / 600.0).exp();
    let mut transitions = vec![
        make(diag.clone(), true, vec![0.02, 0.01, -0.005], phi),
        make(dense, false, vec![0.015, 0.012, -0.004], phi),
        make(
            diag.iter().map(|v| v * v * v).collect(),
            true,
            vec![0.0; r],
            phi.powi(3),
        ),
    ];
    transitions[1].eigen = Some(Eigen {
        q: q.to_vec(),
        e: e.iter().map(|v| v * 0.97).collect(),
    });
    transitions[2].q_gap = 0.4; // the "gap" transition: the block's offset uncertain
    for t in &mut transitions[..2] {
        t.q_modes = vec![0.0, 3e-4, 0.0]; // a coordinate with noise of its own
    }
    let steps = n_t - 1;
    let index: Vec<u32> = (0..steps)
        .map(|s| match s % 1500 {
            40..=55 | 600..=800 => 1,
            80 | 1000 => 2,
            _ => 0,
        })
        .collect();
    let w: Vec<f64> = (0..steps * r)
        .map(|i| if (i / r) % 50 < 10 { 0.3 } else { 0.01 } * (1.0 + (i % r) as f64))
        .collect();
    let n = r + 1 + usize::from(lag);
    let mut p = Problem {
        order: r,
        lag,
        brake: false,
        t_ref_c: 20.0,
        transitions,
        index: Cow::Owned(index),
        w: Cow::Owned(w),
        power_noise: Cow::Owned(Vec::new()),
        reading_c: Cow::Owned(vec![0.0; n_t]),
        c_probe,
        c_mean: vec![0.5, 0.2, 0.4],
        c_nodes: vec![0.6, 0.3, 0.5, 0.4, 0.5, -0.2, 0.7, -0.1, 0.9],
        x0: vec![0.0; n],
        cov0: vec![0.0; n * n],
        p_prior_unit: 300.0,
        gap_dir: vec![0.0; n],
    };
    p.gap_dir[..r].copy_from_slice(&[0.3, -0.2, 0.5]);
    if lag {
        p.gap_dir[r + 1] = 1.0;
    }
    for i in 0..n {
        p.cov0[i * n + i] = 0.5 + 0.1 * i as f64;
        if i + 1 < n {
            p.cov0[i * n + i + 1] = 0.05;
            p.cov0[(i + 1) * n + i] = 0.05;
        }
    }
    read_truth(&mut p, power_from, &mut rng);
    p
}

/// The readings of `p` (its length's worth): a truth stepped by the model from rest, with an
/// unexplained power of 2 W from step `power_from` on, read with noise and missing stretches.
fn read_truth(p: &mut Problem<'static>, power_from: usize, rng: &mut Rng) {
    let (r, n, lag) = (p.order, p.n_state(), p.lag);
    let n_t = p.reading_c.len();
    let mut x = vec![0.0; n];
    let mut h = vec![0.0; n];
    if lag {
        h[r + 1] = 1.0;
    } else {
        h[..r].copy_from_slice(&p.c_probe);
    }
    for t in 0..n_t {
        if t > 0 {
            let f = dense_f(p, p.index[t - 1] as usize);
            let mut nx = vec![0.0; n];
            for i in 0..n {
                nx[i] = dot(&f[i * n..(i + 1) * n], &x);
            }
            for i in 0..r {
                nx[i] += p.w[(t - 1) * r + i];
            }
            if lag {
                nx[r + 1] += p.transitions[p.index[t - 1] as usize].lag_b1
                    * dot(&p.c_probe, &p.w[(t - 1) * r..t * r]);
            }
            x = nx;
        }
        if t == power_from {
            x[r] = 2.0;
        }
        let missing = (t % 1500 > 1480) || t % 1500 == 7;
        p.reading_c.to_mut()[t] = if missing {
            f64::NAN
        } else {
            dot(&h, &x) + p.t_ref_c + 0.05 * rng.normal()
        };
    }
}

pub(super) struct Naive {
    pub(super) filtered: Estimates,
    pub(super) smoothed: Estimates,
    pub(super) innovation: Vec<f64>,
    pub(super) loglik: f64,
}

/// The textbook filter and Rauch-Tung-Striebel smoother with dense matrices and an
/// inverse, no freezing: what the kernel must equal.
pub(super) fn naive(p: &Problem<'_>, noise: Noise) -> Naive {
    naive_modes(p, noise, None)
}

/// The textbook filter and smoother with σ_w² of each step from the given mode sequence
/// (true: the manoeuvre mode's); None: σ_w everywhere.
pub(super) fn naive_modes(p: &Problem<'_>, noise: Noise, manoeuvre: Option<&[bool]>) -> Naive {
    let (r, n) = (p.order, p.n_state());
    let n_t = p.reading_c.len();
    let mut h = vec![0.0; n];
    if p.lag {
        h[r + 1] = 1.0;
    } else {
        h[..r].copy_from_slice(&p.c_probe);
    }
    let sw2_of = |t: usize| match (manoeuvre, noise.switching) {
        (Some(m), Some(sw)) if !m[t] => {
            let applied = t > 0 && p.transitions[p.index[t - 1] as usize].applied;
            if applied {
                sw.applied_w_per_sqrt_s.powi(2)
            } else {
                sw.quiet_w_per_sqrt_s.powi(2)
            }
        }
        _ => noise.power_w_per_sqrt_s.powi(2),
    };
    let var_v = noise.measurement_k.powi(2);
    let mut x = p.x0.clone();
    let mut cov = p.cov0.clone();
    cov[r * n + r] += sw2_of(0) * p.p_prior_unit;
    let (mut xf, mut pf, mut xp, mut pp) = (vec![], vec![], vec![], vec![]);
    let mut innovation = vec![f64::NAN; n_t];
    let mut loglik = 0.0;
    for t in 0..n_t {
        if t > 0 {
            let k = p.index[t - 1] as usize;
            let f = dense_f(p, k);
            let mut nx = vec![0.0; n];
            for i in 0..n {
                nx[i] = dot(&f[i * n..(i + 1) * n], &x);
            }
            for i in 0..r {
                nx[i] += p.w[(t - 1) * r + i];
            }
            if p.lag {
                nx[r + 1] += p.transitions[k].lag_b1 * dot(&p.c_probe, &p.w[(t - 1) * r..t * r]);
            }
            x = nx;
            cov = matmul(&matmul(&f, &cov, n), &transpose(&f, n), n);
            let pi = p.power_noise.get(t - 1).copied().unwrap_or(0.0);
            cov[r * n + r] += (sw2_of(t) + pi) * p.transitions[k].q_unit;
            if p.brake {
                cov[n * n - 1] += p.transitions[k].brake_q;
            }
            for i in 0..n {
                for j in 0..n {
                    cov[i * n + j] += p.transitions[k].q_gap * p.gap_dir[i] * p.gap_dir[j];
                    if i == j && i < r && !p.transitions[k].q_modes.is_empty() {
                        cov[i * n + j] += p.transitions[k].q_modes[i];
                    }
                }
            }
        }
        xp.push(x.clone());
        pp.push(cov.clone());
        if p.reading_c[t].is_finite() {
            let mut ph = vec![0.0; n];
            for i in 0..n {
                ph[i] = dot(&cov[i * n..(i + 1) * n], &h);
            }
            let s = dot(&h, &ph) + var_v;
            let nu = p.reading_c[t] - dot(&h, &x) - p.t_ref_c;
            innovation[t] = nu;
            loglik -= 0.5 * ((2.0 * std::f64::consts::PI * s).ln() + nu * nu / s);
            for i in 0..n {
                x[i] += ph[i] / s * nu;
                for j in 0..n {
                    cov[i * n + j] -= ph[i] * ph[j] / s;
                }
            }
        }
        xf.push(x.clone());
        pf.push(cov.clone());
    }
    let (mut xs, mut ps) = (xf.clone(), pf.clone());
    for t in (0..n_t - 1).rev() {
        let f = dense_f(p, p.index[t] as usize);
        let g = matmul(
            &matmul(&pf[t], &transpose(&f, n), n),
            &inverse(&pp[t + 1], n),
            n,
        );
        let dx: Vec<f64> = (0..n).map(|i| xs[t + 1][i] - xp[t + 1][i]).collect();
        let dp: Vec<f64> = (0..n * n).map(|i| ps[t + 1][i] - pp[t + 1][i]).collect();
        for i in 0..n {
            xs[t][i] = xf[t][i] + dot(&g[i * n..(i + 1) * n], &dx);
        }
        let gdg = matmul(&matmul(&g, &dp, n), &transpose(&g, n), n);
        for i in 0..n * n {
            ps[t][i] = pf[t][i] + gdg[i];
        }
    }
    let report = |xs: &[Vec<f64>], ps: &[Vec<f64>]| {
        let mut e = Estimates::nan(n_t);
        let pad = |c: &[f64]| {
            let mut v = vec![0.0; n];
            v[..r].copy_from_slice(c);
            v
        };
        let quad = |c: &[f64], m: &[f64]| {
            (0..n)
                .map(|i| c[i] * dot(&m[i * n..(i + 1) * n], c))
                .sum::<f64>()
        };
        for t in 0..n_t {
            let cm = pad(&p.c_mean);
            e.mean_c[t] = dot(&cm, &xs[t]) + p.t_ref_c;
            e.mean_sd_k[t] = quad(&cm, &ps[t]).sqrt();
            let (mut best, mut j) = (f64::NEG_INFINITY, 0);
            for (jj, c) in p.c_nodes.chunks_exact(r).enumerate() {
                let v = dot(c, &xs[t][..r]);
                if v > best {
                    (best, j) = (v, jj);
                }
            }
            e.max_c[t] = best + p.t_ref_c;
            e.max_sd_k[t] = quad(&pad(&p.c_nodes[j * r..(j + 1) * r]), &ps[t]).sqrt();
            // the reported power: P (+ P_b)
            let mut ep = vec![0.0; n];
            ep[r] = 1.0;
            if p.brake {
                ep[n - 1] = 1.0;
            }
            e.power_w[t] = dot(&ep, &xs[t]);
            e.power_sd_w[t] = quad(&ep, &ps[t]).sqrt();
        }
        e
    };
    Naive {
        filtered: report(&xf, &pf),
        smoothed: report(&xs, &ps),
        innovation,
        loglik,
    }
}

/// That two outputs differ somewhere by more than `at_least` (an option changed something).
pub(super) fn assert_differ(name: &str, a: &[f64], b: &[f64], at_least: f64) {
    let diff = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    assert!(diff > at_least, "{name} changed by only {diff}");
}

pub(super) fn assert_close(name: &str, a: &[f64], b: &[f64], tol: f64) {
    assert_eq!(a.len(), b.len(), "{name}: lengths");
    for (t, (x, y)) in a.iter().zip(b).enumerate() {
        if x.is_nan() && y.is_nan() {
            continue;
        }
        let scale = 1.0f64.max(x.abs()).max(y.abs());
        assert!((x - y).abs() <= tol * scale, "{name}[{t}]: {x} vs {y}");
    }
}

pub(super) fn assert_estimates(what: &str, a: &Estimates, b: &Estimates, tol: f64) {
    assert_close(&format!("{what} mean"), &a.mean_c, &b.mean_c, tol);
    assert_close(&format!("{what} mean sd"), &a.mean_sd_k, &b.mean_sd_k, tol);
    assert_close(&format!("{what} max"), &a.max_c, &b.max_c, tol);
    assert_close(&format!("{what} max sd"), &a.max_sd_k, &b.max_sd_k, tol);
    assert_close(&format!("{what} power"), &a.power_w, &b.power_w, tol);
    assert_close(
        &format!("{what} power sd"),
        &a.power_sd_w,
        &b.power_sd_w,
        tol,
    );
}

/// `out` is the textbook filter's and smoother's `reference`: the filtered estimates and
/// the innovations to 1e-9, the smoothed estimates and the log-likelihood to 1e-8.
pub(super) fn assert_textbook(out: &Outputs, reference: &Naive) {
    assert_estimates("filtered", &out.filtered, &reference.filtered, 1e-9);
    let smoothed = out.smoothed.as_ref().unwrap();
    assert_estimates("smoothed", smoothed, &reference.smoothed, 1e-8);
    assert_close("innovation", &out.innovation_k, &reference.innovation, 1e-9);
    let rel = (out.log_likelihood - reference.loglik).abs() / reference.loglik.abs();
    assert!(rel < 1e-8, "log-likelihood {rel}");
}

pub(super) const NOISE: Noise = Noise {
    measurement_k: 0.05,
    power_w_per_sqrt_s: 0.3,
    switching: None,
};

/// Switching between a quiet σ_q = 0.03 and σ_w = 0.3, on a test that leaves the quiet
/// mode now and then on these data.
pub(super) const SWITCHING: Noise = Noise {
    measurement_k: 0.05,
    power_w_per_sqrt_s: 0.3,
    switching: Some(Switching {
        quiet_w_per_sqrt_s: 0.03,
        window_steps: 10.0,
        on_sigma: 2.0,
        off_sigma: 1.0,
        hold_power_sigma: 1.0,
        smoother_lead_steps: 0,
        applied_w_per_sqrt_s: 0.03,
    }),
};

pub(super) fn settings(tol: f64, block: usize) -> Settings {
    Settings {
        smooth: true,
        steady_tolerance: tol,
        smoother_tolerance: tol,
        manoeuvre_tolerances: None,
        checkpoint_steps: block,
        outputs: true,
        replay: true,
    }
}

/// The problem with the braking's power `P_b`: a random walk over the dense transition
/// (the "braking" one here: steps 40-55 and 600-800 of every 1,500), decaying without
/// noise over the diagonal one and the gap.
pub(super) fn brake_problem(lag: bool, n_t: usize, seed: u64) -> Problem<'static> {
    let mut p = problem(lag, n_t, seed);
    let n = p.n_state() + 1;
    p.brake = true;
    for (k, t) in p.transitions.iter_mut().enumerate() {
        (t.brake_phi, t.brake_q) = match k {
            1 => (1.0, 0.04),
            0 => (0.95, 0.0),
            _ => (0.95f64.powi(3), 0.0),
        };
    }
    // the prior and the gap's direction with P_b's entry (0: no braking yet)
    let old = n - 1;
    let mut cov0 = vec![0.0; n * n];
    for i in 0..old {
        cov0[i * n..i * n + old].copy_from_slice(&p.cov0[i * old..(i + 1) * old]);
    }
    cov0[n * n - 1] = 0.3;
    p.cov0 = cov0;
    p.x0.push(0.0);
    p.gap_dir.push(0.0);
    p
}

/// `problem` with a second dense transition (3: another mixing of the first two modes,
/// the third coordinate left alone with a noise of its own, as the seat's error is) and
/// steps that go dense -> dense, dense -> diagonal, diagonal -> dense, into a gap and
/// out of it into a dense run long enough to be steady, with missing readings.
pub(super) fn dense_runs_problem(lag: bool, n_t: usize, seed: u64) -> Problem<'static> {
    let mut p = problem(lag, n_t, seed);
    let r = p.order;
    let e: Vec<f64> = [0.004f64, 0.2, 1.5]
        .iter()
        .map(|l| (-l).exp() * 0.95)
        .collect();
    let (cs, sn) = (0.28f64, 0.96f64);
    let q = [cs, -sn, 0.0, sn, cs, 0.0, 0.0, 0.0, 1.0];
    let mut a = vec![0.0; r * r];
    for i in 0..r {
        for j in 0..r {
            for kk in 0..r {
                a[i * r + j] += q[i * r + kk] * e[kk] * q[j * r + kk];
            }
        }
    }
    let mut tr = p.transitions[1].clone();
    if lag {
        let (la, b1) = (tr.lag_a, tr.lag_b1);
        let c = 30.0 * (1.0 - la) - la;
        tr.lag_row = (0..r)
            .map(|i| {
                b1 * (0..r).map(|kk| a[kk * r + i] * p.c_probe[kk]).sum::<f64>() + c * p.c_probe[i]
            })
            .collect();
        tr.lag_power = b1 * dot(&p.c_probe, &tr.gamma);
    }
    tr.e = (0..r).map(|i| a[i * r + i]).collect();
    tr.a = a;
    tr.eigen = Some(Eigen { q: q.to_vec(), e });
    tr.q_modes = vec![0.0, 0.0, 2e-4];
    p.transitions.push(tr);
    let index: Vec<u32> = (0..n_t - 1)
        .map(|s| match s % 1500 {
            40..=55 | 71..=75 | 801..=820 => 1,
            56..=70 | 81..=90 | 600..=800 | 1001..=1100 => 3,
            80 | 1000 => 2,
            _ => 0,
        })
        .collect();
    p.index = Cow::Owned(index);
    p
}
