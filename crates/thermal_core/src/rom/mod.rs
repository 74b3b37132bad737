//! Time stepping of a reduced model in modal form, for many events at once.
//!
//! Each mode i evolves exactly for inputs held over a step:
//! `ξ_i ← e_i ξ_i + g_i (b_q,i q_n + b_a,i a_n)`, with `e_i = exp(−λ_i dt)`,
//! `g_i = (1 − e_i)/λ_i`, `q` the flux and `a` the air drive `T_amb − T_ref` (the nominal
//! convection folded into `b_a`). Outputs `y = C ξ + T_ref`: the probes, the friction-face
//! mean, and the maximum over the friction-face nodes that stand for the face.
//!
//! Laid out by what is stepped: `batch` (many events of one model at once, one per SIMD
//! lane), `propagators` (one run through switching step systems) kept in each rotated
//! propagator's basis by `basis_run`, a span's chain of pieces with its anchoring
//! (`chain`, the pieces in `piece`), and the chain's step systems and convection
//! (`convection`).

mod basis_run;
mod batch;
mod chain;
mod convection;
mod piece;
mod propagators;
#[cfg(test)]
mod testing;

pub use batch::{BatchOutputs, ModalStepper};
pub use chain::{
    AnchorRule, ChainModel, ChainOutputs, ChainSteps, ANCHOR_AFTER, ANCHOR_BEFORE, ANCHOR_NONE,
    ANCHOR_START,
};
pub use convection::{
    chain_step_convection, chain_step_convection_into, step_systems, step_systems_into, StepSystems,
};
pub use propagators::Propagators;

/// The exact one-step propagator of modes `dξ/dt = −λ ξ + u` with `u` held over the step:
/// `e = exp(−λ dt)`, `g = (1 − e)/λ` (`dt` where `λ dt` vanishes), computed without
/// cancellation. The one place it is computed: the batch stepper uses it, and Python's
/// reduced model calls it (`rom_exact_propagator`) for its switching propagators.
pub fn exact_propagator(lam: &[f64], dt_s: f64) -> (Vec<f64>, Vec<f64>) {
    lam.iter()
        .map(|&l| {
            let x = l * dt_s;
            let g = if x.abs() > 1e-12 {
                -(-x).exp_m1() / l
            } else {
                dt_s
            };
            ((-x).exp(), g)
        })
        .unzip()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exact_propagator_has_its_limits() {
        let dt = 2.0;
        let (e, g) = exact_propagator(&[0.0, 1e-15, 0.3, 1e6], dt);
        // no decay: e = 1, g = dt (the limit of (1 - e)/λ), also just above zero
        assert_eq!((e[0], g[0]), (1.0, dt));
        assert!((g[1] - dt).abs() <= 1e-12 * dt && e[1] <= 1.0);
        // the middle: the formula itself
        assert!((e[2] - (-0.6f64).exp()).abs() < 1e-15);
        assert!((g[2] - (1.0 - (-0.6f64).exp()) / 0.3).abs() < 1e-14);
        // fast modes: gone in one step, g = 1/λ (the steady response)
        assert_eq!(e[3], 0.0);
        assert!((g[3] - 1e-6).abs() < 1e-20);
    }
}
