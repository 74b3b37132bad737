//! The virtual sensor's kernel: a Kalman filter and a Rauch-Tung-Striebel smoother (in the
//! modified Bryson-Frazier form, which needs no matrix inverse) on a reduced model's state,
//! augmented with an unexplained heat power on the friction face and, optionally, the
//! thermistor's lag.
//!
//! State `x = (ξ, P[, s])`, `n = r + 1 (+ 1)`: the modal state `ξ` (r), the unexplained power
//! `P`, the lagged reading `s`. Transition `k` is
//!
//! ```text
//!     ξ' = A ξ + γ P + w        A diagonal (nominal convection) or dense
//!     P' = φ P + ω              var ω = (σ_w(mode, cylinder applied)² + π_k) q_unit
//!     (ξ, s) += u ε             var ε = q_gap (an unlogged interval: the block's offset)
//!     ξ_i += η_i                var η_i = q_modes_i (the seat's model error, a coordinate)
//!     s' = α s + ℓ·ξ + ℓ_P P + β₁ c_p·w
//! ```
//!
//! With `Problem::brake` the state carries the braking's unexplained power `P_b` as its last
//! entry: it heats the modes as `P` does (`ξ' = A ξ + γ (P + P_b) + w`, the lag's `ℓ_P` on
//! both), `P_b' = φ_b P_b + ω_b` (`var ω_b = q_b`, `Transition::brake_phi`, `brake_q`: a
//! random walk while the declared inputs brake, a decay without noise otherwise), and the
//! reported power is `P + P_b`. Its covariance steps take the fused passes of the diagonal
//! transition with `P_b` as a second border column (`γ` on the modes, `ℓ_P` on the lag).
//!
//! with `w` the modal response to the declared inputs of the step (given per step) and
//! `π_k = (g P_declared,k)²` (W²/s, given per step; `Problem::power_noise`) the share of the
//! power's diffusion that scales with the declared braking power: the declared input's own
//! error (a scale error of the logged pressure) is in proportion to it. A step with `π_k > 0`
//! has no steady-state key: its covariance is always computed (released seconds, `π = 0`,
//! keep the steady path and the replay). The
//! reading is `y = h x + T_ref + v`, `h = c_p` on the modes (or `e_s` with a lag),
//! `var v = σ_v²`; NaN skips the update.
//!
//! The power's noise switches between two modes (`Switching`): a quiet one (`σ_q`, the
//! declared model nearly right) and a manoeuvre one (`σ_w`, a persistent unknown input).
//! The mode of step t+1 is decided after the update at t from a windowed test of the
//! normalised innovations `z = ν/√S`: their exponentially weighted mean
//! `m_t = (1-β) m_t-1 + β z_t` (β = 1/window) has standard deviation `√(β/(2-β))` while the
//! model holds; the manoeuvre mode starts where `|m|` exceeds `on` of those and holds while
//! `|m|` exceeds `off` or the estimated power is more than `hold` standard deviations from
//! zero. The mode sequence is part of the filter's output: the smoother replays it (the same
//! Q at every step), and the steady-state key includes it.
//!
//! Speed comes from the structure: the transition is applied as "diagonal plus a border"
//! (O(n²) per covariance step instead of O(n³)); and where the step's key (transition,
//! reading or not) repeats and the covariance has stopped changing (every element by at
//! most `tol √(Σ_ii Σ_jj)`), the steady gain and covariance are kept and only the mean is
//! stepped (O(n)); a steady state found again for the same key within that tolerance is the
//! one found before, and an excursion from it (the keys that leave it and come back) is
//! recorded the first time and replayed after (`Memo`: the same operations on the same
//! numbers give the same covariances). The smoother runs backwards over blocks of
//! `checkpoint_steps` seconds, each replayed from the filter's checkpoint, so its memory does
//! not grow with the series; its information matrix `Λ` is frozen the same way inside a
//! steady stretch.
//!
//! A dense transition (a convection other than the nominal one mixes the modes) is symmetric,
//! `A = Q diag(e) Qᵀ` with Q orthogonal. Given that decomposition (`Transition::eigen`: the
//! one `A` was made of, `prepare`'s `eigh` of the convection's operator, so the kernel steps
//! the numpy reference's numbers) it is stepped as a diagonal one in the basis of its
//! eigenvectors (`in_own_basis`; Q leaves the seat's error a coordinate of its own), with
//! `γ`, the lag's row, the reading's and the outputs' rows and the gap's direction rotated
//! once per transition (`Rows`), `w` per step (`Qᵀw`), and the mode noise `Qᵀ diag(q) Q`
//! (dense only where Q mixes a noisy coordinate). The state at second t lives in the basis
//! of the transition into t (the prior in the problem's own): where consecutive steps have
//! different bases the mean and covariance are rotated once, `T = diag(Q_newᵀ Q_old, I)`
//! (`Rotation`, two blocked products), the smoother's `λ`, `Λ` back with `Tᵀ`; a run of one
//! dense transition costs what a diagonal one does. Steady keys, caches and recorded
//! excursions are a transition's, so their covariances are in its basis; the steady tests
//! decide as in the problem's own basis (`converged_own`: cheap necessary conditions first,
//! then the element that failed last, then both matrices rotated), so the freezing, and with
//! it the estimates, are those of the dense stepping to rounding. A dense transition without
//! a decomposition is stepped as two blocked products on padded matrices (`DenseF`), the
//! second only on the symmetric result's lower triangle.

use std::borrow::Cow;

use rayon::prelude::*;

use crate::error::{Result, ThermalError};
use crate::simd::{has_avx2_fma, madd};

/// One distinct transition of a problem (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Transition {
    /// Whether `a` is diagonal (then `e` holds its diagonal).
    pub diagonal: bool,
    /// The modal propagator, r x r row-major.
    pub a: Vec<f64>,
    /// The diagonal of `a`.
    pub e: Vec<f64>,
    /// Response of the modes to 1 W of unexplained power over the step.
    pub gamma: Vec<f64>,
    /// Decay of the unexplained power over the step.
    pub phi: f64,
    /// Variance of the power's increment per unit σ_w².
    pub q_unit: f64,
    /// Variance (K²) added over the step to the block's uniform offset (`Problem::gap_dir`):
    /// what an unlogged interval may have done to the block that the model does not know.
    pub q_gap: f64,
    /// Variance added over the step to each modal coordinate (r; empty: none): the reduced
    /// model's error at the sensor seat, carried as a coordinate of its own.
    pub q_modes: Vec<f64>,
    /// Decay of the lagged reading.
    pub lag_a: f64,
    /// Weight of the seat temperature at the step's end in the lagged reading.
    pub lag_b1: f64,
    /// The lag's row of the transition on the modes.
    pub lag_row: Vec<f64>,
    /// The lag's entry on the power.
    pub lag_power: f64,
    /// Whether the cylinder is applied over the step: the quiet mode's noise is then
    /// `Switching::applied_w_per_sqrt_s`.
    pub applied: bool,
    /// Decay of the braking's power `P_b` over the step (`Problem::brake`; 1 while braking).
    pub brake_phi: f64,
    /// Variance (W²) added to `P_b` over the step.
    pub brake_q: f64,
    /// A dense `a`'s eigendecomposition as its maker computed it (`a = Q diag(e) Qᵀ`; the
    /// numpy peer's `prepare`: the `eigh` that `a` is made of): the transition is stepped as
    /// a diagonal one in that basis. None: it is stepped dense (`DenseF`).
    pub eigen: Option<Eigen>,
}

/// The eigenvectors and eigenvalues of a symmetric modal propagator, `a = Q diag(e) Qᵀ`.
#[derive(Debug, Clone, PartialEq)]
pub struct Eigen {
    /// Q, r x r row-major: its columns the eigenvectors (orthonormal).
    pub q: Vec<f64>,
    /// The eigenvalues (r), in the order of Q's columns.
    pub e: Vec<f64>,
}

/// One wagon's filtering problem.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem<'a> {
    pub order: usize,
    pub lag: bool,
    /// Whether the state carries the braking's power `P_b` (its last entry; module docs).
    pub brake: bool,
    pub t_ref_c: f64,
    pub transitions: Vec<Transition>,
    /// Transition of each step (N - 1). The per-step series may be borrowed (from the
    /// caller's arrays, without a copy) or owned.
    pub index: Cow<'a, [u32]>,
    /// (N - 1, r) row-major: modal response to the declared inputs of each step.
    pub w: Cow<'a, [f64]>,
    /// (N - 1, or empty: none) the power's diffusion over each step in proportion to the
    /// declared braking power, `(g P_declared)²`, W²/s (times the transition's `q_unit`).
    pub power_noise: Cow<'a, [f64]>,
    /// Readings (N), NaN where none.
    pub reading_c: Cow<'a, [f64]>,
    pub c_probe: Vec<f64>,
    pub c_mean: Vec<f64>,
    /// (m, r) row-major: the friction-face nodes that stand for the face maximum.
    pub c_nodes: Vec<f64>,
    pub x0: Vec<f64>,
    /// (n, n) row-major, without the power's prior (added as σ_w² `p_prior_unit`).
    pub cov0: Vec<f64>,
    pub p_prior_unit: f64,
    /// (n): the state of a uniform 1 K offset of the block (and of the lagged reading), the
    /// direction of the `q_gap` noise.
    pub gap_dir: Vec<f64>,
}

/// The noise parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Noise {
    /// σ_v, K.
    pub measurement_k: f64,
    /// σ_w, W/√s (the manoeuvre mode's when `switching` is given).
    pub power_w_per_sqrt_s: f64,
    /// The quiet mode and the test that leaves it; None: σ_w at every step.
    pub switching: Option<Switching>,
}

/// Two modes of the power's noise and the innovation test between them (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Switching {
    /// σ_q, W/√s: the quiet mode's diffusion.
    pub quiet_w_per_sqrt_s: f64,
    /// Window of the innovations' exponentially weighted mean, steps (β = 1/window).
    pub window_steps: f64,
    /// The manoeuvre mode starts where |m| exceeds this many of its standard deviations.
    pub on_sigma: f64,
    /// ... and holds while |m| exceeds this many ...
    pub off_sigma: f64,
    /// ... or while |P| exceeds this many of P's filtered standard deviations.
    pub hold_power_sigma: f64,
    /// The smoother's mode sequence: the filter's, with the manoeuvre mode begun this many
    /// steps before each switch-on (the test switches a window after a step of the power;
    /// the smoother, which sees the whole series, lets the power step where it did). Where
    /// that changes the sequence, the smoother runs on a second forward pass with it (resumed
    /// from the filter's checkpoint before the first second it changes). 0: the filter's
    /// sequence.
    pub smoother_lead_steps: usize,
    /// σ_q over a step with the cylinder applied (`Transition::applied`), W/√s.
    pub applied_w_per_sqrt_s: f64,
}

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

/// How to run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings {
    pub smooth: bool,
    /// The filter's covariance counts as steady when no element changed by more than this
    /// times `√(Σ_ii Σ_jj)` in a step (0: only when unchanged).
    pub steady_tolerance: f64,
    /// The same for the smoother's information matrix (which only the smoothed variances
    /// use: the smoothed means do not depend on it).
    pub smoother_tolerance: f64,
    /// The filter's and the smoother's tolerances for the steps in the manoeuvre mode (whose
    /// keys and steady states are their own); None: `steady_tolerance` and
    /// `smoother_tolerance` there too. A loose tolerance freezes the quiet mode's long
    /// settling after each release at little cost to the estimates, while in the manoeuvre
    /// mode, where the power's variance moves fast and the estimates follow it, the same
    /// tolerance moves them by far more (`docs/estimator.md`, session 15).
    pub manoeuvre_tolerances: Option<(f64, f64)>,
    pub checkpoint_steps: usize,
    /// Whether to produce the per-second outputs (false: the likelihood only).
    pub outputs: bool,
    /// Whether to record excursions from steady states and replay them (`Memo`; false:
    /// compute every step that is not frozen, the same numbers).
    pub replay: bool,
}

/// Per-second estimates of one quantity set (filtered or smoothed).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Estimates {
    pub mean_c: Vec<f64>,
    pub mean_sd_k: Vec<f64>,
    pub max_c: Vec<f64>,
    pub max_sd_k: Vec<f64>,
    pub power_w: Vec<f64>,
    pub power_sd_w: Vec<f64>,
}

impl Estimates {
    fn nan(len: usize) -> Self {
        let v = vec![f64::NAN; len];
        Estimates {
            mean_c: v.clone(),
            mean_sd_k: v.clone(),
            max_c: v.clone(),
            max_sd_k: v.clone(),
            power_w: v.clone(),
            power_sd_w: v,
        }
    }
}

/// What a run returns.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Outputs {
    pub filtered: Estimates,
    pub innovation_k: Vec<f64>,
    pub innovation_var_k2: Vec<f64>,
    pub predicted_reading_c: Vec<f64>,
    /// Whether the step into each second used the manoeuvre mode's σ_w (with `switching`;
    /// without, true everywhere).
    pub manoeuvre: Vec<bool>,
    pub manoeuvre_steps: usize,
    pub smoothed: Option<Estimates>,
    pub log_likelihood: f64,
    pub updates: usize,
    pub frozen_steps: usize,
    /// Steps whose covariance was a recorded excursion's (`Memo`), not computed again.
    pub memo_steps: usize,
    pub smoother_frozen_steps: usize,
    pub final_state: Vec<f64>,
    pub final_cov: Vec<f64>,
}

