//! The pieces of a span's chain: a piece's steps taken by a [`PieceStepper`] (the kernel's
//! [`BasisRun`]), its outputs at the rows wanted, the sensor's lag, and a coarse piece's grid
//! interpolated to the seconds.

use super::basis_run::{basis_at, largest, BasisRun};
use super::chain::{AnchorRule, ChainModel, ChainSteps};
use super::propagators::Propagators;
use crate::simd::has_avx2_fma;

impl<'a> BasisRun<'a> {
    /// The outputs onto a piece's rows: the sensor (the first probe), the face mean and the
    /// maximum over the face nodes (NaN when the run has no face-node rows), with `t_ref`
    /// added; NaN for a row not `wanted` (nothing computed).
    #[inline(always)]
    pub(super) fn emit(&mut self, np: usize, t_ref: f64, rows: &mut PieceRows, wanted: bool) {
        if !wanted {
            rows.sensor.push(f64::NAN);
            rows.mean.push(f64::NAN);
            rows.max.push(f64::NAN);
            return;
        }
        self.outputs();
        let top = if self.n_out > np + 1 {
            largest(&self.y[np + 1..self.n_out])
        } else {
            f64::NAN
        };
        rows.sensor.push(self.y[0] + t_ref);
        rows.mean.push(self.y[np] + t_ref);
        rows.max.push(top + t_ref);
    }

    /// A chain's steps `s0 .. s1` from the state as it is, the outputs before the first and
    /// after each onto `rows` (those `job.need` wants). The inputs are the flux vector then
    /// the face sets' (`inputs` laid out by [`BasisRun::for_chain`]).
    #[inline(always)]
    pub(super) fn chain_steps_generic(&mut self, job: &StepsJob, rows: &mut PieceRows) {
        let steps = job.steps;
        let r = self.props.order;
        let n_faces = self.inputs.len() / r - 1;
        self.emit(job.n_probes, job.t_ref, rows, job.wants(0));
        for s in job.s0..job.s1 {
            let k = steps.prop[s];
            self.enter(k);
            let (e, g) = self.props.rates(k);
            let basis = basis_at(&self.modal, &self.rotated, self.at);
            let (b_flux, b_faces) = basis.b.split_at(r);
            let q = steps.flux[s];
            let air = steps.ambient[s] - job.t_ref;
            for (ui, &b) in self.u.iter_mut().zip(b_flux) {
                *ui = q * b;
            }
            for (f, b_face) in b_faces.chunks_exact(r).enumerate() {
                let d = steps.h[s * n_faces + f] * air;
                for (ui, &b) in self.u.iter_mut().zip(b_face) {
                    *ui += d * b;
                }
            }
            for (((w, &ei), &gi), &ui) in self.w.iter_mut().zip(e).zip(g).zip(&self.u) {
                *w = ei * *w + gi * ui;
            }
            self.emit(job.n_probes, job.t_ref, rows, job.wants(s + 1 - job.s0));
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn chain_steps_avx2(&mut self, job: &StepsJob, rows: &mut PieceRows) {
        self.chain_steps_generic(job, rows);
    }

    /// A run for [`Propagators::simulate_chain`]: the inputs `b_flux` then `b_faces`.
    pub(super) fn for_chain(props: &'a Propagators, model: &ChainModel<'a>) -> Self {
        let mut inputs = model.b_flux.to_vec();
        inputs.extend_from_slice(model.b_faces);
        BasisRun::new(props, inputs, model.c)
    }
}

/// The steps of one piece to take: `s0 .. s1` of `steps`, at reference `t_ref`; the output
/// rows wanted (`need`, one per row: before the first step and after each; `None`: all).
pub(super) struct StepsJob<'s, 'a> {
    pub(super) steps: &'s ChainSteps<'a>,
    pub(super) s0: usize,
    pub(super) s1: usize,
    pub(super) t_ref: f64,
    pub(super) n_probes: usize,
    pub(super) need: Option<&'s [bool]>,
}

impl StepsJob<'_, '_> {
    /// Whether output row `i` of the piece is wanted.
    #[inline(always)]
    pub(super) fn wants(&self, i: usize) -> bool {
        self.need.is_none_or(|need| need[i])
    }
}

/// The rows a piece's steps give, one per output time: sensor, face mean, face maximum.
#[derive(Debug, Default)]
pub(super) struct PieceRows {
    pub(super) sensor: Vec<f64>,
    pub(super) mean: Vec<f64>,
    pub(super) max: Vec<f64>,
}

/// How the steps of a chain's pieces are taken: the kernel's [`BasisRun`]; the tests' stepping
/// by the formula (a rotated propagator rotates in and out every step) is the reference it
/// must equal.
pub(super) trait PieceStepper {
    /// The steps of `job` from `xi` (modal coordinates), the state after them left in `xi`;
    /// the outputs before the first step and after each pushed onto `rows` (NaN for a row
    /// `job` does not want).
    fn run(&mut self, job: &StepsJob, xi: &mut [f64], rows: &mut PieceRows);
}

impl PieceStepper for BasisRun<'_> {
    fn run(&mut self, job: &StepsJob, xi: &mut [f64], rows: &mut PieceRows) {
        self.start(xi);
        self.chain_steps(job, rows);
        self.state(xi);
    }
}

impl BasisRun<'_> {
    pub(super) fn chain_steps(&mut self, job: &StepsJob, rows: &mut PieceRows) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            // SAFETY: the CPU has the features the function is compiled for.
            unsafe { self.chain_steps_avx2(job, rows) };
            return;
        }
        self.chain_steps_generic(job, rows);
    }
}

