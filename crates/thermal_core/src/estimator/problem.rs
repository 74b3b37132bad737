//! What the kernel is given: one wagon's transitions, per-step series and output rows
//! (`Problem`, with its checks), the noise and its switching modes, and how to run.

use std::borrow::Cow;

use crate::error::{Result, ThermalError};

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
    /// A dense `a`'s eigendecomposition as its maker computed it (`a = Q diag(e) Qᵀ`: the
    /// `eigh` in `fleetbrake.model.estimator.prepare` that `a` is made of): the transition is
    /// stepped as a diagonal one in that basis. None: it is stepped dense (`DenseF`).
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
    /// tolerance moves them by far more (`docs/decisions/0001-estimator-covariance-path.md`).
    pub manoeuvre_tolerances: Option<(f64, f64)>,
    pub checkpoint_steps: usize,
    /// Whether to produce the per-second outputs (false: the likelihood only).
    pub outputs: bool,
    /// Whether to record excursions from steady states and replay them (`Memo`; false:
    /// compute every step that is not frozen, the same numbers).
    pub replay: bool,
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::run;
    use crate::estimator::testing::*;

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
}