impl Problem<'_> {
    pub fn n_state(&self) -> usize {
        self.order + 1 + usize::from(self.lag) + usize::from(self.brake)
    }

    pub fn n_nodes(&self) -> usize {
        self.c_nodes.len() / self.order.max(1)
    }

    /// Check every length and index.
    pub fn validate(&self) -> Result<()> {
        let r = self.order;
        let n = self.n_state();
        let steps = self.reading_c.len().saturating_sub(1);
        let mismatch = |name: &str, expected: usize, got: usize| {
            Err(ThermalError::LengthMismatch {
                name: name.into(),
                expected,
                got,
            })
        };
        if r == 0 {
            return mismatch("estimator order", 1, 0);
        }
        if self.reading_c.is_empty() {
            return mismatch("estimator readings", 1, 0);
        }
        for (name, len, expected) in [
            ("estimator step index", self.index.len(), steps),
            ("estimator step inputs", self.w.len(), steps * r),
            ("estimator c_probe", self.c_probe.len(), r),
            ("estimator c_mean", self.c_mean.len(), r),
            ("estimator x0", self.x0.len(), n),
            ("estimator cov0", self.cov0.len(), n * n),
            ("estimator gap_dir", self.gap_dir.len(), n),
        ] {
            if len != expected {
                return mismatch(name, expected, len);
            }
        }
        if self.c_nodes.is_empty() || self.c_nodes.len() % r != 0 {
            return mismatch("estimator c_nodes", r, self.c_nodes.len());
        }
        for (k, t) in self.transitions.iter().enumerate() {
            for (name, len, expected) in [
                ("transition a", t.a.len(), r * r),
                ("transition e", t.e.len(), r),
                ("transition gamma", t.gamma.len(), r),
                ("transition lag_row", t.lag_row.len(), r),
            ] {
                if len != expected {
                    return mismatch(&format!("{name} of transition {k}"), expected, len);
                }
            }
            if let Some(Eigen { q, e }) = &t.eigen {
                for (name, len, expected) in [
                    ("transition eigenvectors", q.len(), r * r),
                    ("transition eigenvalues", e.len(), r),
                ] {
                    if len != expected {
                        return mismatch(&format!("{name} of transition {k}"), expected, len);
                    }
                }
                if let Some(&bad) = q.iter().chain(e).find(|v| !v.is_finite()) {
                    return Err(ThermalError::InvalidParameter {
                        name: format!("estimator eigendecomposition of transition {k}"),
                        value: bad,
                        reason: "must be finite".to_string(),
                    });
                }
            }
            if !(t.q_modes.is_empty() || t.q_modes.len() == r) {
                return mismatch(
                    &format!("transition q_modes of transition {k}"),
                    r,
                    t.q_modes.len(),
                );
            }
            if let Some(&bad) = t.q_modes.iter().find(|q| !(q.is_finite() && **q >= 0.0)) {
                return Err(ThermalError::InvalidParameter {
                    name: format!("estimator q_modes of transition {k}"),
                    value: bad,
                    reason: "must be variances (finite, >= 0)".to_string(),
                });
            }
            if !(t.brake_q.is_finite() && t.brake_q >= 0.0 && t.brake_phi.is_finite()) {
                return Err(ThermalError::InvalidParameter {
                    name: format!("estimator brake_q / brake_phi of transition {k}"),
                    value: t.brake_q,
                    reason: "must be a variance (finite, >= 0) and a finite factor".to_string(),
                });
            }
            if !(t.q_gap.is_finite() && t.q_gap >= 0.0) {
                return Err(ThermalError::InvalidParameter {
                    name: format!("estimator q_gap of transition {k}"),
                    value: t.q_gap,
                    reason: "must be a variance (finite, >= 0)".to_string(),
                });
            }
        }
        if let Some(&bad) = self
            .index
            .iter()
            .find(|&&k| k as usize >= self.transitions.len())
        {
            return Err(ThermalError::InvalidParameter {
                name: "estimator transition index".into(),
                value: f64::from(bad),
                reason: format!("only {} transitions", self.transitions.len()),
            });
        }
        if !(self.power_noise.is_empty() || self.power_noise.len() == steps) {
            return mismatch("estimator power_noise", steps, self.power_noise.len());
        }
        if let Some(&bad) = self
            .power_noise
            .iter()
            .find(|q| !(q.is_finite() && **q >= 0.0))
        {
            return Err(ThermalError::InvalidParameter {
                name: "estimator power_noise".into(),
                value: bad,
                reason: "must be variances per second (finite, >= 0)".to_string(),
            });
        }
        crate::error::check_finite("t_ref_c", self.t_ref_c)?;
        Ok(())
    }
}

// ------------------------------------------------------------------------------------------
// Small dense helpers (row-major, n x n). `FMA`: fused multiply-adds, only where the caller
// enables the CPU feature (without it `mul_add` is a call into libm).

/// `Σ a_i b_i` in four partial sums.
#[inline(always)]
fn dot<const FMA: bool>(a: &[f64], b: &[f64]) -> f64 {
    let mut s = [0.0f64; 4];
    let ca = a.chunks_exact(4);
    let cb = b.chunks_exact(4);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            s[l] = madd::<FMA>(x[l], y[l], s[l]);
        }
    }
    let mut t = (s[0] + s[1]) + (s[2] + s[3]);
    for (x, y) in ra.iter().zip(rb) {
        t = madd::<FMA>(*x, *y, t);
    }
    t
}

/// `y += α x`.
#[inline(always)]
fn axpy<const FMA: bool>(alpha: f64, x: &[f64], y: &mut [f64]) {
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi = madd::<FMA>(alpha, *xi, *yi);
    }
}

/// Four dot products of `x` in one pass: `[x·a, x·b, x·c, x·d]`, each summed as `dot` sums
/// it (four lanes, `(l0 + l1) + (l2 + l3)`, then the tail), so equal to four `dot`s to the
/// bit. With FMA: one AVX2 register per product (written out: the compiler's own
/// vectorisation of sixteen scalar accumulators spilled them to the stack).
#[inline(always)]
fn dot4<const FMA: bool>(x: &[f64], a: &[f64], b: &[f64], c: &[f64], d: &[f64]) -> [f64; 4] {
    let n = x.len();
    assert!(a.len() >= n && b.len() >= n && c.len() >= n && d.len() >= n);
    let n4 = n / 4 * 4;
    let mut out = [0.0f64; 4];
    #[cfg(target_arch = "x86_64")]
    if FMA {
        use std::arch::x86_64::*;
        // SAFETY: FMA is only true inside functions compiled with avx2 and fma (`run_avx2`),
        // and every load reads four values below n4 <= the length of each slice.
        unsafe {
            let mut s = [_mm256_setzero_pd(); 4];
            for q in (0..n4).step_by(4) {
                let xv = _mm256_loadu_pd(x.as_ptr().add(q));
                s[0] = _mm256_fmadd_pd(xv, _mm256_loadu_pd(a.as_ptr().add(q)), s[0]);
                s[1] = _mm256_fmadd_pd(xv, _mm256_loadu_pd(b.as_ptr().add(q)), s[1]);
                s[2] = _mm256_fmadd_pd(xv, _mm256_loadu_pd(c.as_ptr().add(q)), s[2]);
                s[3] = _mm256_fmadd_pd(xv, _mm256_loadu_pd(d.as_ptr().add(q)), s[3]);
            }
            for (o, v) in out.iter_mut().zip(s) {
                let mut l = [0.0f64; 4];
                _mm256_storeu_pd(l.as_mut_ptr(), v);
                *o = (l[0] + l[1]) + (l[2] + l[3]);
            }
        }
    }
    #[cfg(target_arch = "x86_64")]
    let vectorised = FMA;
    #[cfg(not(target_arch = "x86_64"))]
    let vectorised = false;
    if !vectorised {
        let mut s = [[0.0f64; 4]; 4];
        for q in (0..n4).step_by(4) {
            for l in 0..4 {
                let xv = x[q + l];
                s[0][l] = madd::<FMA>(xv, a[q + l], s[0][l]);
                s[1][l] = madd::<FMA>(xv, b[q + l], s[1][l]);
                s[2][l] = madd::<FMA>(xv, c[q + l], s[2][l]);
                s[3][l] = madd::<FMA>(xv, d[q + l], s[3][l]);
            }
        }
        for (o, lanes) in out.iter_mut().zip(&s) {
            *o = (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
        }
    }
    for q in n4..n {
        out[0] = madd::<FMA>(x[q], a[q], out[0]);
        out[1] = madd::<FMA>(x[q], b[q], out[1]);
        out[2] = madd::<FMA>(x[q], c[q], out[2]);
        out[3] = madd::<FMA>(x[q], d[q], out[3]);
    }
    out
}

/// `out += Σ_i (σ a_i) rows_i` (σ = ±1) over the first `out.len()` entries of the rows
/// `rows[i stride ..]`, i in order: each entry is the chain of multiply-adds of `axpy` row
/// after row, to the bit. With FMA the entries are held in AVX2 registers by blocks of 16
/// columns while the rows stream past (an `axpy` per row loads and stores the whole output
/// again).
#[inline(always)]
fn gemv_rows<const FMA: bool>(a: &[f64], sign: f64, rows: &[f64], stride: usize, out: &mut [f64]) {
    let w = out.len();
    assert!(w <= stride);
    assert!(a.is_empty() || rows.len() >= (a.len() - 1) * stride + w);
    #[cfg(target_arch = "x86_64")]
    if FMA {
        // SAFETY: FMA is only true inside functions compiled with avx2 and fma (`run_avx2`);
        // the lengths are the ones asserted above.
        unsafe { gemv_rows_avx2(a, sign, rows, stride, out) };
        return;
    }
    for (i, &ai) in a.iter().enumerate() {
        axpy::<FMA>(sign * ai, &rows[i * stride..i * stride + w], out);
    }
}

/// `gemv_rows` with AVX2 and FMA. Caller: the lengths `gemv_rows` asserts.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn gemv_rows_avx2(a: &[f64], sign: f64, rows: &[f64], stride: usize, out: &mut [f64]) {
    use std::arch::x86_64::*;
    let (w, rp, op) = (out.len(), rows.as_ptr(), out.as_mut_ptr());
    // SAFETY: every load reads row i < a.len() at columns below w <= stride (the caller's
    // lengths), every store writes below w.
    unsafe {
        let mut j0 = 0;
        while j0 + 16 <= w {
            let mut s: [__m256d; 4] = std::array::from_fn(|q| _mm256_loadu_pd(op.add(j0 + 4 * q)));
            for (i, &av) in a.iter().enumerate() {
                let ai = _mm256_set1_pd(sign * av);
                let row = rp.add(i * stride + j0);
                for (q, sq) in s.iter_mut().enumerate() {
                    *sq = _mm256_fmadd_pd(ai, _mm256_loadu_pd(row.add(4 * q)), *sq);
                }
            }
            for (q, v) in s.iter().enumerate() {
                _mm256_storeu_pd(op.add(j0 + 4 * q), *v);
            }
            j0 += 16;
        }
        while j0 + 4 <= w {
            let mut s = _mm256_loadu_pd(op.add(j0));
            for (i, &av) in a.iter().enumerate() {
                let x = _mm256_loadu_pd(rp.add(i * stride + j0));
                s = _mm256_fmadd_pd(_mm256_set1_pd(sign * av), x, s);
            }
            _mm256_storeu_pd(op.add(j0), s);
            j0 += 4;
        }
        for j in j0..w {
            let mut s = *op.add(j);
            for (i, &av) in a.iter().enumerate() {
                s = (sign * av).mul_add(*rp.add(i * stride + j), s);
            }
            *op.add(j) = s;
        }
    }
}

/// `gemv_rows` with two more outputs: `out += Σ_i a_i rows_i`, `out2 += Σ_{i < b.len()}
/// b_i rows_i` and `out3 += Σ_{i < b.len()} c_i rows_i` (`c` as long as `b`), each entry the
/// chain of multiply-adds of `axpy` row after row, to the bit (as `gemv_rows`'s and `times`'s:
/// the smoother's `Σλ`, `Σ c_mean` and `Σ c_node` of one face node in one pass over Σ). With
/// FMA the entries are held in AVX2 registers by blocks of 8 columns.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn gemv_rows3<const FMA: bool>(
    a: &[f64],
    b: &[f64],
    c: &[f64],
    rows: &[f64],
    stride: usize,
    out: &mut [f64],
    out2: &mut [f64],
    out3: &mut [f64],
) {
    let w = out.len();
    let nb = b.len();
    assert!(nb <= a.len() && c.len() == nb && w <= stride);
    assert!(out2.len() == w && out3.len() == w);
    assert!(a.is_empty() || rows.len() >= (a.len() - 1) * stride + w);
    #[cfg(target_arch = "x86_64")]
    if FMA {
        // SAFETY: FMA is only true inside functions compiled with avx2 and fma (`run_avx2`);
        // the lengths are the ones asserted above.
        unsafe { gemv_rows3_avx2(a, b, c, rows, stride, out, out2, out3) };
        return;
    }
    for (i, &ai) in a.iter().enumerate() {
        let row = &rows[i * stride..i * stride + w];
        axpy::<FMA>(ai, row, out);
        if i < nb {
            axpy::<FMA>(b[i], row, out2);
            axpy::<FMA>(c[i], row, out3);
        }
    }
}

/// `gemv_rows3` with AVX2 and FMA. Caller: the lengths `gemv_rows3` asserts.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
unsafe fn gemv_rows3_avx2(
    a: &[f64],
    b: &[f64],
    c: &[f64],
    rows: &[f64],
    stride: usize,
    out: &mut [f64],
    out2: &mut [f64],
    out3: &mut [f64],
) {
    use std::arch::x86_64::*;
    let (w, nb, rp) = (out.len(), b.len(), rows.as_ptr());
    let (op, o2p, o3p) = (out.as_mut_ptr(), out2.as_mut_ptr(), out3.as_mut_ptr());
    // SAFETY: every load reads row i < a.len() at columns below w <= stride (the caller's
    // lengths), every store writes below w into outputs of length w.
    unsafe {
        let mut j0 = 0;
        while j0 + 8 <= w {
            let ld = |p: *mut f64| [_mm256_loadu_pd(p.add(j0)), _mm256_loadu_pd(p.add(j0 + 4))];
            let (mut s, mut s2, mut s3) = (ld(op), ld(o2p), ld(o3p));
            for i in 0..nb {
                let row = rp.add(i * stride + j0);
                let (ai, bi, ci) = (
                    _mm256_set1_pd(a[i]),
                    _mm256_set1_pd(b[i]),
                    _mm256_set1_pd(c[i]),
                );
                for q in 0..2 {
                    let x = _mm256_loadu_pd(row.add(4 * q));
                    s[q] = _mm256_fmadd_pd(ai, x, s[q]);
                    s2[q] = _mm256_fmadd_pd(bi, x, s2[q]);
                    s3[q] = _mm256_fmadd_pd(ci, x, s3[q]);
                }
            }
            for (i, &av) in a.iter().enumerate().skip(nb) {
                let (ai, row) = (_mm256_set1_pd(av), rp.add(i * stride + j0));
                for (q, sq) in s.iter_mut().enumerate() {
                    *sq = _mm256_fmadd_pd(ai, _mm256_loadu_pd(row.add(4 * q)), *sq);
                }
            }
            for q in 0..2 {
                _mm256_storeu_pd(op.add(j0 + 4 * q), s[q]);
                _mm256_storeu_pd(o2p.add(j0 + 4 * q), s2[q]);
                _mm256_storeu_pd(o3p.add(j0 + 4 * q), s3[q]);
            }
            j0 += 8;
        }
        for j in j0..w {
            let (mut s, mut s2, mut s3) = (*op.add(j), *o2p.add(j), *o3p.add(j));
            for (i, &av) in a.iter().enumerate() {
                let x = *rp.add(i * stride + j);
                s = av.mul_add(x, s);
                if i < nb {
                    s2 = b[i].mul_add(x, s2);
                    s3 = c[i].mul_add(x, s3);
                }
            }
            *op.add(j) = s;
            *o2p.add(j) = s2;
            *o3p.add(j) = s3;
        }
    }
}

