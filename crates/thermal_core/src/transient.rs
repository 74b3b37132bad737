//! Time integration of `M dT/dt + K(t) T = f(t)` by the theta method, driven step by step by
//! time series (flux, convection coefficients, ambient), with a damped (Rannacher) start.
//!
//! Inputs of step n hold on the interval [t_n, t_n+1]. With `K_n = K_cond + Σ_s h_s,n H_s` and
//! `f_n = q_n G_flux + Σ_s h_s,n T_amb,n G_s`:
//! `(M/dt + θ K_n) T_n+1 = (M/dt − (1−θ) K_n) T_n + f_n`.
//! Each step is solved for its increment `ΔT = T_n+1 − T_n` from the residual of the current
//! state: `(M/dt + θ K_n) ΔT = f_n − K_n T_n` (see [`Precision`]).

use crate::error::{check_finite, check_non_negative, Result, ThermalError};

/// Crank–Nicolson (θ = 1/2) or backward Euler (θ = 1), and how many steps are each replaced
/// by two backward-Euler half steps after the start (damps the spurious oscillation
/// Crank–Nicolson leaves after a non-smooth start).
///
/// Crank–Nicolson also rings after every discontinuity of its inputs (a brake applied or
/// released as a step of flux): with `jump_fraction` > 0, a step whose flux, ambient or
/// convection changes by more than that fraction of the series' largest magnitude restarts
/// the damping (Rannacher's remedy; second order is kept).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scheme {
    pub theta: f64,
    pub damped_steps: usize,
    pub jump_fraction: f64,
    pub precision: Precision,
}

/// The precision of the factor's values in the step's triangular solves.
///
/// Each step solves for the increment `ΔT` from the residual of the current state, formed
/// in double precision: `(M/dt + θ K) ΔT = f − K T_n`. An error in the solve is then an
/// error relative to the increment (kelvins a step), not to the temperature, and it does
/// not accumulate into the fixed point. `Mixed` reads the factor in single precision (half
/// the memory traffic of a step, which is what a step costs) and keeps the arithmetic in
/// double; both correct the increment's uniform part so that the global heat balance
/// `1ᵀ (M/dt + θ K) ΔT = 1ᵀ (f − K T_n)` holds exactly (a Galerkin correction on the
/// constant vector, the slowest mode), whatever the solve's rounding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Precision {
    Double,
    Mixed,
}

impl Precision {
    pub fn from_name(name: &str) -> Option<Self> {
        match name.to_ascii_lowercase().as_str() {
            "double" | "f64" => Some(Precision::Double),
            "mixed" => Some(Precision::Mixed),
            _ => None,
        }
    }
}

impl Scheme {
    pub const CRANK_NICOLSON: Scheme = Scheme {
        theta: 0.5,
        damped_steps: 1,
        jump_fraction: 0.05,
        precision: Precision::Mixed,
    };
    pub const BACKWARD_EULER: Scheme = Scheme {
        theta: 1.0,
        damped_steps: 0,
        jump_fraction: 0.0,
        precision: Precision::Mixed,
    };

    pub fn from_name(name: &str, damped_steps: usize) -> Option<Scheme> {
        match name.to_ascii_lowercase().replace('_', "-").as_str() {
            "crank-nicolson" | "cn" => Some(Scheme {
                damped_steps,
                ..Scheme::CRANK_NICOLSON
            }),
            "backward-euler" | "be" | "implicit-euler" => Some(Scheme {
                damped_steps,
                ..Scheme::BACKWARD_EULER
            }),
            _ => None,
        }
    }

    /// For each step, whether it is taken as two backward-Euler half steps.
    pub fn damped_mask(&self, loading: &Loading) -> Vec<bool> {
        let n = loading.n_steps;
        let mut mask = vec![false; n];
        let mut mark = |from: usize| {
            for m in mask.iter_mut().skip(from).take(self.damped_steps) {
                *m = true;
            }
        };
        mark(0);
        if self.jump_fraction > 0.0 && self.theta < 1.0 {
            let mut series: Vec<Series> = vec![loading.flux_w_m2, loading.ambient_c];
            series.extend(loading.convection.iter().map(|c| c.h_w_m2k));
            for s in series {
                if let Series::Steps(values) = s {
                    let scale = values.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                    let threshold = self.jump_fraction * scale;
                    for k in 1..values.len() {
                        if scale > 0.0 && (values[k] - values[k - 1]).abs() > threshold {
                            mark(k);
                        }
                    }
                }
            }
        }
        mask
    }

