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
//! one `A` was made of, the `eigh` of the convection's operator in
//! `fleetbrake.model.estimator.prepare`, so the kernel and the numpy oracle step the same
//! numbers) it is stepped as a diagonal one in the basis of its
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

mod basis;
mod covariance;
mod filter;
mod kernel;
mod linalg;
mod outputs;
mod problem;
mod smoother;
#[cfg(test)]
mod testing;
mod transition;

use rayon::prelude::*;

use crate::error::Result;
use crate::simd::has_avx2_fma;

use filter::forward;
use kernel::Kernel;
use smoother::smooth;

pub use outputs::{Estimates, Outputs};
pub use problem::{Eigen, Noise, Problem, Settings, Switching, Transition};
pub use smoother::led_modes;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::testing::*;

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
}