/// The transpose of a rows x cols row-major matrix, its rows padded with zeros to `width`
/// (>= rows) entries.
fn transpose(a: &[f64], rows: usize, cols: usize, width: usize) -> Vec<f64> {
    let mut t = vec![0.0; width * cols];
    for i in 0..rows {
        for j in 0..cols {
            t[j * width + i] = a[i * cols + j];
        }
    }
    t
}

/// The row stride of the padded matrices of the dense products: n rounded up to eight.
#[inline(always)]
fn padded(n: usize) -> usize {
    n.next_multiple_of(8)
}

/// `dst = src` by chunks of 8 (moved in registers: a call of `memcpy` per short row of the
/// padded matrices costs more than the copy).
#[inline(always)]
fn copy_row(dst: &mut [f64], src: &[f64]) {
    assert_eq!(dst.len(), src.len());
    let mut d = dst.chunks_exact_mut(8);
    let mut s = src.chunks_exact(8);
    for (dc, sc) in (&mut d).zip(&mut s) {
        let v: [f64; 8] = sc.try_into().unwrap();
        dc.copy_from_slice(&v);
    }
    for (dv, &sv) in d.into_remainder().iter_mut().zip(s.remainder()) {
        *dv = sv;
    }
}

/// `c = l r` for padded row-major p x p matrices (p a multiple of 8, zeros outside the
/// matrices: `l`'s first `k` columns times `r`'s first `k` rows), for the rows below `rows`
/// (rounded up to 4); `lower`: at least the column blocks of 8 that reach the diagonal (a
/// symmetric product's lower triangle; the rest may be left as it was). Blocks of the result
/// are held in registers. Every element is one chain of multiply-adds over `0..k` in order,
/// so the vectorised and the scalar code sum alike.
#[inline(always)]
fn gemm_padded<const FMA: bool>(
    l: &[f64],
    r: &[f64],
    c: &mut [f64],
    p: usize,
    k: usize,
    rows: usize,
    lower: bool,
) {
    assert!(p % 8 == 0 && k <= p && rows <= p);
    assert!(l.len() >= p * p && r.len() >= p * p && c.len() >= p * p);
    #[cfg(target_arch = "x86_64")]
    if FMA {
        // SAFETY: FMA is only true inside functions compiled with avx2 and fma (`run_avx2`);
        // the sizes are the ones asserted above.
        unsafe { gemm_padded_avx2(l, r, c, p, k, rows, lower) };
        return;
    }
    for i0 in (0..rows).step_by(4) {
        let cols = if lower { (i0 / 8 + 1) * 8 } else { p };
        for j0 in (0..cols).step_by(8) {
            let mut s = [[0.0f64; 8]; 4];
            for q in 0..k {
                let rq = &r[q * p + j0..q * p + j0 + 8];
                for (ii, si) in s.iter_mut().enumerate() {
                    let a = l[(i0 + ii) * p + q];
                    for (v, &b) in si.iter_mut().zip(rq) {
                        *v = madd::<FMA>(a, b, *v);
                    }
                }
            }
            for (ii, si) in s.iter().enumerate() {
                c[(i0 + ii) * p + j0..(i0 + ii) * p + j0 + 8].copy_from_slice(si);
            }
        }
    }
}

/// `gemm_padded` with AVX2 and FMA, by blocks of 6 x 8 (and 4 x 8 where fewer than 6 rows, or
/// 8, are left). Caller: the sizes of `gemm_padded`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn gemm_padded_avx2(
    l: &[f64],
    r: &[f64],
    c: &mut [f64],
    p: usize,
    k: usize,
    rows: usize,
    lower: bool,
) {
    let rows = rows.next_multiple_of(4);
    let mut i0 = 0;
    while i0 < rows {
        let left = rows - i0;
        let height = if left == 4 || left == 8 { 4 } else { 6 };
        let cols = if lower {
            ((i0 + height - 1) / 8 + 1) * 8
        } else {
            p
        };
        for j0 in (0..cols).step_by(8) {
            // SAFETY: i0 + height <= rows <= p, j0 + 8 <= p (p a multiple of 8), k <= p.
            unsafe {
                if height == 6 {
                    block_avx2::<6>(l, r, c, p, k, i0, j0);
                } else {
                    block_avx2::<4>(l, r, c, p, k, i0, j0);
                }
            }
        }
        i0 += height;
    }
}

/// Rows `i0..i0 + H`, columns `j0..j0 + 8` of `gemm_padded`'s product in 2 H registers.
/// Caller: i0 + H <= p, j0 + 8 <= p, k <= p, the slices at least p x p.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn block_avx2<const H: usize>(
    l: &[f64],
    r: &[f64],
    c: &mut [f64],
    p: usize,
    k: usize,
    i0: usize,
    j0: usize,
) {
    use std::arch::x86_64::*;
    let (lp, rp, cp) = (l.as_ptr(), r.as_ptr(), c.as_mut_ptr());
    // SAFETY: the caller's bounds.
    unsafe {
        let mut s = [[_mm256_setzero_pd(); 2]; H];
        for q in 0..k {
            let r0 = _mm256_loadu_pd(rp.add(q * p + j0));
            let r1 = _mm256_loadu_pd(rp.add(q * p + j0 + 4));
            for (ii, si) in s.iter_mut().enumerate() {
                let a = _mm256_broadcast_sd(&*lp.add((i0 + ii) * p + q));
                si[0] = _mm256_fmadd_pd(a, r0, si[0]);
                si[1] = _mm256_fmadd_pd(a, r1, si[1]);
            }
        }
        for (ii, si) in s.iter().enumerate() {
            _mm256_storeu_pd(cp.add((i0 + ii) * p + j0), si[0]);
            _mm256_storeu_pd(cp.add((i0 + ii) * p + j0 + 4), si[1]);
        }
    }
}

/// Every element changed by at most `tol √(d_i d_j)` (d: the new diagonal); stops at the
/// first that did not.
#[inline(always)]
fn converged(new: &[f64], old: &[f64], n: usize, tol: f64, d: &mut [f64]) -> bool {
    for (i, di) in d.iter_mut().enumerate() {
        *di = new[i * n + i].abs().sqrt();
    }
    for i in 0..n {
        let row_new = &new[i * n..(i + 1) * n];
        let row_old = &old[i * n..(i + 1) * n];
        let bound = tol * d[i];
        for j in 0..n {
            if (row_new[j] - row_old[j]).abs() > bound * d[j] {
                return false;
            }
        }
    }
    true
}

/// `converged`'s first element that changed by more (row-major order), None: every one.
#[inline(always)]
fn first_change(
    new: &[f64],
    old: &[f64],
    n: usize,
    tol: f64,
    d: &mut [f64],
) -> Option<(usize, usize)> {
    for (i, di) in d.iter_mut().enumerate() {
        *di = new[i * n + i].abs().sqrt();
    }
    for i in 0..n {
        let bound = tol * d[i];
        for j in 0..n {
            if (new[i * n + j] - old[i * n + j]).abs() > bound * d[j] {
                return Some((i, j));
            }
        }
    }
    None
}

// ------------------------------------------------------------------------------------------
// The transition's structured products

struct Dims {
    r: usize,
    n: usize,
    lag: bool,
    /// The braking's power `P_b` at index n - 1.
    brake: bool,
}

impl Transition {
    /// `out = F x`.
    #[inline(always)]
    fn apply<const FMA: bool>(&self, d: &Dims, x: &[f64], out: &mut [f64]) {
        let r = d.r;
        // the power heating the modes: P (+ P_b)
        let p = if d.brake { x[r] + x[d.n - 1] } else { x[r] };
        if self.diagonal {
            let pairs = self.e.iter().zip(&self.gamma);
            for ((o, &xi), (&e, &g)) in out[..r].iter_mut().zip(&x[..r]).zip(pairs) {
                *o = madd::<FMA>(e, xi, g * p);
            }
        } else {
            let rows = self.a.chunks_exact(r).zip(&self.gamma);
            for (o, (row, &g)) in out[..r].iter_mut().zip(rows) {
                *o = madd::<FMA>(g, p, dot::<FMA>(row, &x[..r]));
            }
        }
        out[r] = self.phi * x[r];
        if d.lag {
            let s = dot::<FMA>(&self.lag_row, &x[..r]);
            out[r + 1] = madd::<FMA>(self.lag_a, x[r + 1], madd::<FMA>(self.lag_power, p, s));
        }
        if d.brake {
            out[d.n - 1] = self.brake_phi * x[d.n - 1];
        }
    }

    /// `out = Fᵀ x`.
    #[inline(always)]
    fn apply_t<const FMA: bool>(&self, d: &Dims, x: &[f64], out: &mut [f64]) {
        let r = d.r;
        let s = if d.lag { x[r + 1] } else { 0.0 };
        if self.diagonal {
            if d.lag {
                let pairs = self.e.iter().zip(&self.lag_row);
                for ((o, &xi), (&e, &l)) in out[..r].iter_mut().zip(&x[..r]).zip(pairs) {
                    *o = madd::<FMA>(e, xi, l * s);
                }
            } else {
                for ((o, &xi), &e) in out[..r].iter_mut().zip(&x[..r]).zip(&self.e) {
                    *o = e * xi;
                }
            }
        } else {
            out[..r].fill(0.0);
            for (k, row) in self.a.chunks_exact(r).enumerate() {
                axpy::<FMA>(x[k], row, &mut out[..r]);
            }
            axpy::<FMA>(s, &self.lag_row, &mut out[..r]);
        }
        let g = dot::<FMA>(&self.gamma, &x[..r]);
        out[r] = madd::<FMA>(self.lag_power, s, madd::<FMA>(self.phi, x[r], g));
        if d.lag {
            out[r + 1] = self.lag_a * s;
        }
        if d.brake {
            let ib = d.n - 1;
            out[ib] = madd::<FMA>(self.lag_power, s, madd::<FMA>(self.brake_phi, x[ib], g));
        }
    }