    pub fn validate(&self) -> Result<()> {
        if !(self.theta >= 0.5 && self.theta <= 1.0) {
            return Err(ThermalError::InvalidParameter {
                name: "theta".into(),
                value: self.theta,
                reason: "must lie in [0.5, 1] for an unconditionally stable scheme".into(),
            });
        }
        if !(self.jump_fraction >= 0.0) || !self.jump_fraction.is_finite() {
            return Err(ThermalError::InvalidParameter {
                name: "jump_fraction".into(),
                value: self.jump_fraction,
                reason: "must be a non-negative fraction".into(),
            });
        }
        Ok(())
    }
}

/// A quantity that is constant or given per step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Series<'a> {
    Constant(f64),
    Steps(&'a [f64]),
}

impl Series<'_> {
    #[inline]
    pub fn at(&self, n: usize) -> f64 {
        match self {
            Series::Constant(v) => *v,
            Series::Steps(s) => s[n],
        }
    }

    /// Length and finiteness (and sign, when `non_negative`) against the number of steps.
    pub fn check(&self, name: &str, n_steps: usize, non_negative: bool) -> Result<()> {
        let values: &[f64] = match self {
            Series::Constant(v) => std::slice::from_ref(v),
            Series::Steps(s) => {
                if s.len() != n_steps {
                    return Err(ThermalError::LengthMismatch {
                        name: name.to_string(),
                        expected: n_steps,
                        got: s.len(),
                    });
                }
                s
            }
        };
        for (i, v) in values.iter().enumerate() {
            let label = format!("{name}[{i}]");
            if non_negative {
                check_non_negative(&label, *v)?;
            } else {
                check_finite(&label, *v)?;
            }
        }
        Ok(())
    }
}

/// Convection on one face set: coefficient (W/m² K) per step; the air is at the ambient.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Convection<'a> {
    pub face: usize,
    pub h_w_m2k: Series<'a>,
}

/// The initial temperature.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Initial<'a> {
    Uniform(f64),
    Field(&'a [f64]),
}

/// Everything that drives one simulation.
#[derive(Debug, Clone, PartialEq)]
pub struct Loading<'a> {
    pub dt_s: f64,
    pub n_steps: usize,
    /// Heat flux into the flux face (W/m²), per step.
    pub flux_w_m2: Series<'a>,
    pub ambient_c: Series<'a>,
    pub convection: Vec<Convection<'a>>,
    pub initial: Initial<'a>,
}

impl Loading<'_> {
    pub fn validate(&self, n_nodes: usize, n_faces: usize) -> Result<()> {
        if !(self.dt_s.is_finite() && self.dt_s > 0.0) {
            return Err(ThermalError::InvalidTimeStep(self.dt_s));
        }
        self.flux_w_m2.check("flux_w_m2", self.n_steps, false)?;
        self.ambient_c.check("ambient_c", self.n_steps, false)?;
        for c in &self.convection {
            if c.face >= n_faces {
                return Err(ThermalError::InvalidMesh(format!(
                    "face operator {} does not exist",
                    c.face
                )));
            }
            c.h_w_m2k.check("h_w_m2k", self.n_steps, true)?;
        }
        match self.initial {
            Initial::Uniform(v) => check_finite("initial_c", v)?,
            Initial::Field(f) => {
                if f.len() != n_nodes {
                    return Err(ThermalError::LengthMismatch {
                        name: "initial_c field".into(),
                        expected: n_nodes,
                        got: f.len(),
                    });
                }
                for (i, v) in f.iter().enumerate() {
                    check_finite(&format!("initial_c[{i}]"), *v)?;
                }
            }
        }
        Ok(())
    }
}

/// Heat bookkeeping of a run (joules), exact for the time-discrete scheme.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct EnergyLedger {
    /// Heat stored in the block: Σ_i (M 1)_i (T_i − T0_i).
    pub stored_j: f64,
    /// Heat that entered through the flux face.
    pub flux_in_j: f64,
    /// Heat that left by convection (negative when the air heats the block).
    pub convected_out_j: f64,
}

/// What a simulation returns.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Outputs {
    pub time_s: Vec<f64>,
    /// Row-major (n_steps + 1) x n_probes.
    pub probe_c: Vec<f64>,
    pub n_probes: usize,
    /// Area-weighted mean over the friction (flux) face, per output time.
    pub face_mean_c: Vec<f64>,
    /// Nodal maximum over the friction (flux) face.
    pub face_max_c: Vec<f64>,
    /// Row-major fields (one per kept step) of n_nodes values.
    pub fields_c: Vec<f64>,
    pub field_steps: Vec<usize>,
    /// The state after the last step (to continue a simulation).
    pub final_c: Vec<f64>,
    pub energy: EnergyLedger,
    pub factorizations: usize,
    pub seconds_factorization: f64,
    pub seconds_stepping: f64,
}