/// One piece run: outputs at its samples, the state and the lag's last value after it.
#[derive(Debug, Default)]
pub(super) struct Piece {
    pub(super) sensor: Vec<f64>,
    pub(super) mean: Vec<f64>,
    pub(super) max: Vec<f64>,
    pub(super) xi: Vec<f64>,
    pub(super) lag_last: Option<f64>,
}

/// The output rows of piece `p` wanted into `need`: `wanted(i)` for row `i` (sample
/// `piece_a[p] + i`) of a 1 s piece, every row of a coarse one (its grid is interpolated).
pub(super) fn piece_need(
    steps: &ChainSteps,
    p: usize,
    need: &mut Vec<bool>,
    wanted: impl Fn(usize) -> bool,
) {
    let rows = steps.step_off[p + 1] - steps.step_off[p] + 1;
    need.clear();
    if steps.at_off[p + 1] > steps.at_off[p] {
        need.resize(rows, true);
    } else {
        need.extend((0..rows).map(wanted));
    }
}

/// `first_order_lag` of `fleetbrake.model.rom`: exact for a signal linear between samples.
pub(super) fn lag_filter(x: &mut [f64], dt_s: f64, tau_s: f64, initial: Option<f64>) {
    if tau_s <= 0.0 || x.is_empty() {
        return;
    }
    let a = (-dt_s / tau_s).exp();
    let c = tau_s / dt_s * (1.0 - a) - a;
    let mut prev_x = x[0];
    let mut prev_y = initial.unwrap_or(x[0]);
    x[0] = prev_y;
    for v in x.iter_mut().skip(1) {
        let xk = *v;
        let y = a * prev_y + (1.0 - a) * xk - (xk - prev_x) * c;
        prev_x = xk;
        prev_y = y;
        *v = y;
    }
}

/// `numpy.interp(x, xp, fp)` for `x` inside `[xp[0], xp[-1]]`, `xp` increasing.
pub(super) fn interp_into(x0: usize, count: usize, xp: &[f64], fp: &[f64], out: &mut Vec<f64>) {
    out.clear();
    let last = xp.len() - 1;
    let mut j = 0;
    for i in 0..count {
        let x = (x0 + i) as f64;
        while j < last && xp[j + 1] <= x {
            j += 1;
        }
        out.push(if j == last || xp[j] == x {
            fp[j]
        } else {
            let slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j]);
            slope * (x - xp[j]) + fp[j]
        });
    }
}

impl Propagators {
    /// Run piece `p` from `xi0` at reference `t_ref` (see [`ChainSteps`]).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn run_piece<S: PieceStepper>(
        &self,
        stepper: &mut S,
        model: &ChainModel,
        steps: &ChainSteps,
        p: usize,
        t_ref: f64,
        xi0: &[f64],
        lag_last: Option<f64>,
        rule: &AnchorRule,
        t_first: f64,
        need: Option<&[bool]>,
        out: &mut Piece,
    ) {
        let (s0, s1) = (steps.step_off[p], steps.step_off[p + 1]);
        let rows = s1 - s0 + 1;
        let mut xi = xi0.to_vec();
        let mut taken = PieceRows {
            sensor: Vec::with_capacity(rows),
            mean: Vec::with_capacity(rows),
            max: Vec::with_capacity(rows),
        };
        let job = StepsJob {
            steps,
            s0,
            s1,
            t_ref,
            n_probes: model.n_probes,
            need,
        };
        stepper.run(&job, &mut xi, &mut taken);
        let PieceRows {
            mut sensor,
            mean,
            max,
        } = taken;
        let mut new_lag = None;
        if let Some(tau) = rule.lag_tau_s {
            // the lag acts on the block's temperature, the anchoring shifts on the reading
            let shift = t_ref - t_first;
            for x in sensor.iter_mut() {
                *x -= shift;
            }
            lag_filter(&mut sensor, steps.piece_dt[p], tau, lag_last);
            new_lag = sensor.last().copied();
            for x in sensor.iter_mut() {
                *x += shift;
            }
        }
        let (a0, a1) = (steps.at_off[p], steps.at_off[p + 1]);
        if a1 > a0 {
            let at = &steps.at[a0..a1];
            let count = steps.piece_b[p] - steps.piece_a[p] + 1;
            interp_into(steps.piece_a[p], count, at, &sensor, &mut out.sensor);
            interp_into(steps.piece_a[p], count, at, &mean, &mut out.mean);
            interp_into(steps.piece_a[p], count, at, &max, &mut out.max);
        } else {
            out.sensor = sensor;
            out.mean = mean;
            out.max = max;
        }
        out.xi = xi;
        out.lag_last = new_lag;
    }
}