    /// `out = F X Fᵀ` for a symmetric X (symmetric to rounding) and a diagonal transition
    /// (a dense one: `DenseF::predict_cov`). `a`, `b`: n scratch; `big`: n x n scratch.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn predict_cov<const FMA: bool>(
        &self,
        d: &Dims,
        x: &[f64],
        out: &mut [f64],
        a: &mut [f64],
        b: &mut [f64],
        big: &mut [f64],
        mut ph: Option<(&[f64], &mut [f64])>,
        gap: Option<&[f64]>,
    ) {
        let (r, n) = (d.r, d.n);
        debug_assert!(self.diagonal);
        if let Some((_, acc)) = ph.as_mut() {
            acc.fill(0.0);
        }
        let ib = n - 1;
        // T = X Fᵀ: row P first (every mode row of F X Fᵀ needs it), with P_b its row too
        // and the power heating the modes, T_P + T_Pb
        let tp = &mut *a;
        self.apply::<FMA>(d, &x[r * n..(r + 1) * n], tp);
        let z = &mut *b;
        z.fill(0.0);
        // (`big` holds three rows with P_b, n >= 3; without it only `t` is used)
        let (t, rest) = big.split_at_mut(n);
        let (tb, tsum) = rest.split_at_mut(rest.len().min(n));
        if d.brake {
            self.apply::<FMA>(d, &x[ib * n..], tb);
            for ((s, &pj), &bj) in tsum[..n].iter_mut().zip(tp.iter()).zip(tb.iter()) {
                *s = pj + bj;
            }
        }
        let tpow: &[f64] = if d.brake { &tsum[..n] } else { tp };
        if !d.lag {
            // without a lag no row of T is needed whole: row i of F X Fᵀ is made in one
            // pass, each mode entry of T made where it is used (the same operations)
            for i in 0..r {
                let xi = &x[i * n..(i + 1) * n];
                let xp = if d.brake { xi[r] + xi[ib] } else { xi[r] };
                t[r] = self.phi * xi[r];
                if d.brake {
                    t[ib] = self.brake_phi * xi[ib];
                }
                let (ei, gi) = (self.e[i], self.gamma[i]);
                let o = &mut out[i * n..(i + 1) * n];
                let gap = gap.filter(|u| u[i] != 0.0).map(|u| (self.q_gap * u[i], u));
                let row = PredictRow {
                    o,
                    t,
                    xi,
                    e: &self.e,
                    gamma: &self.gamma,
                    tpow,
                    xp,
                    ei,
                    gi,
                    r,
                };
                match (ph.as_mut(), gap) {
                    (Some((h, acc)), Some((c, u))) => row.run::<FMA, true, true>(acc, h[i], c, u),
                    (Some((h, acc)), None) => row.run::<FMA, true, false>(acc, h[i], 0.0, tpow),
                    (None, Some((c, u))) => row.run::<FMA, false, true>(z, 0.0, c, u),
                    (None, None) => row.run::<FMA, false, false>(z, 0.0, 0.0, tpow),
                }
            }
        }
        for i in (0..r).filter(|_| d.lag) {
            let xi = &x[i * n..(i + 1) * n];
            // the power heating the modes: X_iP (+ X_iPb)
            let xp = if d.brake { xi[r] + xi[ib] } else { xi[r] };
            // row i of T: e ⊙ X_i + γ X_iP on the modes, φ X_iP, and the lag's entry
            for ((tj, &xj), (&ej, &gj)) in t[..r]
                .iter_mut()
                .zip(&xi[..r])
                .zip(self.e.iter().zip(&self.gamma))
            {
                *tj = madd::<FMA>(ej, xj, gj * xp);
            }
            t[r] = self.phi * xi[r];
            if d.brake {
                t[ib] = self.brake_phi * xi[ib];
            }
            if d.lag {
                let s = dot::<FMA>(&self.lag_row, &xi[..r]);
                t[r + 1] = madd::<FMA>(self.lag_a, xi[r + 1], madd::<FMA>(self.lag_power, xp, s));
                axpy::<FMA>(self.lag_row[i], t, z);
            }
            // row i of F T: e_i T_i + γ_i T_P (and its share of Σh, in the same pass)
            let (ei, gi) = (self.e[i], self.gamma[i]);
            let o = &mut out[i * n..(i + 1) * n];
            // `gap`: the mode rows' share of `q_gap u uᵀ` (the caller's pass, done here)
            let gap = gap.filter(|u| u[i] != 0.0).map(|u| (self.q_gap * u[i], u));
            match (ph.as_mut(), gap) {
                (Some((h, acc)), Some((c, u))) => {
                    let hi = h[i];
                    for ((((oj, &tj), &pj), aj), &uj) in o
                        .iter_mut()
                        .zip(t.iter())
                        .zip(tpow.iter())
                        .zip(acc.iter_mut())
                        .zip(u)
                    {
                        let v = madd::<FMA>(ei, tj, gi * pj);
                        *aj = madd::<FMA>(hi, v, *aj);
                        *oj = madd::<FMA>(c, uj, v);
                    }
                }
                (Some((h, acc)), None) => {
                    let hi = h[i];
                    for (((oj, &tj), &pj), aj) in o
                        .iter_mut()
                        .zip(t.iter())
                        .zip(tpow.iter())
                        .zip(acc.iter_mut())
                    {
                        *oj = madd::<FMA>(ei, tj, gi * pj);
                        *aj = madd::<FMA>(hi, *oj, *aj);
                    }
                }
                (None, Some((c, u))) => {
                    for (((oj, &tj), &pj), &uj) in
                        o.iter_mut().zip(t.iter()).zip(tpow.iter()).zip(u)
                    {
                        *oj = madd::<FMA>(c, uj, madd::<FMA>(ei, tj, gi * pj));
                    }
                }
                (None, None) => {
                    for ((oj, &tj), &pj) in o.iter_mut().zip(t.iter()).zip(tpow.iter()) {
                        *oj = madd::<FMA>(ei, tj, gi * pj);
                    }
                }
            }
        }
        for (oj, &pj) in out[r * n..(r + 1) * n].iter_mut().zip(tp.iter()) {
            *oj = self.phi * pj;
        }
        if d.lag {
            // row s: Σ_k ℓ_k T_k + ℓ_P (T_P + T_Pb) + a T_s, with T_s = F X_s
            self.apply::<FMA>(d, &x[(r + 1) * n..(r + 2) * n], t);
            for ((oj, &tj), (&pj, &zj)) in out[(r + 1) * n..(r + 2) * n]
                .iter_mut()
                .zip(t.iter())
                .zip(tpow.iter().zip(z.iter()))
            {
                *oj = madd::<FMA>(self.lag_a, tj, madd::<FMA>(self.lag_power, pj, zj));
            }
        }
        if d.brake {
            // row P_b: φ_b T_Pb
            for (oj, &bj) in out[ib * n..].iter_mut().zip(tb.iter()) {
                *oj = self.brake_phi * bj;
            }
        }
    }

    /// Row k of `L̃ F`: `Fᵀ L_k - h_k Fᵀu + (c h_k - u_k) Fᵀh` (`corr`: u, c, Fᵀu, Fᵀh).
    #[allow(clippy::type_complexity)]
    #[inline(always)]
    fn back_row<const FMA: bool>(
        &self,
        d: &Dims,
        l: &[f64],
        h: &[f64],
        corr: Option<(&[f64], f64, &[f64], &[f64])>,
        k: usize,
        out_row: &mut [f64],
    ) {
        let n = d.n;
        self.apply_t::<FMA>(d, &l[k * n..(k + 1) * n], out_row);
        if let Some((u, c, ftu, fth)) = corr {
            let (hk, uk) = (h[k], u[k]);
            if hk != 0.0 {
                axpy::<FMA>(-hk, ftu, out_row);
            }
            let w = c * hk - uk;
            if w != 0.0 {
                axpy::<FMA>(w, fth, out_row);
            }
        }
    }

    /// `out = Fᵀ L̃ F` with `L̃ = L - h uᵀ - u hᵀ + c h hᵀ` (`corr` = Some((u, c))) or `L`,
    /// for a symmetric L (symmetric to rounding) and a diagonal transition (a dense one:
    /// `DenseF::back_cov`). Row k of `R = L̃ F` is `Fᵀ L_k - h_k Fᵀu + (c h_k - u_k) Fᵀh`
    /// (Fᵀ is linear), then `out = Fᵀ R`. `scratch`: four n vectors.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn back_cov<const FMA: bool>(
        &self,
        d: &Dims,
        l: &[f64],
        h: &[f64],
        corr: Option<(&[f64], f64)>,
        out: &mut [f64],
        scratch: &mut [Vec<f64>; 4],
        big: &mut [f64],
    ) {
        let (r, n) = (d.r, d.n);
        debug_assert!(self.diagonal);
        let [ftu, fth, rs, acc] = scratch;
        if let Some((u, _)) = corr {
            self.apply_t::<FMA>(d, u, ftu);
            self.apply_t::<FMA>(d, h, fth);
        }
        let corr = corr.map(|(u, c)| (u, c, &ftu[..], &fth[..]));
        // Fᵀ has e_i (and ℓ_i) in the mode rows, γ, φ, ℓ_P in the power's (and γ, φ_b, ℓ_P
        // in P_b's: its row gathers the same γ_i R_i in an accumulator of its own)
        let ib = n - 1;
        let accb = &mut big[..n];
        self.back_row::<FMA>(d, l, h, corr, r, acc); // R_P, scaled by φ below
        if d.lag {
            self.back_row::<FMA>(d, l, h, corr, r + 1, rs);
        }
        acc.iter_mut().for_each(|v| *v *= self.phi);
        if d.lag {
            axpy::<FMA>(self.lag_power, rs, acc);
        }
        if d.brake {
            self.back_row::<FMA>(d, l, h, corr, ib, accb); // R_Pb, scaled by φ_b
            accb.iter_mut().for_each(|v| *v *= self.brake_phi);
            if d.lag {
                axpy::<FMA>(self.lag_power, rs, accb);
            }
        }
        for i in 0..r {
            let o = &mut out[i * n..(i + 1) * n];
            let li = &l[i * n..(i + 1) * n];
            // R_i = Fᵀ L_i - h_i Fᵀu + (c h_i - u_i) Fᵀh on the modes, in one pass, then
            // out_i = e_i R_i + ℓ_i R_s and the power's row gathers γ_i R_i
            let ls = if d.lag { li[r + 1] } else { 0.0 };
            let (ei, gi) = (self.e[i], self.gamma[i]);
            let (a1, a2) = match corr {
                Some((u, c, _, _)) => (-h[i], c * h[i] - u[i]),
                None => (0.0, 0.0),
            };
            // the power's and the lag's entries of R_i
            let gl = dot::<FMA>(&self.gamma, &li[..r]);
            let mut rp_i = madd::<FMA>(self.lag_power, ls, madd::<FMA>(self.phi, li[r], gl));
            rp_i = madd::<FMA>(a1, ftu[r], madd::<FMA>(a2, fth[r], rp_i));
            o[r] = rp_i;
            if d.lag {
                let v = self.lag_a * ls;
                o[r + 1] = madd::<FMA>(a1, ftu[r + 1], madd::<FMA>(a2, fth[r + 1], v));
            }
            if d.brake {
                let v = madd::<FMA>(self.lag_power, ls, madd::<FMA>(self.brake_phi, li[ib], gl));
                o[ib] = madd::<FMA>(a1, ftu[ib], madd::<FMA>(a2, fth[ib], v));
            }
            // the mode entries of R_i made and gathered in one pass (the same operations as
            // a pass that makes them and one that gathers them), then the others gathered
            let (e, lr) = (&self.e[..r], &self.lag_row[..r]);
            let (fu, fh, lm) = (&ftu[..r], &fth[..r], &li[..r]);
            let (om, ot) = o.split_at_mut(r);
            let (am, at) = acc[..n].split_at_mut(r);
            if d.brake {
                let (bm, bt) = accb[..n].split_at_mut(r);
                for j in 0..r {
                    let mut v = madd::<FMA>(e[j], lm[j], lr[j] * ls);
                    v = madd::<FMA>(a1, fu[j], v);
                    v = madd::<FMA>(a2, fh[j], v);
                    am[j] = madd::<FMA>(gi, v, am[j]);
                    bm[j] = madd::<FMA>(gi, v, bm[j]);
                    om[j] = v * ei;
                }
                for ((aj, bj), oj) in at.iter_mut().zip(bt.iter_mut()).zip(ot.iter_mut()) {
                    *aj = madd::<FMA>(gi, *oj, *aj);
                    *bj = madd::<FMA>(gi, *oj, *bj);
                    *oj *= ei;
                }
            } else {
                for j in 0..r {
                    let mut v = madd::<FMA>(e[j], lm[j], lr[j] * ls);
                    v = madd::<FMA>(a1, fu[j], v);
                    v = madd::<FMA>(a2, fh[j], v);
                    am[j] = madd::<FMA>(gi, v, am[j]);
                    om[j] = v * ei;
                }
                for (aj, oj) in at.iter_mut().zip(ot.iter_mut()) {
                    *aj = madd::<FMA>(gi, *oj, *aj);
                    *oj *= ei;
                }
            }
            if d.lag {
                axpy::<FMA>(self.lag_row[i], rs, o);
            }
        }
        out[r * n..(r + 1) * n].copy_from_slice(acc);
        if d.lag {
            for (oj, &sj) in out[(r + 1) * n..(r + 2) * n].iter_mut().zip(rs.iter()) {
                *oj = self.lag_a * sj;
            }
        }
        if d.brake {
            out[ib * n..].copy_from_slice(accb);
        }
    }
}

/// Row i of `F X Fᵀ` for a diagonal transition without a lag, in one pass: the mode entries
/// of `T = X Fᵀ` made where they are used, `t` holding its other entries (`P`, `P_b`).
struct PredictRow<'a> {
    o: &'a mut [f64],
    t: &'a [f64],
    xi: &'a [f64],
    e: &'a [f64],
    gamma: &'a [f64],
    tpow: &'a [f64],
    xp: f64,
    ei: f64,
    gi: f64,
    r: usize,
}

impl PredictRow<'_> {
    /// `ACC`: adds `h_i` times the row into `acc` (Σh); `GAP`: adds `c u` (the mode row's
    /// share of `q_gap u uᵀ`). Each entry: `v = e_i T_ij + γ_i T_Pj`, then those, in the
    /// order of `Transition::predict_cov`'s passes.
    #[inline(always)]
    fn run<const FMA: bool, const ACC: bool, const GAP: bool>(
        self,
        acc: &mut [f64],
        hi: f64,
        c: f64,
        u: &[f64],
    ) {
        let (r, n) = (self.r, self.o.len());
        let (ei, gi, xp) = (self.ei, self.gi, self.xp);
        let (o, tpow) = (&mut self.o[..n], &self.tpow[..n]);
        let (acc, u) = (&mut acc[..n], &u[..n]);
        let (xi, e, g) = (&self.xi[..r], &self.e[..r], &self.gamma[..r]);
        for j in 0..r {
            let tj = madd::<FMA>(e[j], xi[j], g[j] * xp);
            let v = madd::<FMA>(ei, tj, gi * tpow[j]);
            if ACC {
                acc[j] = madd::<FMA>(hi, v, acc[j]);
            }
            o[j] = if GAP { madd::<FMA>(c, u[j], v) } else { v };
        }
        for j in r..n {
            let v = madd::<FMA>(ei, self.t[j], gi * tpow[j]);
            if ACC {
                acc[j] = madd::<FMA>(hi, v, acc[j]);
            }
            o[j] = if GAP { madd::<FMA>(c, u[j], v) } else { v };
        }
    }
}

/// A dense transition's F and Fᵀ as padded row-major matrices (`padded(n)` square, zeros
/// outside n x n), made once per problem: its covariance steps are two blocked products
/// (`gemm_padded`), the second only on the symmetric result's lower triangle.
struct DenseF {
    f: Vec<f64>,
    ft: Vec<f64>,
}

impl DenseF {
    /// F from `Transition::apply` on the unit vectors (its columns, exactly).
    fn new(tr: &Transition, d: &Dims) -> Self {
        let (n, p) = (d.n, padded(d.n));
        let mut f = vec![0.0; p * p];
        let mut ft = vec![0.0; p * p];
        let mut unit = vec![0.0; n];
        let mut col = vec![0.0; n];
        for j in 0..n {
            unit[j] = 1.0;
            tr.apply::<false>(d, &unit, &mut col);
            unit[j] = 0.0;
            for (i, &v) in col.iter().enumerate() {
                f[i * p + j] = v;
                ft[j * p + i] = v;
            }
        }
        DenseF { f, ft }
    }

    /// `out` (n x n) from the lower triangle of the padded `c` (`gemm_padded`'s `lower`),
    /// mirrored: exactly symmetric. The mirror is made in `c` by tiles of 8 x 8 (each tile
    /// below the diagonal transposed into its place above it), then the rows are copied
    /// (and, with `ph` = Some((h, acc)), `acc = Σ_i h_i out_i` summed in the same pass).
    #[inline(always)]
    fn unpad_symmetric<const FMA: bool>(
        c: &mut [f64],
        n: usize,
        out: &mut [f64],
        mut ph: Option<(&[f64], &mut [f64])>,
    ) {
        let p = padded(n);
        let tiles = n.div_ceil(8);
        assert!(c.len() >= p * p && out.len() >= n * n && tiles * 8 <= p);
        for ib in 0..tiles {
            for jb in 0..=ib {
                let mut t = [[0.0f64; 8]; 8];
                for (a, ta) in t.iter_mut().enumerate() {
                    ta.copy_from_slice(&c[(ib * 8 + a) * p + jb * 8..][..8]);
                }
                for b in 0..8 {
                    let row = &mut c[(jb * 8 + b) * p + ib * 8..][..8];
                    for (a, v) in row.iter_mut().enumerate() {
                        // on a diagonal tile only the entries above its diagonal
                        if ib != jb || a > b {
                            *v = t[a][b];
                        }
                    }
                }
            }
        }
        if let Some((_, acc)) = ph.as_mut() {
            acc.fill(0.0);
        }
        for (i, (src, dst)) in c.chunks_exact(p).zip(out.chunks_exact_mut(n)).enumerate() {
            copy_row(dst, &src[..n]);
            if let Some((h, acc)) = ph.as_mut().filter(|(h, _)| i < h.len()) {
                axpy::<FMA>(h[i], &src[..n], acc);
            }
        }
    }

    /// `out = F X Fᵀ` for a symmetric X (`Transition::predict_cov`'s dense case), with `Σh`
    /// (h on the modes) into `ph` when given. `pad`: three `padded(n)` square scratch
    /// matrices, zero outside n x n.
    #[inline(always)]
    fn predict_cov<const FMA: bool>(
        &self,
        d: &Dims,
        x: &[f64],
        out: &mut [f64],
        pad: &mut [Vec<f64>; 3],
        ph: Option<(&[f64], &mut [f64])>,
    ) {
        let (n, p) = (d.n, padded(d.n));
        let [xp, tp, cp] = pad;
        for (src, dst) in x.chunks_exact(n).zip(xp.chunks_exact_mut(p)) {
            copy_row(&mut dst[..n], src);
        }
        gemm_padded::<FMA>(&self.f, xp, tp, p, n, n, false); // T = F X
        gemm_padded::<FMA>(tp, &self.ft, cp, p, n, n, true); // T Fᵀ, lower triangle
        Self::unpad_symmetric::<FMA>(cp, n, out, ph);
    }

    /// `out = Fᵀ L̃ F` with `L̃ = L - h uᵀ - u hᵀ + c h hᵀ` (`corr` = Some((u, c))) or `L`, for
    /// a symmetric L (`Transition::back_cov`'s dense case); row i of `L̃` is
    /// `L_i - h_i u + (c h_i - u_i) h`. `pad` as for `predict_cov`.
    #[inline(always)]
    fn back_cov<const FMA: bool>(
        &self,
        d: &Dims,
        l: &[f64],
        h: &[f64],
        corr: Option<(&[f64], f64)>,
        out: &mut [f64],
        pad: &mut [Vec<f64>; 3],
    ) {
        let (n, p) = (d.n, padded(d.n));
        let [lp, tp, cp] = pad;
        for (i, (src, dst)) in l.chunks_exact(n).zip(lp.chunks_exact_mut(p)).enumerate() {
            let dst = &mut dst[..n];
            copy_row(dst, src);
            if let Some((u, c)) = corr {
                let (hi, ui) = (h[i], u[i]);
                if hi != 0.0 {
                    axpy::<FMA>(-hi, u, dst);
                }
                let w = c * hi - ui;
                if w != 0.0 {
                    axpy::<FMA>(w, h, dst);
                }
            }
        }
        gemm_padded::<FMA>(lp, &self.f, tp, p, n, n, false); // R = L̃ F
        gemm_padded::<FMA>(&self.ft, tp, cp, p, n, n, true); // Fᵀ R, lower triangle
        Self::unpad_symmetric::<FMA>(cp, n, out, None);
    }
}

// ------------------------------------------------------------------------------------------
// Dense transitions in their own basis

/// The reading's row, the outputs' rows and the gap's direction in one basis of the modal
/// coordinates: `q` (r x r row-major, its columns the basis vectors in the problem's
/// coordinates; empty: the problem's own basis). A row `c` on the modes is `Qᵀ c` in it.
struct Rows {
    r: usize,
    q: Vec<f64>,
    h: Vec<f64>,
    cm: Vec<f64>,
    /// (m, r) row-major.
    c_nodes: Vec<f64>,
    /// The face nodes' rows transposed (r x m, m padded to a multiple of 4): node values as a
    /// sum of r scaled rows.
    cn_t: Vec<f64>,
    gap_dir: Vec<f64>,
}

impl Rows {
    fn new(p: &Problem<'_>, q: Vec<f64>) -> Self {
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
    fn node_row(&self, j: usize) -> &[f64] {
        &self.c_nodes[j * self.r..(j + 1) * self.r]
    }
}

/// `v = Qᵀ v` (Q r x r row-major; `tmp`: r scratch).
fn rotate_t(q: &[f64], r: usize, v: &mut [f64], tmp: &mut [f64]) {
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
fn in_own_basis(tr: &Transition, r: usize) -> Option<(Vec<f64>, Transition, Vec<f64>)> {
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
fn rotate_vec<const FMA: bool>(rm: &[f64], r: usize, x: &mut [f64], tmp: &mut [f64]) {
    for (t, row) in tmp.iter_mut().zip(rm.chunks_exact(r)) {
        *t = dot::<FMA>(row, &x[..r]);
    }
    x[..r].copy_from_slice(&tmp[..r]);
}

/// The change from one basis of the modal coordinates to another, `T = diag(R, I)` with
/// `R = Q_newᵀ Q_old` (r x r row-major), and `Rᵀ`; `f`: T for the covariance's products
/// (`T X Tᵀ` forwards, `Tᵀ Λ T` backwards, the blocked products of a dense transition).
struct Rotation {
    r: Vec<f64>,
    rt: Vec<f64>,
    f: DenseF,
}

impl Rotation {
    fn new(rm: Vec<f64>, d: &Dims) -> Self {
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

    /// `out = T X Tᵀ` (out of line: the hot loops stay as they were).
    #[inline(never)]
    fn forward_cov<const FMA: bool>(
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
    fn back_cov<const FMA: bool>(
        &self,
        d: &Dims,
        l: &[f64],
        out: &mut [f64],
        pad: &mut [Vec<f64>; 3],
    ) {
        self.f.back_cov::<FMA>(d, l, &[], None, out, pad);
    }
}

// ------------------------------------------------------------------------------------------
// The filter

/// Step `t`'s covariance mode: computed in full, or the steady cache `id`.
const FULL: u32 = u32::MAX;

/// What the covariance step into a second depends on: the transition, a reading or not, the
/// power's noise mode.
type Key = (u32, bool, bool);

/// What stays constant while the filter is steady for one key.
#[derive(Debug, Clone)]
struct Steady {
    key: Key,
    cov: Vec<f64>,
    gain: Vec<f64>,
    s_var: f64,
    mean_var: f64,
    /// Filtered variance of every face node.
    node_var: Vec<f64>,
    power_var: f64,
    /// `P`'s own variance (the manoeuvre mode's hold test; `power_var` without `P_b`).
    hold_var: f64,
    /// `Σ c_mean`, `Σ c_node` (m x n), `Σ e` (the reported power's): the smoother's products
    /// with Σ.
    sig_mean: Vec<f64>,
    sig_nodes: Vec<f64>,
    /// `sig_nodes` transposed (n x m, m padded to a multiple of 4).
    sig_nodes_t: Vec<f64>,
    sig_power: Vec<f64>,
}

/// The filter's checkpoint at the start of a smoother block.
#[derive(Debug, Clone)]
struct Checkpoint {
    x: Vec<f64>,
    /// Empty when the step was steady (the cache has it).
    cov: Vec<f64>,
    gain: Vec<f64>,
    nu: f64,
    s_var: f64,
    /// The pass's state at the checkpoint besides these (a second pass resumes from it):
    /// where the filtered covariance is, the steady cache in force, and how many caches and
    /// recorded excursion steps there were.
    last: Last,
    steady: Option<usize>,
    n_caches: usize,
    n_nodes: usize,
}

/// One recorded step of an excursion from a steady state: the filtered covariance after a
/// step with `key` from its parent (a steady cache or the node before).
#[derive(Debug, Clone)]
struct MemoNode {
    cov: Vec<f64>,
    gain: Vec<f64>,
    s_var: f64,
    mean_var: f64,
    power_var: f64,
    hold_var: f64,
    /// Filtered variance of each face node, NaN until asked for.
    node_var: Vec<f64>,
    children: Vec<(Key, u32)>,
    /// The steady cache the step entered (its convergence test passed there).
    steady: Option<usize>,
}

/// Excursions from steady states, recorded the first time and replayed after: leaving steady
/// cache `c` with the keys `k1, k2, ...` gives the same covariances, gains and steady cache
/// every time (the same operations on the same numbers), so a missing reading in a steady
/// stretch, a switch of convection and back, the first seconds after them, cost the mean's
/// step only the second time. Bounded by `cap` nodes.
struct Memo {
    roots: Vec<Vec<(Key, u32)>>,
    nodes: Vec<MemoNode>,
    cap: usize,
}

/// Where the last filtered covariance is.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Last {
    /// The forward pass's own buffer (`cov`).
    Buf,
    /// A steady cache (a frozen step).
    Cache(usize),
    /// A recorded excursion's node.
    Node(usize),
}

/// Memory for the recorded excursions of one forward pass.
const MEMO_BYTES: usize = 32 << 20;

impl Memo {
    fn new(n: usize, replay: bool) -> Self {
        Memo {
            roots: Vec::new(),
            nodes: Vec::new(),
            cap: if replay {
                MEMO_BYTES / (8 * (n * n + 2 * n + 64))
            } else {
                0
            },
        }
    }

    fn children(&self, last: Last) -> Option<&Vec<(Key, u32)>> {
        match last {
            Last::Buf => None,
            Last::Cache(c) => self.roots.get(c),
            Last::Node(u) => Some(&self.nodes[u].children),
        }
    }

    fn child(&self, last: Last, key: Key) -> Option<usize> {
        self.children(last)?
            .iter()
            .find(|(k, _)| *k == key)
            .map(|&(_, u)| u as usize)
    }

    /// Back to the memo as it was with `n_nodes` nodes and `n_caches` steady caches (nodes and
    /// children are only ever appended).
    fn truncate(&mut self, n_nodes: usize, n_caches: usize) {
        self.nodes.truncate(n_nodes);
        self.roots.truncate(n_caches);
        let keep = |list: &mut Vec<(Key, u32)>| list.retain(|&(_, u)| (u as usize) < n_nodes);
        self.roots.iter_mut().for_each(keep);
        self.nodes
            .iter_mut()
            .for_each(|node| keep(&mut node.children));
    }

    /// Whether a child of `last` would be recorded: `last` is recorded and the memory is not
    /// spent.
    fn can_record(&self, last: Last) -> bool {
        self.nodes.len() < self.cap && !matches!(last, Last::Buf)
    }

    /// Record `node` as the child of `last` for `key`; None when `last` is not recorded or
    /// the memory is spent.
    fn record(&mut self, last: Last, key: Key, node: MemoNode) -> Option<usize> {
        if !self.can_record(last) {
            return None;
        }
        let id = self.nodes.len();
        let list = match last {
            Last::Cache(c) => {
                if self.roots.len() <= c {
                    self.roots.resize(c + 1, Vec::new());
                }
                &mut self.roots[c]
            }
            Last::Node(u) => &mut self.nodes[u].children,
            Last::Buf => unreachable!(),
        };
        list.push((key, id as u32));
        self.nodes.push(node);
        Some(id)
    }
}

/// Scratch vectors of a covariance step.
struct Work {
    a: Vec<f64>,
    b: Vec<f64>,
    d: Vec<f64>,
    big: Vec<f64>,
    four: [Vec<f64>; 4],
    /// The dense products' padded matrices (`DenseF`).
    pad: [Vec<f64>; 3],
    /// A covariance rotated into a transition's basis (n x n).
    rot: Vec<f64>,
    /// Two matrices in the problem's own basis (the steady tests', n x n).
    own: [Vec<f64>; 2],
    /// The element of the problem's own basis that failed the last steady test made there
    /// (tried first the next time: it is usually the same one until the test passes).
    fail: (usize, usize),
}

impl Work {
    fn new(n: usize) -> Self {
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

struct Kernel<'a> {
    p: &'a Problem<'a>,
    d: Dims,
    m: usize,
    var_v: f64,
    /// σ_w² of the quiet and the manoeuvre mode, and of the quiet mode with the cylinder
    /// applied.
    sw2: [f64; 3],
    switching: Option<Switching>,
    /// The steady tests' tolerances, (the filter's, the smoother's), in the quiet mode and in
    /// the manoeuvre mode (indexed by the key's mode).
    tols: [(f64, f64); 2],
    /// The transitions as stepped: a dense one as a diagonal one in its own basis (module
    /// docs), the others as given.
    trs: Vec<Transition>,
    /// The basis of each transition's result (0: the problem's own; `rows`).
    basis: Vec<u32>,
    /// The reading's and the outputs' rows in each basis.
    rows: Vec<Rows>,
    /// The rotation between two bases met in a row (`R = Q_newᵀ Q_old` and `Rᵀ`), by
    /// (old, new).
    rotations: std::collections::HashMap<(u32, u32), Rotation>,
    /// Each transition's mode noise in its basis where it is not diagonal (r x r; empty: it
    /// is, `q_modes`).
    noise_rot: Vec<Vec<f64>>,
    /// Each transition's dense F (None: diagonal, stepped by its structure).
    dense: Vec<Option<DenseF>>,
    /// Whether each transition adds noise to a mode (`q_modes` not all zero).
    mode_noise: Vec<bool>,
}

impl<'a> Kernel<'a> {
    fn new(p: &'a Problem<'a>, noise: Noise, settings: &Settings) -> Self {
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
    fn basis_at(&self, t: usize) -> u32 {
        if t == 0 {
            0
        } else {
            self.basis[self.p.index[t - 1] as usize]
        }
    }

    /// The rows in the basis of the state at second `t`.
    #[inline(always)]
    fn rows_at(&self, t: usize) -> &Rows {
        &self.rows[self.basis_at(t) as usize]
    }

    /// The rotation from the basis `from` to the basis `to`; None where they are the same.
    #[inline(always)]
    fn rotation(&self, from: u32, to: u32) -> Option<&Rotation> {
        (from != to).then(|| &self.rotations[&(from, to)])
    }

    /// The rotation into the basis of step `t`'s transition from the state's at `t - 1`.
    #[inline(always)]
    fn change(&self, t: usize) -> Option<&Rotation> {
        self.rotation(self.basis_at(t - 1), self.basis_at(t))
    }

    /// `converged(new, old)` for two symmetric matrices in basis `b`, as in the problem's own
    /// basis: the steady tests decide as they would on a transition stepped dense (the
    /// answer does not depend on the basis a step is made in). First the tests that need
    /// no rotation, each a consequence of `converged` there (the entries off the modes are
    /// the same in every basis; the modes' traces, their Frobenius norms and each border
    /// column's norm too) and the element that failed there the last time (three products
    /// with an n x n matrix): where one fails, `converged` there fails; else both matrices
    /// rotated (two blocked products).
    #[inline(always)]
    fn converged_own<const FMA: bool>(
        &self,
        b: u32,
        new: &[f64],
        old: &[f64],
        tol: f64,
        w: &mut Work,
    ) -> bool {
        let n = self.d.n;
        match self.rotation(b, 0) {
            None => converged(new, old, n, tol, &mut w.d),
            Some(rot) => self.converged_rotated::<FMA>(rot, new, old, tol, w),
        }
    }

    /// `converged_own` in a basis of a dense transition (out of line).
    #[inline(never)]
    fn converged_rotated<const FMA: bool>(
        &self,
        rot: &Rotation,
        new: &[f64],
        old: &[f64],
        tol: f64,
        w: &mut Work,
    ) -> bool {
        let (r, n) = (self.d.r, self.d.n);
        let diag = |i: usize| new[i * n + i].abs();
        // the entries off the modes
        for i in r..n {
            for j in r..n {
                let dij = (new[i * n + j] - old[i * n + j]).abs();
                if dij > tol * diag(i).sqrt() * diag(j).sqrt() {
                    return false;
                }
            }
        }
        // |Δ_ii| <= tol Σ_ii on the modes: |tr Δ| <= tol tr Σ; |Δ_ij| <= tol √(Σ_ii Σ_jj):
        // ‖Δ‖_F <= tol tr Σ on the modes, ‖Δ_mj‖² <= tol² Σ_jj tr Σ for a border column j
        let trace: f64 = (0..r).map(diag).sum();
        let trace_d: f64 = (0..r).map(|i| new[i * n + i] - old[i * n + i]).sum();
        if trace_d.abs() > tol * trace {
            return false;
        }
        // the element that failed last time, alone (three products with n x n), ...
        let (fi, fj) = w.fail;
        let [vi, vj, u, ui] = &mut w.four;
        for (v, i) in [(&mut *vi, fi), (&mut *vj, fj)] {
            v.fill(0.0);
            if i < r {
                v[..r].copy_from_slice(&rot.r[i * r..(i + 1) * r]);
            } else {
                v[i] = 1.0;
            }
        }
        self.times::<FMA>(new, vj, u);
        let (new_ij, d_j) = (dot::<FMA>(vi, u), dot::<FMA>(vj, u));
        self.times::<FMA>(new, vi, ui);
        let d_i = dot::<FMA>(vi, ui);
        self.times::<FMA>(old, vj, u);
        let old_ij = dot::<FMA>(vi, u);
        if (new_ij - old_ij).abs() > tol * d_i.abs().sqrt() * d_j.abs().sqrt() {
            return false;
        }
        // ... the norms, then every element
        let mut frob = 0.0;
        for i in 0..r {
            for j in 0..r {
                let dij = new[i * n + j] - old[i * n + j];
                frob += dij * dij;
            }
        }
        if frob > tol * tol * trace * trace {
            return false;
        }
        for j in r..n {
            let col: f64 = (0..r)
                .map(|i| (new[i * n + j] - old[i * n + j]).powi(2))
                .sum();
            if col > tol * tol * diag(j) * trace {
                return false;
            }
        }
        let [a, c] = &mut w.own;
        rot.forward_cov::<FMA>(&self.d, new, a, &mut w.pad);
        rot.forward_cov::<FMA>(&self.d, old, c, &mut w.pad);
        match first_change(a, c, n, tol, &mut w.d) {
            Some(ij) => {
                w.fail = ij;
                false
            }
            None => true,
        }
    }

    #[inline(always)]
    fn key(&self, t: usize, manoeuvre: bool) -> Option<Key> {
        // a step whose power noise follows the declared power is never steady
        (t > 0 && self.power_noise(t) == 0.0).then(|| {
            (
                self.p.index[t - 1],
                self.p.reading_c[t].is_finite(),
                manoeuvre,
            )
        })
    }

    /// The steady tests' tolerances (the filter's, the smoother's inside the filter's steady
    /// state) for a step with `key`.
    #[inline(always)]
    fn tols_of(&self, key: Key) -> (f64, f64) {
        self.tols[usize::from(key.2)]
    }

    /// `(g P_declared)²` of the step into `t` (t > 0), W²/s.
    #[inline(always)]
    fn power_noise(&self, t: usize) -> f64 {
        self.p.power_noise.get(t - 1).copied().unwrap_or(0.0)
    }

    /// The reported power of a state (or of a covariance's row combination): `P (+ P_b)`.
    #[inline(always)]
    fn power_of(&self, x: &[f64]) -> f64 {
        let r = self.d.r;
        if self.d.brake {
            x[r] + x[self.d.n - 1]
        } else {
            x[r]
        }
    }

    /// `Σ e` (e: the reported power's row) into `out`.
    #[inline(always)]
    fn sig_power_into(&self, cov: &[f64], out: &mut [f64]) {
        let (r, n) = (self.d.r, self.d.n);
        out.copy_from_slice(&cov[r * n..(r + 1) * n]);
        if self.d.brake {
            for (o, &v) in out.iter_mut().zip(&cov[(n - 1) * n..]) {
                *o += v;
            }
        }
    }

    /// The reported power's variance `eᵀ Σ e`.
    #[inline(always)]
    fn power_var_of(&self, cov: &[f64]) -> f64 {
        let (r, n) = (self.d.r, self.d.n);
        if self.d.brake {
            let ib = n - 1;
            cov[r * n + r] + cov[ib * n + ib] + 2.0 * cov[r * n + ib]
        } else {
            cov[r * n + r]
        }
    }

    /// The mode at the start: the manoeuvre mode only without switching.
    fn first_mode(&self) -> bool {
        self.switching.is_none()
    }

    fn prior_cov(&self) -> Vec<f64> {
        let (r, n) = (self.d.r, self.d.n);
        let mut cov = self.p.cov0.clone();
        cov[r * n + r] += self.sw2[usize::from(self.first_mode())] * self.p.p_prior_unit;
        cov
    }

    /// The mean's prediction into step `t` (t > 0): `x_prior = F x + w`.
    #[inline(always)]
    fn predict_mean<const FMA: bool>(&self, t: usize, x: &[f64], out: &mut [f64]) {
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
    fn predict_cov<const FMA: bool>(
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
    fn filter_cov<const FMA: bool>(
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

    /// Node values `c_j ξ - s_j·λ` (`minus`: Some((s transposed, n x m, λ))) into `v`, and
    /// the largest with its index.
    #[inline(always)]
    fn nodes_max<const FMA: bool>(
        &self,
        rows: &Rows,
        x: &[f64],
        minus: Option<(&[f64], &[f64])>,
        v: &mut [f64],
    ) -> (f64, usize) {
        let (r, m) = (self.d.r, self.m.next_multiple_of(4));
        v.fill(0.0);
        gemv_rows::<FMA>(&x[..r], 1.0, &rows.cn_t, m, &mut v[..m]);
        if let Some((s_t, lam)) = minus {
            gemv_rows::<FMA>(lam, -1.0, s_t, m, &mut v[..m]);
        }
        let mut best = (f64::NEG_INFINITY, 0usize);
        for (j, &vj) in v[..self.m].iter().enumerate() {
            if vj > best.0 {
                best = (vj, j);
            }
        }
        best
    }

    /// `M c` for a symmetric M and `c` on the first entries.
    #[inline(always)]
    fn times<const FMA: bool>(&self, m: &[f64], c: &[f64], out: &mut [f64]) {
        let n = self.d.n;
        out.fill(0.0);
        gemv_rows::<FMA>(&c[..c.len().min(n)], 1.0, m, n, &mut out[..n]);
    }

    /// `sᵀ M s` for a symmetric M (`tmp`: n scratch).
    #[inline(always)]
    fn quad<const FMA: bool>(&self, m: &[f64], s: &[f64], tmp: &mut [f64]) -> f64 {
        self.times::<FMA>(m, s, tmp);
        dot::<FMA>(s, tmp)
    }

    #[inline(always)]
    fn make_steady<const FMA: bool>(
        &self,
        key: Key,
        cov: &[f64],
        gain: &[f64],
        s_var: f64,
        smooth: bool,
    ) -> Steady {
        let (r, n) = (self.d.r, self.d.n);
        // the key's transition's basis
        let rows = &self.rows[self.basis[key.0 as usize] as usize];
        let mut sig_mean = vec![0.0; n];
        self.times::<FMA>(cov, &rows.cm, &mut sig_mean);
        let mut sig_nodes = vec![0.0; self.m * n];
        let mut node_var = Vec::with_capacity(self.m);
        for (j, out) in sig_nodes.chunks_exact_mut(n).enumerate() {
            self.times::<FMA>(cov, rows.node_row(j), out);
            node_var.push(dot::<FMA>(rows.node_row(j), &out[..r]));
        }
        let mean_var = dot::<FMA>(&rows.cm, &sig_mean[..r]);
        let mut sig_power = vec![0.0; n];
        self.sig_power_into(cov, &mut sig_power);
        if !smooth {
            sig_nodes.clear();
        }
        let sig_nodes_t = if smooth {
            transpose(&sig_nodes, self.m, n, self.m.next_multiple_of(4))
        } else {
            Vec::new()
        };
        Steady {
            key,
            cov: cov.to_vec(),
            gain: gain.to_vec(),
            s_var,
            mean_var,
            node_var,
            power_var: self.power_var_of(cov),
            hold_var: cov[r * n + r],
            sig_mean,
            sig_nodes,
            sig_nodes_t,
            sig_power,
        }
    }
}

/// Run one problem.
pub fn run(problem: &Problem<'_>, noise: Noise, settings: &Settings) -> Result<Outputs> {
    problem.validate()?;
    crate::error::check_positive("measurement noise", noise.measurement_k)?;
    crate::error::check_positive("power noise", noise.power_w_per_sqrt_s)?;
    if let Some(sw) = noise.switching {
        crate::error::check_positive("quiet power noise", sw.quiet_w_per_sqrt_s)?;
        crate::error::check_positive("applied quiet power noise", sw.applied_w_per_sqrt_s)?;
        crate::error::check_positive("innovation window", sw.window_steps)?;
        crate::error::check_non_negative("switch-on threshold", sw.on_sigma)?;
        crate::error::check_non_negative("switch-off threshold", sw.off_sigma)?;
        crate::error::check_non_negative("power hold threshold", sw.hold_power_sigma)?;
    }
    crate::error::check_non_negative("steady tolerance", settings.steady_tolerance)?;
    crate::error::check_non_negative("smoother tolerance", settings.smoother_tolerance)?;
    if let Some((filter, smoother)) = settings.manoeuvre_tolerances {
        crate::error::check_non_negative("manoeuvre steady tolerance", filter)?;
        crate::error::check_non_negative("manoeuvre smoother tolerance", smoother)?;
    }
    #[cfg(target_arch = "x86_64")]
    if has_avx2_fma() {
        // SAFETY: the CPU has the features the function is compiled for.
        return Ok(unsafe { run_avx2(problem, noise, settings) });
    }
    Ok(run_generic::<false>(problem, noise, settings))
}

/// Run many problems (one per wagon) in parallel.
pub fn run_many(
    problems: &[Problem<'_>],
    noise: Noise,
    settings: &Settings,
) -> Result<Vec<Outputs>> {
    problems
        .par_iter()
        .map(|p| run(p, noise, settings))
        .collect()
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn run_avx2(problem: &Problem<'_>, noise: Noise, settings: &Settings) -> Outputs {
    run_generic::<true>(problem, noise, settings)
}

#[inline(always)]
fn run_generic<const FMA: bool>(
    problem: &Problem<'_>,
    noise: Noise,
    settings: &Settings,
) -> Outputs {
    run_led::<FMA>(problem, noise, settings, true)
}

/// `resume`: the smoother's second pass on the led mode sequence starts from the filter's
/// checkpoint before the first second whose mode the lead changes (false: from the prior;
/// the same results to the bit, tested).
#[inline(always)]
fn run_led<const FMA: bool>(
    problem: &Problem<'_>,
    noise: Noise,
    settings: &Settings,
    resume: bool,
) -> Outputs {
    let k = Kernel::new(problem, noise, settings);
    let mut fwd = forward::<FMA>(&k, settings, None, None);
    let mut out = std::mem::take(&mut fwd.outputs);
    if settings.smooth {
        let lead = k.switching.map_or(0, |s| s.smoother_lead_steps);
        // the smoother's pass: the filter's, or a second one on the led mode sequence. Up
        // to the step before the first second the lead changes both passes do the same
        // operations on the same numbers: the second one resumes from the filter's last
        // checkpoint before it, with the filter's caches and recorded excursions as they
        // were there.
        let pass = match led_modes(&fwd.manoeuvre, lead) {
            Some(modes) => {
                let quiet = Settings {
                    outputs: false,
                    ..*settings
                };
                let first = (1..modes.len())
                    .find(|&t| modes[t] != fwd.manoeuvre[t])
                    .expect("led modes differ somewhere");
                let block = (first - 1) / settings.checkpoint_steps.max(1);
                let from = resume.then_some((fwd, block));
                forward::<FMA>(&k, &quiet, Some(&modes), from)
            }
            None => fwd,
        };
        let (est, frozen) = smooth::<FMA>(&k, &pass, settings);
        out.smoothed = Some(est);
        out.smoother_frozen_steps = frozen;
    }
    out
}

struct Forward {
    outputs: Outputs,
    modes: Vec<u32>,
    /// The power-noise mode of the step into each second (the smoother replays it).
    manoeuvre: Vec<bool>,
    caches: Vec<Steady>,
    checkpoints: Vec<Checkpoint>,
    memo: Memo,
    /// The recorded node whose covariance step t replayed (FULL: none).
    memo_of: Vec<u32>,
}

/// The forward pass (`forced`: the power noise's mode of each step instead of the test's).
/// `from`: a pass with the same settings and the same modes up to and including the step of
/// its checkpoint `b`, whose checkpoints, caches and recorded excursions are taken and which
/// this pass resumes after that step (only without outputs: those before it are not made).
// `t` indexes the readings, the modes, the outputs and the steps alike
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn forward<const FMA: bool>(
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

/// The smoothed variances while the smoother's information matrix is steady inside one
/// steady stretch of the filter.
struct BackSteady {
    cache: u32,
    mean_var: f64,
    node_var: Vec<f64>,
    power_var: f64,
}

/// One block of the filter replayed from its checkpoint: filtered state, covariance (full
/// steps), gain, innovation and its variance, per step.
struct Replay {
    xs: Vec<f64>,
    covs: Vec<f64>,
    gains: Vec<f64>,
    nus: Vec<f64>,
    s_vars: Vec<f64>,
    x_prior: Vec<f64>,
    ph: Vec<f64>,
    work: Work,
}

impl Replay {
    fn new(block: usize, n: usize) -> Self {
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
    fn run<const FMA: bool>(
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
fn smooth<const FMA: bool>(k: &Kernel, pass: &Forward, settings: &Settings) -> (Estimates, usize) {
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
    let mut big = vec![0.0; nn];
    let mut big_new = vec![0.0; nn];
    let mut work = Work::new(n);
    let mut xs_t = vec![0.0; n];
    let mut sc_mean = vec![0.0; n];
    let mut sc_node = vec![0.0; n];
    let mut sc_power = vec![0.0; n];
    let mut q = [vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]];
    let mut node_values = vec![0.0; k.m.next_multiple_of(4)];
    let mut back: Option<BackSteady> = None;
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
            let frozen = mode != FULL && back.as_ref().is_some_and(|bs| bs.cache == mode);
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
            let (mean_var, node_var, power_var) = match back.as_ref().filter(|_| frozen) {
                Some(bs) => {
                    frozen_steps += 1;
                    (bs.mean_var, bs.node_var[j], bs.power_var)
                }
                None => {
                    // one pass over Λ (symmetric): its rows dotted with Σc for the three
                    // outputs and with K; the quadratic forms (Σc)ᵀΛ(Σc), and ΛK
                    let u = &mut q[3];
                    let mut quad = [0.0f64; 3];
                    for (row_i, row) in big.chunks_exact(n).enumerate() {
                        let [dm, dn, dp, du] =
                            dot4::<FMA>(row, sig_mean, sig_node, sig_power, gain);
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
            if frozen {
                if let Some(rot) = change {
                    // (the steady stretch's first step) Λ stays the steady one: Tᵀ Λ T
                    rot.back_cov::<FMA>(&k.d, &big, &mut big_new, &mut work.pad);
                    std::mem::swap(&mut big, &mut big_new);
                }
                continue; // Λ stays the steady one
            }
            back = None;
            let corr = if measured {
                let u = &q[3];
                Some((&u[..], dot::<FMA>(gain, u) + 1.0 / rep.s_vars[i]))
            } else {
                None
            };
            match &k.dense[p.index[t - 1] as usize] {
                Some(df) => {
                    df.back_cov::<FMA>(&k.d, &big, &rows.h, corr, &mut big_new, &mut work.pad)
                }
                None => tr.back_cov::<FMA>(
                    &k.d,
                    &big,
                    &rows.h,
                    corr,
                    &mut big_new,
                    &mut work.four,
                    &mut work.big,
                ),
            }
            if let Some(rot) = change {
                // Tᵀ Λ T
                rot.back_cov::<FMA>(&k.d, &big_new, &mut work.big, &mut work.pad);
                std::mem::swap(&mut big_new, &mut work.big);
            }
            if mode != FULL
                && change.is_none()
                && k.converged_own::<FMA>(
                    k.basis_at(t),
                    &big_new,
                    &big,
                    k.tols_of(caches[mode as usize].key).1,
                    &mut work,
                )
            {
                let c = &caches[mode as usize];
                let mean_var = dot::<FMA>(&rows.cm, &c.sig_mean[..r])
                    - k.quad::<FMA>(&big_new, &c.sig_mean, &mut work.a);
                let mut node_var = Vec::with_capacity(k.m);
                for jj in 0..k.m {
                    let sn = &c.sig_nodes[jj * n..(jj + 1) * n];
                    node_var.push(
                        dot::<FMA>(rows.node_row(jj), &sn[..r])
                            - k.quad::<FMA>(&big_new, sn, &mut work.a),
                    );
                }
                let power_var =
                    k.power_of(&c.sig_power) - k.quad::<FMA>(&big_new, &c.sig_power, &mut work.a);
                back = Some(BackSteady {
                    cache: mode,
                    mean_var,
                    node_var,
                    power_var,
                });
            }
            std::mem::swap(&mut big, &mut big_new);
        }
    }
    (est, frozen_steps)
}

#[cfg(test)]
// the reference implementations index as the textbook writes them
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    fn dot(a: &[f64], b: &[f64]) -> f64 {
        super::dot::<false>(a, b)
    }

    /// xorshift64*: reproducible numbers without a dependency.
    struct Rng(u64);

    impl Rng {
        fn uniform(&mut self) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
        }

        fn normal(&mut self) -> f64 {
            let (u, v) = (self.uniform().max(1e-300), self.uniform());
            (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
        }
    }

    fn matmul(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
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

    fn transpose(a: &[f64], n: usize) -> Vec<f64> {
        (0..n * n).map(|ij| a[(ij % n) * n + ij / n]).collect()
    }

    fn inverse(a: &[f64], n: usize) -> Vec<f64> {
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

    fn dense_f(p: &Problem<'_>, k: usize) -> Vec<f64> {
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
    fn f_matrix(t: &Transition, d: &Dims) -> Vec<f64> {
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
    fn l_tilde(l: &[f64], h: &[f64], corr: Option<(&[f64], f64)>, n: usize) -> Vec<f64> {
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
    fn problem(lag: bool, n_t: usize, seed: u64) -> Problem<'static> {
        problem_from(lag, n_t, seed, 0)
    }

    /// `problem` with the truth's unexplained power of 2 W from step `power_from` on.
    fn problem_from(lag: bool, n_t: usize, seed: u64, power_from: usize) -> Problem<'static> {
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
        // readings of a truth stepped by the model, with an unexplained power of 2 W
        let mut x = vec![0.0; n];
        let mut h = vec![0.0; n];
        if lag {
            h[r + 1] = 1.0;
        } else {
            h[..r].copy_from_slice(&p.c_probe);
        }
        for t in 0..n_t {
            if t > 0 {
                let f = dense_f(&p, p.index[t - 1] as usize);
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
        p
    }

    struct Naive {
        filtered: Estimates,
        smoothed: Estimates,
        innovation: Vec<f64>,
        loglik: f64,
    }

    /// The textbook filter and Rauch-Tung-Striebel smoother with dense matrices and an
    /// inverse, no freezing: what the kernel must equal.
    fn naive(p: &Problem<'_>, noise: Noise) -> Naive {
        naive_modes(p, noise, None)
    }

    /// The textbook filter and smoother with σ_w² of each step from the given mode sequence
    /// (true: the manoeuvre mode's); None: σ_w everywhere.
    fn naive_modes(p: &Problem<'_>, noise: Noise, manoeuvre: Option<&[bool]>) -> Naive {
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
                    nx[r + 1] +=
                        p.transitions[k].lag_b1 * dot(&p.c_probe, &p.w[(t - 1) * r..t * r]);
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
    fn assert_differ(name: &str, a: &[f64], b: &[f64], at_least: f64) {
        let diff = a
            .iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        assert!(diff > at_least, "{name} changed by only {diff}");
    }

    fn assert_close(name: &str, a: &[f64], b: &[f64], tol: f64) {
        assert_eq!(a.len(), b.len(), "{name}: lengths");
        for (t, (x, y)) in a.iter().zip(b).enumerate() {
            if x.is_nan() && y.is_nan() {
                continue;
            }
            let scale = 1.0f64.max(x.abs()).max(y.abs());
            assert!((x - y).abs() <= tol * scale, "{name}[{t}]: {x} vs {y}");
        }
    }

    fn assert_estimates(what: &str, a: &Estimates, b: &Estimates, tol: f64) {
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
    fn assert_textbook(out: &Outputs, reference: &Naive) {
        assert_estimates("filtered", &out.filtered, &reference.filtered, 1e-9);
        let smoothed = out.smoothed.as_ref().unwrap();
        assert_estimates("smoothed", smoothed, &reference.smoothed, 1e-8);
        assert_close("innovation", &out.innovation_k, &reference.innovation, 1e-9);
        let rel = (out.log_likelihood - reference.loglik).abs() / reference.loglik.abs();
        assert!(rel < 1e-8, "log-likelihood {rel}");
    }

    const NOISE: Noise = Noise {
        measurement_k: 0.05,
        power_w_per_sqrt_s: 0.3,
        switching: None,
    };

    /// Switching between a quiet σ_q = 0.03 and σ_w = 0.3, on a test that leaves the quiet
    /// mode now and then on these data.
    const SWITCHING: Noise = Noise {
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

    fn settings(tol: f64, block: usize) -> Settings {
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

    #[test]
    fn the_kernel_is_the_textbook_filter_and_smoother() {
        for lag in [false, true] {
            let p = problem(lag, 400, 7);
            let reference = naive(&p, NOISE);
            let out = run(&p, NOISE, &settings(0.0, 64)).unwrap();
            assert_textbook(&out, &reference);
            assert!(out.updates > 300);
        }
    }

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

    /// The problem with the braking's power `P_b`: a random walk over the dense transition
    /// (the "braking" one here: steps 40-55 and 600-800 of every 1,500), decaying without
    /// noise over the diagonal one and the gap.
    fn brake_problem(lag: bool, n_t: usize, seed: u64) -> Problem<'static> {
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

    #[test]
    fn the_braking_power_state_keeps_the_fast_paths_exact() {
        for lag in [false, true] {
            let mut p = brake_problem(lag, 6000, 11);
            // forgotten at the release (τ_b = 0): its variance exactly 0 there, so the
            // released stretches settle (a geometric decay never passes the relative test)
            for t in &mut p.transitions {
                if t.brake_q == 0.0 {
                    t.brake_phi = 0.0;
                }
            }
            // a reading missing every 400 s: excursions from the steady states, replayed
            for t in (200..6000).step_by(400) {
                p.reading_c.to_mut()[t] = f64::NAN;
            }
            let exact = run(&p, SWITCHING, &settings(0.0, 256)).unwrap();
            let fast = run(&p, SWITCHING, &settings(1e-7, 256)).unwrap();
            assert!(
                fast.frozen_steps > 0 && fast.memo_steps > 0,
                "{} {}",
                fast.frozen_steps,
                fast.memo_steps
            );
            assert_estimates("filtered", &fast.filtered, &exact.filtered, 1e-4);
            let mut no_replay = settings(1e-7, 256);
            no_replay.replay = false;
            let computed = run(&p, SWITCHING, &no_replay).unwrap();
            assert_estimates(
                "filtered, replayed",
                &fast.filtered,
                &computed.filtered,
                0.0,
            );
            assert_estimates(
                "smoothed, replayed",
                fast.smoothed.as_ref().unwrap(),
                computed.smoothed.as_ref().unwrap(),
                0.0,
            );
        }
    }

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

    /// `problem` with a second dense transition (3: another mixing of the first two modes,
    /// the third coordinate left alone with a noise of its own, as the seat's error is) and
    /// steps that go dense -> dense, dense -> diagonal, diagonal -> dense, into a gap and
    /// out of it into a dense run long enough to be steady, with missing readings.
    fn dense_runs_problem(lag: bool, n_t: usize, seed: u64) -> Problem<'static> {
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
                    b1 * (0..r).map(|kk| a[kk * r + i] * p.c_probe[kk]).sum::<f64>()
                        + c * p.c_probe[i]
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

    #[test]
    fn steady_stretches_change_nothing_but_the_cost() {
        for lag in [false, true] {
            let p = problem(lag, 3000, 11);
            let exact = run(&p, NOISE, &settings(0.0, 128)).unwrap();
            let fast = run(&p, NOISE, &settings(1e-12, 128)).unwrap();
            assert!(fast.frozen_steps > 1000, "{} frozen", fast.frozen_steps);
            assert_estimates("filtered", &fast.filtered, &exact.filtered, 1e-9);
            assert_estimates(
                "smoothed",
                fast.smoothed.as_ref().unwrap(),
                exact.smoothed.as_ref().unwrap(),
                1e-9,
            );
        }
    }

    #[test]
    fn replayed_excursions_are_the_computed_ones() {
        // the problem repeats every 1,500 steps (missing readings, a dense stretch, a gap):
        // the same excursions from the same steady states, recorded once, replayed after
        for (lag, noise) in [(false, NOISE), (true, NOISE), (false, SWITCHING)] {
            let p = problem(lag, 9000, 13);
            for tol in [1e-12, 1e-7] {
                let replayed = run(&p, noise, &settings(tol, 128)).unwrap();
                let mut s = settings(tol, 128);
                s.replay = false;
                let computed = run(&p, noise, &s).unwrap();
                assert_eq!(computed.memo_steps, 0);
                assert!(
                    replayed.memo_steps > 100,
                    "{} replayed at {tol}",
                    replayed.memo_steps
                );
                assert_eq!(replayed.frozen_steps, computed.frozen_steps);
                assert_eq!(replayed.manoeuvre, computed.manoeuvre);
                // the same operations on the same numbers, but the face node's variance (a
                // different order of summation where the replay asks for another node)
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&replayed.innovation_k), bits(&computed.innovation_k));
                assert_eq!(replayed.filtered.mean_c, computed.filtered.mean_c);
                assert_eq!(replayed.final_cov, computed.final_cov);
                assert_estimates("filtered", &replayed.filtered, &computed.filtered, 1e-13);
                assert_estimates(
                    "smoothed",
                    replayed.smoothed.as_ref().unwrap(),
                    computed.smoothed.as_ref().unwrap(),
                    1e-13,
                );
            }
        }
    }

    #[test]
    fn the_default_tolerances_move_estimates_by_nothing_that_matters() {
        let p = problem(false, 3000, 5);
        let exact = run(&p, NOISE, &settings(0.0, 128)).unwrap();
        let mut s = settings(1e-8, 128);
        s.smoother_tolerance = 1e-6;
        let fast = run(&p, NOISE, &s).unwrap();
        assert!(fast.frozen_steps > 1500 && fast.smoother_frozen_steps > 1000);
        let (a, b) = (&fast.filtered, &exact.filtered);
        assert_close("mean", &a.mean_c, &b.mean_c, 1e-7);
        assert_close("power", &a.power_w, &b.power_w, 1e-6);
        assert_close("mean sd", &a.mean_sd_k, &b.mean_sd_k, 1e-6);
        let (a, b) = (fast.smoothed.unwrap(), exact.smoothed.unwrap());
        assert_close("smoothed mean", &a.mean_c, &b.mean_c, 1e-7);
        assert_close("smoothed mean sd", &a.mean_sd_k, &b.mean_sd_k, 1e-4);
        assert_close("smoothed power sd", &a.power_sd_w, &b.power_sd_w, 1e-4);
    }

    #[test]
    fn the_manoeuvre_modes_own_tolerances_apply_to_its_steps_only() {
        let p = problem(false, 3000, 5);
        let with = |tol: f64, manoeuvre: Option<(f64, f64)>| {
            let mut s = settings(tol, 128);
            s.manoeuvre_tolerances = manoeuvre;
            run(&p, SWITCHING, &s).unwrap()
        };
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let frozen = |o: &Outputs| (o.frozen_steps, o.smoother_frozen_steps);
        let loose = with(1e-3, None);
        assert!(loose.manoeuvre_steps > 100, "{}", loose.manoeuvre_steps);
        // the quiet mode's tolerances given again for the manoeuvre mode: the same run
        let again = with(1e-3, Some((1e-3, 1e-3)));
        assert_eq!(frozen(&again), frozen(&loose));
        assert_eq!(again.manoeuvre, loose.manoeuvre);
        assert_eq!(bits(&again.filtered.mean_c), bits(&loose.filtered.mean_c));
        assert_eq!(
            bits(&again.smoothed.as_ref().unwrap().power_sd_w),
            bits(&loose.smoothed.as_ref().unwrap().power_sd_w)
        );
        // the manoeuvre mode held to 0: fewer steady steps, filter and smoother (1,769 and
        // 1,094 against 1,882 and 1,262 when written)
        let held = with(1e-3, Some((0.0, 0.0)));
        assert!(
            held.frozen_steps < loose.frozen_steps,
            "{:?}",
            frozen(&held)
        );
        assert!(held.smoother_frozen_steps < loose.smoother_frozen_steps);
        // the quiet mode exact and the manoeuvre mode loose: more (240 and 187 against 127
        // and 3)
        let exact = with(0.0, None);
        let mixed = with(0.0, Some((1e-3, 1e-3)));
        assert!(
            mixed.frozen_steps > exact.frozen_steps,
            "{:?}",
            frozen(&mixed)
        );
        assert!(mixed.smoother_frozen_steps > exact.smoother_frozen_steps);
        // the settings are checked
        let mut s = settings(1e-7, 128);
        s.manoeuvre_tolerances = Some((1e-7, -1.0));
        assert!(run(&p, SWITCHING, &s).is_err());
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

    #[test]
    fn many_problems_at_once_are_each_alone() {
        let problems = [problem(false, 300, 1), problem(true, 500, 2)];
        let all = run_many(&problems, NOISE, &settings(1e-12, 64)).unwrap();
        for (p, out) in problems.iter().zip(&all) {
            let alone = run(p, NOISE, &settings(1e-12, 64)).unwrap();
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&out.innovation_k), bits(&alone.innovation_k));
            assert_eq!(out.filtered, alone.filtered);
            assert_eq!(out.smoothed, alone.smoothed);
            assert_eq!(out.log_likelihood, alone.log_likelihood);
        }
    }

    #[test]
    fn bad_problems_are_errors() {
        let mut p = problem(false, 50, 1);
        p.index.to_mut()[3] = 9;
        assert!(run(&p, NOISE, &settings(0.0, 8)).is_err());
        let mut p = problem(false, 50, 1);
        p.w.to_mut().pop();
        assert!(run(&p, NOISE, &settings(0.0, 8)).is_err());
        let p = problem(false, 50, 1);
        let bad = Noise {
            measurement_k: 0.0,
            power_w_per_sqrt_s: 1.0,
            switching: None,
        };
        assert!(run(&p, bad, &settings(0.0, 8)).is_err());
    }

    /// `gemm_padded`'s element (i, j): the chain of multiply-adds over q in order, fused or
    /// not.
    fn chain(l: &[f64], r: &[f64], p: usize, k: usize, i: usize, j: usize, fused: bool) -> f64 {
        (0..k).fold(0.0, |acc, q| {
            let (a, b) = (l[i * p + q], r[q * p + j]);
            if fused {
                a.mul_add(b, acc)
            } else {
                a * b + acc
            }
        })
    }

    #[test]
    fn the_blocked_products_are_the_chains_of_multiply_adds() {
        let mut rng = Rng(11);
        for n in [3, 8, 13, 37, 38, 39, 41] {
            let p = padded(n);
            let mut fill = || {
                let mut m = vec![0.0; p * p];
                for i in 0..n {
                    for j in 0..n {
                        m[i * p + j] = rng.normal();
                    }
                }
                m
            };
            let (l, r) = (fill(), fill());
            for lower in [false, true] {
                let check = |c: &[f64], fused: bool, what: &str| {
                    for i in 0..n {
                        for j in 0..if lower { i + 1 } else { n } {
                            let want = chain(&l, &r, p, n, i, j, fused);
                            assert_eq!(
                                c[i * p + j].to_bits(),
                                want.to_bits(),
                                "{what} n {n} ({i}, {j})"
                            );
                        }
                    }
                };
                let mut c = vec![f64::NAN; p * p];
                gemm_padded::<false>(&l, &r, &mut c, p, n, n, lower);
                check(&c, false, "scalar");
                #[cfg(target_arch = "x86_64")]
                {
                    if has_avx2_fma() {
                        let mut c = vec![f64::NAN; p * p];
                        // SAFETY: the CPU has the features; p x p slices, k = rows = n <= p.
                        unsafe { gemm_padded_avx2(&l, &r, &mut c, p, n, n, lower) };
                        check(&c, true, "avx2");
                    }
                }
            }
        }
    }

    #[test]
    fn the_register_held_row_sums_are_the_axpy_chains() {
        // `gemv_rows` (both codes) against `axpy` row after row, to the bit: every width
        // (blocks of 16, of 4, the tail), ±1 (the three outputs: `gemv_rows3`'s test)
        let mut rng = Rng(12);
        for (rows, width, stride) in [
            (37, 24, 24),
            (39, 39, 39),
            (5, 3, 7),
            (38, 38, 40),
            (1, 17, 17),
            (0, 9, 9),
        ] {
            let m: Vec<f64> = (0..rows * stride).map(|_| rng.normal()).collect();
            let a: Vec<f64> = (0..rows).map(|_| rng.normal()).collect();
            let start: Vec<f64> = (0..width).map(|_| rng.normal()).collect();
            for sign in [1.0, -1.0] {
                let mut want = start.clone();
                for i in 0..rows {
                    axpy::<true>(sign * a[i], &m[i * stride..i * stride + width], &mut want);
                }
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                let check = |fma: bool| {
                    let mut got = start.clone();
                    if fma {
                        #[cfg(target_arch = "x86_64")]
                        {
                            // SAFETY: the CPU has the features; the lengths are gemv_rows'.
                            unsafe { gemv_rows_avx2(&a, sign, &m, stride, &mut got) };
                        }
                    } else {
                        gemv_rows::<false>(&a, sign, &m, stride, &mut got);
                    }
                    let what = format!("fma {fma} rows {rows} width {width} sign {sign}");
                    if fma {
                        assert_eq!(bits(&got), bits(&want), "{what}");
                    } else {
                        // the scalar code is the unfused chain: within rounding of the fused
                        for (x, y) in got.iter().zip(&want) {
                            assert!((x - y).abs() <= 1e-12 * (1.0 + y.abs()), "{what}");
                        }
                    }
                };
                check(false);
                #[cfg(target_arch = "x86_64")]
                if has_avx2_fma() {
                    check(true);
                }
            }
        }
    }

    #[test]
    fn the_three_row_sums_are_the_axpy_chains() {
        // `gemv_rows3` (both codes) against `axpy` row after row, to the bit: every width
        // (blocks of 8, the tail), the second and third outputs over the first rows
        let mut rng = Rng(31);
        for (rows, width, stride, nb) in [
            (39, 39, 39, 37),
            (38, 38, 38, 37),
            (5, 3, 7, 2),
            (9, 17, 17, 9),
            (4, 8, 8, 0),
            (0, 9, 9, 0),
        ] {
            let m: Vec<f64> = (0..rows * stride).map(|_| rng.normal()).collect();
            let a: Vec<f64> = (0..rows).map(|_| rng.normal()).collect();
            let b: Vec<f64> = (0..nb).map(|_| rng.normal()).collect();
            let c: Vec<f64> = (0..nb).map(|_| rng.normal()).collect();
            let start: Vec<f64> = (0..width).map(|_| rng.normal()).collect();
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            let check = |fma: bool| {
                let mut want = [start.clone(), start.clone(), start.clone()];
                for i in 0..rows {
                    let row = &m[i * stride..i * stride + width];
                    if fma {
                        axpy::<true>(a[i], row, &mut want[0]);
                        if i < nb {
                            axpy::<true>(b[i], row, &mut want[1]);
                            axpy::<true>(c[i], row, &mut want[2]);
                        }
                    } else {
                        axpy::<false>(a[i], row, &mut want[0]);
                        if i < nb {
                            axpy::<false>(b[i], row, &mut want[1]);
                            axpy::<false>(c[i], row, &mut want[2]);
                        }
                    }
                }
                let [mut o1, mut o2, mut o3] = [start.clone(), start.clone(), start.clone()];
                if fma {
                    #[cfg(target_arch = "x86_64")]
                    {
                        // SAFETY: the CPU has the features; the lengths are gemv_rows3's.
                        unsafe {
                            gemv_rows3_avx2(&a, &b, &c, &m, stride, &mut o1, &mut o2, &mut o3)
                        };
                    }
                } else {
                    gemv_rows3::<false>(&a, &b, &c, &m, stride, &mut o1, &mut o2, &mut o3);
                }
                let what = format!("fma {fma} rows {rows} width {width} nb {nb}");
                assert_eq!(bits(&o1), bits(&want[0]), "{what}");
                assert_eq!(bits(&o2), bits(&want[1]), "{what}: second");
                assert_eq!(bits(&o3), bits(&want[2]), "{what}: third");
            };
            check(false);
            #[cfg(target_arch = "x86_64")]
            if has_avx2_fma() {
                check(true);
            }
        }
    }

    #[test]
    fn the_dense_covariance_steps_are_the_plain_products() {
        // a dense transition of the refinement-1.0 model's size (37 modes), with and without
        // the lag: F X Fᵀ and Fᵀ L̃ F against plain products, and exactly symmetric
        let mut rng = Rng(5);
        let r = 37;
        for lag in [false, true] {
            let n = r + 1 + usize::from(lag);
            let mut normal = |len: usize, scale: f64| -> Vec<f64> {
                (0..len).map(|_| scale * rng.normal()).collect()
            };
            let tr = Transition {
                diagonal: false,
                a: normal(r * r, 0.2),
                e: Vec::new(),
                gamma: normal(r, 0.01),
                phi: 0.999,
                q_unit: 1.0,
                q_gap: 0.0,
                q_modes: Vec::new(),
                lag_a: if lag { 0.97 } else { 0.0 },
                lag_b1: 0.0,
                lag_row: if lag { normal(r, 0.1) } else { vec![0.0; r] },
                lag_power: if lag { 0.001 } else { 0.0 },
                applied: false,
                brake_phi: 1.0,
                brake_q: 0.0,
                eigen: None,
            };
            let d = Dims {
                r,
                n,
                lag,
                brake: false,
            };
            let f = f_matrix(&tr, &d);
            let ft = transpose(&f, n);
            let b = normal(n * n, 1.0);
            let x = matmul(&b, &transpose(&b, n), n); // symmetric, positive definite
            let (h, u) = (normal(n, 1.0), normal(n, 1.0));
            let c = 0.7;
            let dense = DenseF::new(&tr, &d);
            let mut pad = Work::new(n).pad;
            let close = |got: &[f64], want: &[f64], what: &str| {
                let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                for i in 0..n {
                    for j in 0..n {
                        let (g, w) = (got[i * n + j], want[i * n + j]);
                        assert!(
                            (g - w).abs() <= 1e-13 * scale,
                            "{what} lag {lag} ({i}, {j}): {g} {w}"
                        );
                        assert_eq!(g.to_bits(), got[j * n + i].to_bits(), "{what} symmetric");
                    }
                }
            };
            let mut out = vec![0.0; n * n];
            let mut ph = vec![0.0; n];
            dense.predict_cov::<false>(&d, &x, &mut out, &mut pad, Some((&h[..r], &mut ph)));
            close(&out, &matmul(&matmul(&f, &x, n), &ft, n), "F X Fᵀ");
            for j in 0..n {
                let want: f64 = (0..r).map(|i| h[i] * out[i * n + j]).sum();
                assert!(
                    (ph[j] - want).abs() <= 1e-12 * want.abs().max(1.0),
                    "Σh lag {lag}"
                );
            }
            for corr in [None, Some((&u[..], c))] {
                let lt = l_tilde(&x, &h, corr, n);
                dense.back_cov::<false>(&d, &x, &h, corr, &mut out, &mut pad);
                close(&out, &matmul(&matmul(&ft, &lt, n), &f, n), "Fᵀ L̃ F");
            }
        }
    }

    /// The fused passes of a diagonal transition with the braking's power `P_b` (a second
    /// border column) are the plain products `F X Fᵀ`, `Fᵀ L̃ F` and `Σh`.
    #[test]
    fn the_fused_steps_with_the_braking_power_are_the_plain_products() {
        let mut rng = Rng(23);
        let mut normal =
            |len: usize, sd: f64| -> Vec<f64> { (0..len).map(|_| sd * rng.normal()).collect() };
        let r = 5;
        for lag in [false, true] {
            let n = r + 2 + usize::from(lag);
            let tr = Transition {
                diagonal: true,
                a: Vec::new(),
                e: normal(r, 0.5),
                gamma: normal(r, 0.01),
                phi: 0.999,
                q_unit: 1.0,
                q_gap: 0.0,
                q_modes: Vec::new(),
                lag_a: if lag { 0.97 } else { 0.0 },
                lag_b1: 0.0,
                lag_row: if lag { normal(r, 0.1) } else { vec![0.0; r] },
                lag_power: if lag { 0.001 } else { 0.0 },
                applied: false,
                brake_phi: 0.9,
                brake_q: 0.0,
                eigen: None,
            };
            let d = Dims {
                r,
                n,
                lag,
                brake: true,
            };
            let mut f = vec![0.0; n * n];
            for i in 0..n {
                let mut unit = vec![0.0; n];
                unit[i] = 1.0;
                let mut col = vec![0.0; n];
                tr.apply::<false>(&d, &unit, &mut col);
                for j in 0..n {
                    f[j * n + i] = col[j];
                }
            }
            assert_eq!(f[n - 1], tr.gamma[0], "P_b heats the modes");
            let ft = transpose(&f, n);
            let b = normal(n * n, 1.0);
            let x = matmul(&b, &transpose(&b, n), n);
            let mut h = normal(n, 1.0);
            h[r..].fill(0.0); // the reading on the modes (the fused Σh is summed without a lag)
            let u = normal(n, 1.0);
            let close = |got: &[f64], want: &[f64], what: &str| {
                let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                for (k, (g, w)) in got.iter().zip(want).enumerate() {
                    assert!(
                        (g - w).abs() <= 1e-13 * scale,
                        "{what} lag {lag} ({}, {}): {g} {w}",
                        k / n,
                        k % n
                    );
                }
            };
            let (mut a, mut bb, mut big) = (vec![0.0; n], vec![0.0; n], vec![0.0; n * n]);
            let mut out = vec![0.0; n * n];
            let mut ph = vec![0.0; n];
            let acc = (!lag).then(|| (&h[..r], &mut ph[..]));
            tr.predict_cov::<false>(&d, &x, &mut out, &mut a, &mut bb, &mut big, acc, None);
            let fxf = matmul(&matmul(&f, &x, n), &ft, n);
            close(&out, &fxf, "F X Fᵀ");
            if !lag {
                for j in 0..n {
                    let want: f64 = (0..r).map(|i| h[i] * out[i * n + j]).sum();
                    assert!((ph[j] - want).abs() <= 1e-12 * want.abs().max(1.0), "Σh");
                }
            }
            // with the mode rows' share of q_gap u uᵀ in the same pass (Σh without it: the
            // caller adds its share)
            let with_gap = Transition {
                q_gap: 0.3,
                ..tr.clone()
            };
            let mut ph_gap = vec![0.0; n];
            let acc = (!lag).then(|| (&h[..r], &mut ph_gap[..]));
            let (o, uu) = (&mut out, Some(&u[..]));
            with_gap.predict_cov::<false>(&d, &x, o, &mut a, &mut bb, &mut big, acc, uu);
            let mut want = fxf.clone();
            for i in 0..r {
                for j in 0..n {
                    want[i * n + j] += 0.3 * u[i] * u[j];
                }
            }
            close(&out, &want, "F X Fᵀ + the mode rows of q_gap u uᵀ");
            if !lag {
                for j in 0..n {
                    let want: f64 = (0..r).map(|i| h[i] * fxf[i * n + j]).sum();
                    assert!(
                        (ph_gap[j] - want).abs() <= 1e-12 * want.abs().max(1.0),
                        "Σh, gap"
                    );
                }
            }
            let mut scratch = Work::new(n).four;
            for corr in [None, Some((&u[..], 0.7))] {
                let lt = l_tilde(&x, &h, corr, n);
                tr.back_cov::<false>(&d, &x, &h, corr, &mut out, &mut scratch, &mut big);
                close(&out, &matmul(&matmul(&ft, &lt, n), &f, n), "Fᵀ L̃ F");
            }
        }
    }
}
