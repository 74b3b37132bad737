//! Time stepping of a reduced model in modal form, for many events at once.
//!
//! Each mode i evolves exactly for inputs held over a step:
//! `ξ_i ← e_i ξ_i + g_i (b_q,i q_n + b_a,i a_n)`, with `e_i = exp(−λ_i dt)`,
//! `g_i = (1 − e_i)/λ_i`, `q` the flux and `a` the air drive `T_amb − T_ref` (the nominal
//! convection folded into `b_a`). Outputs `y = C ξ + T_ref`: the probes, the friction-face
//! mean, and the maximum over the friction-face nodes that stand for the face.

use rayon::prelude::*;

use crate::error::{Result, ThermalError};
use crate::simd::{has_avx2_fma, madd};

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

/// A reduced model in modal form at one time step.
#[derive(Debug, Clone, PartialEq)]
pub struct ModalStepper {
    pub e: Vec<f64>,
    pub g_bq: Vec<f64>,
    pub g_ba: Vec<f64>,
    /// Row-major (n_outputs x r): probes, then the face mean, then face-max nodes.
    pub c: Vec<f64>,
    pub n_probes: usize,
}

/// Outputs of a batch, row-major: `probe_c` (E, S+1, P), `face_mean_c` and `face_max_c`
/// (E, S+1).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BatchOutputs {
    pub probe_c: Vec<f64>,
    pub face_mean_c: Vec<f64>,
    pub face_max_c: Vec<f64>,
}

impl ModalStepper {
    pub fn new(
        lam: &[f64],
        b_q: &[f64],
        b_a: &[f64],
        c: Vec<f64>,
        n_probes: usize,
        dt_s: f64,
    ) -> Result<Self> {
        let r = lam.len();
        if !(dt_s.is_finite() && dt_s > 0.0) {
            return Err(ThermalError::InvalidTimeStep(dt_s));
        }
        if b_q.len() != r || b_a.len() != r || r == 0 || c.len() % r != 0 {
            return Err(ThermalError::LengthMismatch {
                name: "modal arrays".into(),
                expected: r,
                got: b_q.len(),
            });
        }
        let n_out = c.len() / r;
        if n_out < n_probes + 2 {
            return Err(ThermalError::LengthMismatch {
                name: "output rows (probes, mean, at least one face node)".into(),
                expected: n_probes + 2,
                got: n_out,
            });
        }
        let (e, g) = exact_propagator(lam, dt_s);
        let g_bq = g.iter().zip(b_q).map(|(gi, b)| gi * b).collect();
        let g_ba = g.iter().zip(b_a).map(|(gi, b)| gi * b).collect();
        Ok(ModalStepper {
            e,
            g_bq,
            g_ba,
            c,
            n_probes,
        })
    }

    pub fn order(&self) -> usize {
        self.e.len()
    }

    pub fn n_outputs(&self) -> usize {
        self.c.len() / self.order()
    }

    /// Simulate `n_events` events of `n_steps` steps each from rest (θ = 0): `flux` and
    /// `drive` row-major (E, S), or (E) when each event's air drive is constant, `t_ref`
    /// (E). Events run in parallel.
    pub fn simulate_batch(
        &self,
        flux: &[f64],
        drive: &[f64],
        t_ref: &[f64],
        n_steps: usize,
    ) -> Result<BatchOutputs> {
        let n_events = t_ref.len();
        if flux.len() != n_events * n_steps {
            return Err(ThermalError::LengthMismatch {
                name: "flux".into(),
                expected: n_events * n_steps,
                got: flux.len(),
            });
        }
        let drive_steps = if drive.len() == n_events && n_steps != 1 {
            1
        } else {
            n_steps
        };
        if drive.len() != n_events * drive_steps {
            return Err(ThermalError::LengthMismatch {
                name: "drive".into(),
                expected: n_events * n_steps,
                got: drive.len(),
            });
        }
        let p = self.n_probes;
        let rows = n_steps + 1;
        let mut out = BatchOutputs {
            probe_c: vec![0.0; n_events * rows * p],
            face_mean_c: vec![0.0; n_events * rows],
            face_max_c: vec![0.0; n_events * rows],
        };
        // blocks of LANES events advance together, one event per SIMD lane
        out.probe_c
            .par_chunks_mut((LANES * rows * p).max(1))
            .zip(out.face_mean_c.par_chunks_mut(LANES * rows))
            .zip(out.face_max_c.par_chunks_mut(LANES * rows))
            .enumerate()
            .for_each(|(block, ((probe, mean), fmax))| {
                let first = block * LANES;
                let lanes = (n_events - first).min(LANES);
                let inputs = BlockInputs {
                    flux: &flux[first * n_steps..(first + lanes) * n_steps],
                    drive: &drive[first * drive_steps..(first + lanes) * drive_steps],
                    t_ref: &t_ref[first..first + lanes],
                    n_steps,
                    drive_steps,
                };
                self.run_block(&inputs, probe, mean, fmax);
            });
        Ok(out)
    }

    fn run_block(
        &self,
        inputs: &BlockInputs,
        probe: &mut [f64],
        mean: &mut [f64],
        fmax: &mut [f64],
    ) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            // SAFETY: the CPU has the features the function is compiled for.
            unsafe { self.run_block_avx2(inputs, probe, mean, fmax) };
            return;
        }
        self.run_block_generic::<false>(inputs, probe, mean, fmax);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn run_block_avx2(
        &self,
        inputs: &BlockInputs,
        probe: &mut [f64],
        mean: &mut [f64],
        fmax: &mut [f64],
    ) {
        self.run_block_generic::<true>(inputs, probe, mean, fmax);
    }

    /// Up to LANES events, one per SIMD lane: the loops over lanes vectorise. `FMA`: fused
    /// multiply-adds (only where the caller enables the CPU feature: without it `mul_add`
    /// is a call into libm).
    #[inline(always)]
    fn run_block_generic<const FMA: bool>(
        &self,
        inputs: &BlockInputs,
        probe: &mut [f64],
        mean: &mut [f64],
        fmax: &mut [f64],
    ) {
        let r = self.order();
        let p = self.n_probes;
        let n_out = self.n_outputs();
        let s = inputs.n_steps;
        let ds = inputs.drive_steps;
        let rows = s + 1;
        let lanes = inputs.t_ref.len();
        let mut xi = vec![[0.0f64; LANES]; r];
        let blocks = self.row_blocks();
        let mut y = vec![[0.0f64; LANES]; n_out.div_ceil(ROW_BLOCK) * ROW_BLOCK];
        let mut ql = [0.0f64; LANES];
        let mut al = [0.0f64; LANES];
        for k in 0..rows {
            if k > 0 {
                let kd = if ds == 1 { 0 } else { k - 1 };
                for l in 0..lanes {
                    ql[l] = inputs.flux[l * s + k - 1];
                    al[l] = inputs.drive[l * ds + kd];
                }
                for (((x, &e), &gq), &ga) in
                    xi.iter_mut().zip(&self.e).zip(&self.g_bq).zip(&self.g_ba)
                {
                    for l in 0..LANES {
                        x[l] = madd::<FMA>(e, x[l], madd::<FMA>(gq, ql[l], ga * al[l]));
                    }
                }
            }
            Self::outputs::<FMA>(&blocks, r, &xi, &mut y);
            let mut m = [f64::NEG_INFINITY; LANES];
            for yo in &y[p + 1..n_out] {
                for l in 0..LANES {
                    m[l] = if yo[l] > m[l] { yo[l] } else { m[l] };
                }
            }
            for l in 0..lanes {
                let t = inputs.t_ref[l];
                for j in 0..p {
                    probe[(l * rows + k) * p + j] = y[j][l] + t;
                }
                mean[l * rows + k] = y[p][l] + t;
                fmax[l * rows + k] = m[l] + t;
            }
        }
    }

    /// `y = C ξ` for a block of events, from the row blocks of `C` laid out for it
    /// ([`ModalStepper::row_blocks`]). Output rows go `ROW_BLOCK` at a time: independent
    /// accumulator vectors keep the FMA units busy (one row at a time waits on the latency
    /// of its own chain of sums).
    #[inline(always)]
    fn outputs<const FMA: bool>(
        blocks: &[[f64; ROW_BLOCK]],
        r: usize,
        xi: &[[f64; LANES]],
        y: &mut [[f64; LANES]],
    ) {
        for (block, out) in blocks.chunks_exact(r).zip(y.chunks_exact_mut(ROW_BLOCK)) {
            let mut acc = [[0.0f64; LANES]; ROW_BLOCK];
            for (cb, x) in block.iter().zip(xi) {
                for j in 0..ROW_BLOCK {
                    for l in 0..LANES {
                        acc[j][l] = madd::<FMA>(cb[j], x[l], acc[j][l]);
                    }
                }
            }
            out.copy_from_slice(&acc);
        }
    }

    /// `C` in blocks of `ROW_BLOCK` rows, each stored mode by mode (rows padded with zeros
    /// to a whole number of blocks).
    fn row_blocks(&self) -> Vec<[f64; ROW_BLOCK]> {
        let r = self.order();
        let n_out = self.n_outputs();
        let n_blocks = n_out.div_ceil(ROW_BLOCK);
        let mut out = vec![[0.0f64; ROW_BLOCK]; n_blocks * r];
        for (o, row) in self.c.chunks_exact(r).enumerate() {
            for (i, &v) in row.iter().enumerate() {
                out[(o / ROW_BLOCK) * r + i][o % ROW_BLOCK] = v;
            }
        }
        out
    }
}

/// Propagators of a reduced model in modal coordinates ξ, one per distinct step system
/// (time step, scheme, convection): `ξ ← Q [e ⊙ (Qᵀ ξ) + g ⊙ (Qᵀ u)]`, `Q` the eigenbasis of
/// the reduced operator at that convection (the identity for the nominal one, whose modes
/// are the coordinates themselves).
#[derive(Debug, Clone, PartialEq)]
pub struct Propagators {
    order: usize,
    /// (K, r) each.
    e: Vec<f64>,
    g: Vec<f64>,
    /// (K, r, r) row-major, `q[(k r + i) r + j] = Q_k[i, j]`; ignored where not `rotated`.
    q: Vec<f64>,
    rotated: Vec<bool>,
}

impl Propagators {
    pub fn new(
        order: usize,
        e: Vec<f64>,
        g: Vec<f64>,
        q: Vec<f64>,
        rotated: Vec<bool>,
    ) -> Result<Self> {
        let k = rotated.len();
        for (name, len, expected) in [
            ("propagator e", e.len(), k * order),
            ("propagator g", g.len(), k * order),
            ("propagator Q", q.len(), k * order * order),
        ] {
            if len != expected || order == 0 {
                return Err(ThermalError::LengthMismatch {
                    name: name.into(),
                    expected,
                    got: len,
                });
            }
        }
        Ok(Propagators {
            order,
            e,
            g,
            q,
            rotated,
        })
    }

    pub fn len(&self) -> usize {
        self.rotated.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rotated.is_empty()
    }

    /// Propagator `k`'s `e` and `g` (r each).
    fn rates(&self, k: usize) -> (&[f64], &[f64]) {
        let r = self.order;
        (&self.e[k * r..(k + 1) * r], &self.g[k * r..(k + 1) * r])
    }

    /// Propagator `k`'s eigenbasis `Q` (r, r) row-major (meaningful where `rotated`).
    fn basis_matrix(&self, k: usize) -> &[f64] {
        let r = self.order;
        &self.q[k * r * r..(k + 1) * r * r]
    }

    /// One run from `xi0` (length r): step `s` applies propagator `index[s]` `repeats[s]`
    /// times under the modal input `u[s]` (row-major (S, r)); after each step the outputs
    /// `C ξ` (`c` row-major (n_out, r)). Returns (outputs (S+1, n_out), final ξ).
    pub fn simulate(
        &self,
        index: &[usize],
        repeats: &[u32],
        u: &[f64],
        xi0: &[f64],
        c: &[f64],
    ) -> Result<(Vec<f64>, Vec<f64>)> {
        let r = self.order;
        let s = index.len();
        for (name, len, expected) in [
            ("repeats", repeats.len(), s),
            ("modal input", u.len(), s * r),
            ("initial state", xi0.len(), r),
        ] {
            if len != expected {
                return Err(ThermalError::LengthMismatch {
                    name: name.into(),
                    expected,
                    got: len,
                });
            }
        }
        if c.is_empty() || c.len() % r != 0 {
            return Err(ThermalError::LengthMismatch {
                name: "output rows".into(),
                expected: r,
                got: c.len(),
            });
        }
        if let Some(&bad) = index.iter().find(|&&k| k >= self.len()) {
            return Err(ThermalError::InvalidParameter {
                name: "propagator index".into(),
                value: bad as f64,
                reason: format!("only {} propagators", self.len()),
            });
        }
        let n_out = c.len() / r;
        let mut y = vec![0.0; (s + 1) * n_out];
        let mut run = BasisRun::new(self, Vec::new(), c);
        run.start(xi0);
        run.outputs();
        y[..n_out].copy_from_slice(&run.y[..n_out]);
        for step in 0..s {
            let k = index[step];
            run.enter(k);
            let uk = &u[step * r..(step + 1) * r];
            if run.at == MODAL {
                run.u.copy_from_slice(uk);
            } else {
                transpose_times(self.basis_matrix(k), uk, &mut run.u);
            }
            let (e, g) = self.rates(k);
            for _ in 0..repeats[step] {
                for (((w, &ei), &gi), &ui) in run.w.iter_mut().zip(e).zip(g).zip(&run.u) {
                    *w = ei * *w + gi * ui;
                }
            }
            run.outputs();
            y[(step + 1) * n_out..(step + 2) * n_out].copy_from_slice(&run.y[..n_out]);
        }
        let mut xi = vec![0.0; r];
        run.state(&mut xi);
        Ok((y, xi))
    }
}

/// Where a run's state is kept when no rotated propagator holds it: the modal coordinates,
/// the basis of every nominal propagator.
const MODAL: usize = usize::MAX;

/// A propagator's basis as a run steps in it: the input vectors `Qᵀ b` (m, r) row-major,
/// the output rows `C Q` in blocks ([`out_blocks`]), and `Qᵀ` (r, r) row-major, with which
/// the state leaves the basis. The modal basis: the vectors `b` and `C` themselves, no `Qᵀ`.
#[derive(Debug, Clone, Default)]
struct Basis {
    b: Vec<f64>,
    ct: Vec<f64>,
    qt: Vec<f64>,
}

/// `out = Mᵀ x`, `M` row-major (len(x), len(out)), its rows accumulated in order.
#[inline(always)]
fn transpose_times(m: &[f64], x: &[f64], out: &mut [f64]) {
    out.fill(0.0);
    for (row, &xi) in m.chunks_exact(out.len()).zip(x) {
        for (o, &a) in out.iter_mut().zip(row) {
            *o += a * xi;
        }
    }
}

/// Output rows summed together, mode by mode, in registers (four AVX2 vectors): each
/// output's sum runs over the modes in order, as a row-by-row product would.
const OUT_BLOCK: usize = 16;

/// The block of a run with at most this many output rows (the close loop's fits read the
/// sensor and the face mean only): one AVX2 vector instead of four, the same sums.
const SMALL_OUT_BLOCK: usize = 4;

/// The output block of `n_out` rows: [`SMALL_OUT_BLOCK`] for a few, else [`OUT_BLOCK`].
fn out_block(n_out: usize) -> usize {
    if n_out <= SMALL_OUT_BLOCK {
        SMALL_OUT_BLOCK
    } else {
        OUT_BLOCK
    }
}

/// Output rows `c` (n_out, r) row-major in blocks of `block` rows, each block stored mode by
/// mode (`[(b r + i) block + j] = c[b block + j, i]`), the rows padded with zeros to a whole
/// number of blocks.
fn out_blocks(c: &[f64], r: usize, block: usize) -> Vec<f64> {
    let n_out = c.len() / r;
    let mut out = vec![0.0; n_out.div_ceil(block) * block * r];
    for (o, row) in c.chunks_exact(r).enumerate() {
        let (b, j) = (o / block, o % block);
        for (i, &v) in row.iter().enumerate() {
            out[(b * r + i) * block + j] = v;
        }
    }
    out
}

/// `y = C w` from `C` in blocks of `B` rows ([`out_blocks`]); `y` padded to whole blocks.
#[inline(always)]
fn blocks_times<const B: usize>(blocks: &[f64], w: &[f64], y: &mut [f64]) {
    let r = w.len();
    for (block, yb) in blocks.chunks_exact(r * B).zip(y.chunks_exact_mut(B)) {
        let mut acc = [0.0f64; B];
        for (col, &wi) in block.chunks_exact(B).zip(w) {
            for j in 0..B {
                acc[j] += col[j] * wi;
            }
        }
        yb.copy_from_slice(&acc);
    }
}

/// The largest of `y` (`-inf` for none), four lanes at a time.
#[inline(always)]
fn largest(y: &[f64]) -> f64 {
    let mut m = [f64::NEG_INFINITY; 4];
    let mut chunks = y.chunks_exact(4);
    for c in &mut chunks {
        for l in 0..4 {
            m[l] = if c[l] > m[l] { c[l] } else { m[l] };
        }
    }
    chunks
        .remainder()
        .iter()
        .chain(&m)
        .fold(f64::NEG_INFINITY, |top, &v| if v > top { v } else { top })
}

/// A run of propagators that keeps its state `w` in the basis of the propagator that
/// stepped it last. Consecutive steps of one rotated propagator, `ξ ← Q [e ⊙ (Qᵀ ξ) + g ⊙
/// (Qᵀ u)]`, become `w ← e ⊙ w + g ⊙ (Qᵀ u)` with `Qᵀ u` from the basis's rotated input
/// vectors and the outputs from its rotated rows: O(r) a step and input, as a nominal step,
/// instead of three r x r products. `ξ = Q w` is formed only when another basis takes over
/// or the state is handed on. A basis is built the first time a step of its propagator
/// comes (once per run, not per step). Nominal steps are the former ones operation for
/// operation (bit for bit); rotated ones equal them to rounding.
struct BasisRun<'a> {
    props: &'a Propagators,
    /// The input vectors (m, r) and output rows (n_out, r) in modal coordinates.
    inputs: Vec<f64>,
    c: &'a [f64],
    modal: Basis,
    /// Per propagator: its basis once built (rotated ones only).
    rotated: Vec<Option<Basis>>,
    /// The state, in the basis `at` (a propagator's index, or `MODAL`).
    w: Vec<f64>,
    at: usize,
    /// Scratch: the state in modal coordinates (r), the step's input (r), the outputs.
    x: Vec<f64>,
    u: Vec<f64>,
    /// The outputs, padded to whole blocks of `block` rows; `n_out` of them are the model's.
    y: Vec<f64>,
    n_out: usize,
    block: usize,
}

/// The basis `at` of a run (a free function: the caller borrows the run's other fields).
#[inline(always)]
fn basis_at<'b>(modal: &'b Basis, rotated: &'b [Option<Basis>], at: usize) -> &'b Basis {
    if at == MODAL {
        modal
    } else {
        rotated[at]
            .as_ref()
            .expect("a basis is built when the state enters it")
    }
}

impl<'a> BasisRun<'a> {
    /// A run of `props` with input vectors `inputs` (m, r) and output rows `c` (n_out, r),
    /// both row-major in modal coordinates.
    fn new(props: &'a Propagators, inputs: Vec<f64>, c: &'a [f64]) -> Self {
        let r = props.order;
        let n_out = c.len() / r;
        let block = out_block(n_out);
        let modal = Basis {
            b: inputs.clone(),
            ct: out_blocks(c, r, block),
            qt: Vec::new(),
        };
        BasisRun {
            props,
            inputs,
            c,
            modal,
            rotated: vec![None; props.len()],
            w: vec![0.0; r],
            at: MODAL,
            x: vec![0.0; r],
            u: vec![0.0; r],
            y: vec![0.0; n_out.div_ceil(block) * block],
            n_out,
            block,
        }
    }

    /// Start from `xi` (modal coordinates).
    fn start(&mut self, xi: &[f64]) {
        self.w.copy_from_slice(xi);
        self.at = MODAL;
    }

    /// The state in modal coordinates, `ξ = Q w`.
    #[inline(always)]
    fn state(&self, xi: &mut [f64]) {
        if self.at == MODAL {
            xi.copy_from_slice(&self.w);
        } else {
            let qt = &basis_at(&self.modal, &self.rotated, self.at).qt;
            transpose_times(qt, &self.w, xi);
        }
    }

    /// Move the state into propagator `k`'s basis (built if new): nothing when it is there
    /// already (the same propagator, or nominal after nominal).
    #[inline(always)]
    fn enter(&mut self, k: usize) {
        let to = if self.props.rotated[k] { k } else { MODAL };
        if to == self.at {
            return;
        }
        let mut x = std::mem::take(&mut self.x);
        self.state(&mut x);
        if to == MODAL {
            self.w.copy_from_slice(&x);
        } else {
            if self.rotated[k].is_none() {
                self.rotated[k] = Some(self.build(k));
            }
            transpose_times(self.props.basis_matrix(k), &x, &mut self.w);
        }
        self.x = x;
        self.at = to;
    }

    /// Propagator `k`'s rotated basis: `Qᵀ b` for each input vector, `C Q`, `Qᵀ`.
    fn build(&self, k: usize) -> Basis {
        let r = self.props.order;
        let q = self.props.basis_matrix(k);
        let n_out = self.c.len() / r;
        let mut b = vec![0.0; self.inputs.len()];
        for (from, to) in self.inputs.chunks_exact(r).zip(b.chunks_exact_mut(r)) {
            transpose_times(q, from, to);
        }
        // row o of C Q is Qᵀ c_o
        let mut cq = vec![0.0; r * n_out];
        for (row, row_q) in self.c.chunks_exact(r).zip(cq.chunks_exact_mut(r)) {
            transpose_times(q, row, row_q);
        }
        let ct = out_blocks(&cq, r, self.block);
        let mut qt = vec![0.0; r * r];
        for (i, row) in q.chunks_exact(r).enumerate() {
            for (j, &v) in row.iter().enumerate() {
                qt[j * r + i] = v;
            }
        }
        Basis { b, ct, qt }
    }

    /// `y = C ξ` (every output row), from the state in its basis.
    #[inline(always)]
    fn outputs(&mut self) {
        let ct = &basis_at(&self.modal, &self.rotated, self.at).ct;
        if self.block == SMALL_OUT_BLOCK {
            blocks_times::<SMALL_OUT_BLOCK>(ct, &self.w, &mut self.y);
        } else {
            blocks_times::<OUT_BLOCK>(ct, &self.w, &mut self.y);
        }
    }

    /// The outputs onto a piece's rows: the sensor (the first probe), the face mean and the
    /// maximum over the face nodes (NaN when the run has no face-node rows), with `t_ref`
    /// added; NaN for a row not `wanted` (nothing computed).
    #[inline(always)]
    fn emit(&mut self, np: usize, t_ref: f64, rows: &mut PieceRows, wanted: bool) {
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
    fn chain_steps_generic(&mut self, job: &StepsJob, rows: &mut PieceRows) {
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
    unsafe fn chain_steps_avx2(&mut self, job: &StepsJob, rows: &mut PieceRows) {
        self.chain_steps_generic(job, rows);
    }

    /// A run for [`Propagators::simulate_chain`]: the inputs `b_flux` then `b_faces`.
    fn for_chain(props: &'a Propagators, model: &ChainModel<'a>) -> Self {
        let mut inputs = model.b_flux.to_vec();
        inputs.extend_from_slice(model.b_faces);
        BasisRun::new(props, inputs, model.c)
    }
}

/// The steps of one piece to take: `s0 .. s1` of `steps`, at reference `t_ref`; the output
/// rows wanted (`need`, one per row: before the first step and after each; `None`: all).
struct StepsJob<'s, 'a> {
    steps: &'s ChainSteps<'a>,
    s0: usize,
    s1: usize,
    t_ref: f64,
    n_probes: usize,
    need: Option<&'s [bool]>,
}

impl StepsJob<'_, '_> {
    /// Whether output row `i` of the piece is wanted.
    #[inline(always)]
    fn wants(&self, i: usize) -> bool {
        self.need.is_none_or(|need| need[i])
    }
}

/// The rows a piece's steps give, one per output time: sensor, face mean, face maximum.
#[derive(Debug, Default)]
struct PieceRows {
    sensor: Vec<f64>,
    mean: Vec<f64>,
    max: Vec<f64>,
}

/// How the steps of a chain's pieces are taken: the kernel's [`BasisRun`]; the tests keep
/// the former step-by-step rotation as the reference it must equal.
trait PieceStepper {
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
    fn chain_steps(&mut self, job: &StepsJob, rows: &mut PieceRows) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            // SAFETY: the CPU has the features the function is compiled for.
            unsafe { self.chain_steps_avx2(job, rows) };
            return;
        }
        self.chain_steps_generic(job, rows);
    }
}

/// Output rows computed together in [`ModalStepper::outputs`].
const ROW_BLOCK: usize = 6;

/// Events per SIMD block.
const LANES: usize = 8;

/// The inputs of one block of events, row-major (lanes, steps).
struct BlockInputs<'a> {
    flux: &'a [f64],
    drive: &'a [f64],
    t_ref: &'a [f64],
    n_steps: usize,
    /// `n_steps`, or 1 for an air drive constant over each event.
    drive_steps: usize,
}

/// The reduced model's modal input and output arrays, for [`Propagators::simulate_chain`].
#[derive(Debug, Clone, Copy)]
pub struct ChainModel<'a> {
    /// Flux input vector (r).
    pub b_flux: &'a [f64],
    /// Face-set input vectors (F, r) row-major.
    pub b_faces: &'a [f64],
    /// Output rows (n_out, r) row-major: probes, face mean, face-max nodes (none: the
    /// maximum is NaN, and the run computes only the rows it has, as the close loop's fits
    /// do).
    pub c: &'a [f64],
    pub n_probes: usize,
}

/// The steps and pieces of one span's chain, laid out by the caller (see
/// `fleetbrake.simulation.batched`). A *piece* is samples `a ..= b` run from a carried state
/// with one reference temperature: pieces `0 .. J` are the segments of the timeline, in
/// order; the others continue an event's window past its braking segment, un-anchored.
#[derive(Debug, Clone, Copy)]
pub struct ChainSteps<'a> {
    /// Per step (T): flux (W/m²), air temperature (°C), convection per face set (T, F),
    /// propagator index.
    pub flux: &'a [f64],
    pub ambient: &'a [f64],
    pub h: &'a [f64],
    pub prop: &'a [usize],
    /// Per piece (P): first and last sample, time step, steps `step_off[p] .. step_off[p+1]`
    /// (P+1), and for a coarse piece (simulated on its own grid and interpolated to the
    /// seconds) its grid positions `at[at_off[p] .. at_off[p+1]]` (none for a 1 s piece).
    pub piece_a: &'a [usize],
    pub piece_b: &'a [usize],
    pub piece_dt: &'a [f64],
    pub step_off: &'a [usize],
    pub at: &'a [f64],
    pub at_off: &'a [usize],
    /// Per segment (J): the piece continuing its event window (or `usize::MAX`), and the
    /// window's length in samples (0: no window starts there).
    pub seg_cont: &'a [usize],
    pub seg_window: &'a [usize],
}

/// The re-anchoring rule (`fleetbrake.simulation.chains.ChainParams`).
#[derive(Debug, Clone, Copy)]
pub struct AnchorRule {
    pub anchor_s: usize,
    pub anchor_min_readings: usize,
    pub window_s: usize,
    /// A shift found from a segment's own first seconds below this is not applied (K).
    pub tolerance_k: f64,
    /// Sensor lag time constant (s); `None`: no lag.
    pub lag_tau_s: Option<f64>,
}

/// How a segment's field was set: none, uniform start, shifted by the readings before, by
/// its own first readings.
pub const ANCHOR_NONE: u8 = 0;
pub const ANCHOR_START: u8 = 1;
pub const ANCHOR_BEFORE: u8 = 2;
pub const ANCHOR_AFTER: u8 = 3;

/// A span's chain simulated: the timeline (n, NaN where not simulated), per segment the
/// anchoring (code, shift, reference temperature), and the event windows concatenated in
/// segment order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ChainOutputs {
    pub sensor_c: Vec<f64>,
    pub contact_mean_c: Vec<f64>,
    pub contact_max_c: Vec<f64>,
    pub anchor: Vec<u8>,
    pub shift_k: Vec<f64>,
    pub reference_c: Vec<f64>,
    pub window_sensor_c: Vec<f64>,
    pub window_mean_c: Vec<f64>,
    pub window_max_c: Vec<f64>,
}

/// One piece run: outputs at its samples, the state and the lag's last value after it.
#[derive(Debug, Default)]
struct Piece {
    sensor: Vec<f64>,
    mean: Vec<f64>,
    max: Vec<f64>,
    xi: Vec<f64>,
    lag_last: Option<f64>,
}

/// The output rows of piece `p` wanted into `need`: `wanted(i)` for row `i` (sample
/// `piece_a[p] + i`) of a 1 s piece, every row of a coarse one (its grid is interpolated).
fn piece_need(steps: &ChainSteps, p: usize, need: &mut Vec<bool>, wanted: impl Fn(usize) -> bool) {
    let rows = steps.step_off[p + 1] - steps.step_off[p] + 1;
    need.clear();
    if steps.at_off[p + 1] > steps.at_off[p] {
        need.resize(rows, true);
    } else {
        need.extend((0..rows).map(wanted));
    }
}

/// `first_order_lag` of `fleetbrake.model.rom`: exact for a signal linear between samples.
fn lag_filter(x: &mut [f64], dt_s: f64, tau_s: f64, initial: Option<f64>) {
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
fn interp_into(x0: usize, count: usize, xp: &[f64], fp: &[f64], out: &mut Vec<f64>) {
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

/// Mean of `trusted - predicted` over `lo .. hi` where both are finite, if at least
/// `min_count` are.
fn mean_difference(trusted: &[f64], predicted: &[f64], min_count: usize) -> Option<f64> {
    let (mut sum, mut count) = (0.0, 0usize);
    for (t, p) in trusted.iter().zip(predicted) {
        let d = t - p;
        if d.is_finite() {
            sum += d;
            count += 1;
        }
    }
    (count >= min_count && count > 0).then(|| sum / count as f64)
}

impl Propagators {
    /// Run piece `p` from `xi0` at reference `t_ref` (see [`ChainSteps`]).
    #[allow(clippy::too_many_arguments)]
    fn run_piece<S: PieceStepper>(
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

    /// One span's chain: every segment run from the state the one before left, its field
    /// shifted first by the mean of `trusted - predicted` over the `anchor_s` samples before
    /// it (or, with too few readings there, over its own first ones), and the windows of the
    /// events continued un-anchored from their braking segments (the module docs of
    /// `fleetbrake.simulation.chains`). `trusted` and `ambient`: per sample (n).
    pub fn simulate_chain(
        &self,
        model: &ChainModel,
        steps: &ChainSteps,
        trusted: &[f64],
        ambient: &[f64],
        rule: &AnchorRule,
    ) -> Result<ChainOutputs> {
        self.simulate_chain_reading(model, steps, trusted, ambient, rule, None)
    }

    /// [`Propagators::simulate_chain`] with the outputs computed only where they are read
    /// (`windows`: one flag per window output, in the order of `window_*`; `None`: every
    /// output). The state is stepped as by `simulate_chain`; an output is summed only for a
    /// wanted window second and where the anchoring reads the timeline (the `anchor_s`
    /// samples before each segment and its first `anchor_s`), or on every step of a piece
    /// under a sensor lag (the filter runs through them all) and of a coarse piece (its
    /// grid is interpolated): those outputs are `simulate_chain`'s bit for bit, the others
    /// NaN (the close loop's fits read the window seconds with a measurement). With
    /// `windows`, the timeline is the sensor's only, up to the last segment's end (the face
    /// mean's and maximum's empty): a caller reading the windows reads no timeline, and a
    /// fresh n-long vector costs more in page faults than the steps it holds.
    pub fn simulate_chain_reading(
        &self,
        model: &ChainModel,
        steps: &ChainSteps,
        trusted: &[f64],
        ambient: &[f64],
        rule: &AnchorRule,
        windows: Option<&[bool]>,
    ) -> Result<ChainOutputs> {
        let r = self.order;
        let n = trusted.len();
        let n_seg = steps.seg_cont.len();
        let n_piece = steps.piece_a.len();
        let t = steps.prop.len();
        let mismatch = |name: &str, expected: usize, got: usize| {
            Err(ThermalError::LengthMismatch {
                name: name.into(),
                expected,
                got,
            })
        };
        for (name, len, expected) in [
            ("flux input", model.b_flux.len(), r),
            ("step flux", steps.flux.len(), t),
            ("step ambient", steps.ambient.len(), t),
            ("piece_b", steps.piece_b.len(), n_piece),
            ("piece_dt", steps.piece_dt.len(), n_piece),
            ("step offsets", steps.step_off.len(), n_piece + 1),
            ("grid offsets", steps.at_off.len(), n_piece + 1),
            ("segment windows", steps.seg_window.len(), n_seg),
            ("ambient", ambient.len(), n),
        ] {
            if len != expected {
                return mismatch(name, expected, len);
            }
        }
        if model.b_faces.len() % r != 0 || steps.h.len() != t * (model.b_faces.len() / r) {
            return mismatch(
                "step convection",
                t * (model.b_faces.len() / r),
                steps.h.len(),
            );
        }
        if model.c.len() % r != 0 || model.c.len() / r < model.n_probes + 1 || model.n_probes == 0 {
            return mismatch("output rows", (model.n_probes + 1) * r, model.c.len());
        }
        if n_seg > n_piece {
            return mismatch("pieces", n_seg, n_piece);
        }
        if let Some(&bad) = steps.prop.iter().find(|&&k| k >= self.len()) {
            return Err(ThermalError::InvalidParameter {
                name: "propagator index".into(),
                value: bad as f64,
                reason: format!("only {} propagators", self.len()),
            });
        }
        for p in 0..n_piece {
            let (a, b) = (steps.piece_a[p], steps.piece_b[p]);
            let (s0, s1) = (steps.step_off[p], steps.step_off[p + 1]);
            let (a0, a1) = (steps.at_off[p], steps.at_off[p + 1]);
            let grid = if a1 > a0 {
                a1 - a0 - 1
            } else {
                b.wrapping_sub(a)
            };
            let bad = b <= a
                || b >= n
                || s1 < s0
                || s1 > t
                || a1 < a0
                || a1 > steps.at.len()
                || s1 - s0 != grid
                || (a1 > a0 && (steps.at[a0] != a as f64 || steps.at[a1 - 1] != b as f64))
                || !(steps.piece_dt[p] > 0.0);
            if bad {
                return Err(ThermalError::InvalidParameter {
                    name: "chain piece".into(),
                    value: p as f64,
                    reason: format!("piece [{a}, {b}] does not fit its steps or the span"),
                });
            }
        }
        for j in 0..n_seg {
            let c = steps.seg_cont[j];
            if c != usize::MAX
                && (c < n_seg || c >= n_piece || steps.piece_a[c] != steps.piece_b[j])
            {
                return Err(ThermalError::InvalidParameter {
                    name: "window continuation".into(),
                    value: j as f64,
                    reason: "must be a piece starting where its segment ends".into(),
                });
            }
        }
        if let Some(w) = windows {
            let total: usize = steps.seg_window.iter().sum();
            if w.len() != total {
                return mismatch("window outputs wanted", total, w.len());
            }
        }
        let mut stepper = BasisRun::for_chain(self, model);
        Ok(self.chain(&mut stepper, model, steps, trusted, ambient, rule, windows))
    }

    /// [`Propagators::simulate_chain_reading`] on checked inputs, its pieces stepped by
    /// `stepper`.
    #[allow(clippy::too_many_arguments)]
    fn chain<S: PieceStepper>(
        &self,
        stepper: &mut S,
        model: &ChainModel,
        steps: &ChainSteps,
        trusted: &[f64],
        ambient: &[f64],
        rule: &AnchorRule,
        windows: Option<&[bool]>,
    ) -> ChainOutputs {
        let r = self.order;
        let n = trusted.len();
        let n_seg = steps.seg_cont.len();
        let nan = f64::NAN;
        // reading the windows only: the timeline is the sensor's up to the last segment's end
        // (what the anchoring reads), no face mean or maximum (fresh pages cost a fit's
        // evaluation more than its steps)
        let trimmed = windows.is_some();
        let extent = if trimmed {
            steps.piece_b[..n_seg].iter().max().map_or(0, |&b| b + 1)
        } else {
            n
        };
        let timeline = |len: usize| if trimmed { Vec::new() } else { vec![nan; len] };
        // the samples of the timeline the anchoring reads (None: every output wanted)
        let windows = windows.filter(|_| rule.lag_tau_s.is_none());
        let anchored: Option<Vec<bool>> = windows.map(|_| {
            let mut read = vec![false; n];
            for j in 0..n_seg {
                let (a, b) = (steps.piece_a[j], steps.piece_b[j]);
                read[a.saturating_sub(rule.anchor_s)..(a + rule.anchor_s).min(b + 1)].fill(true);
            }
            read
        });
        // the rows wanted of the piece about to run (scratch)
        let mut need: Vec<bool> = Vec::new();
        let mut out = ChainOutputs {
            sensor_c: vec![nan; extent],
            contact_mean_c: timeline(n),
            contact_max_c: timeline(n),
            anchor: vec![ANCHOR_NONE; n_seg],
            shift_k: vec![0.0; n_seg],
            reference_c: vec![nan; n_seg],
            ..Default::default()
        };
        let mut t_ref: Option<f64> = None;
        let mut t_first = 0.0;
        let mut xi = vec![0.0; r];
        let mut lag_last: Option<f64> = None;
        let mut piece = Piece::default();
        let mut more = Piece::default();
        for j in 0..n_seg {
            let (a, b) = (steps.piece_a[j], steps.piece_b[j]);
            let mut anchor = ANCHOR_NONE;
            let mut shift = 0.0;
            let mut reference = match t_ref {
                Some(v) => v,
                None => {
                    let ahead = &trusted[a..(a + rule.window_s).min(n)];
                    let first = ahead.iter().copied().find(|v| v.is_finite());
                    let v = first.unwrap_or(ambient[a]);
                    t_first = v;
                    xi.fill(0.0);
                    anchor = ANCHOR_START;
                    v
                }
            };
            let size = steps.seg_window[j];
            let woff = out.window_sensor_c.len();
            let seg_need = match (windows, &anchored) {
                (Some(w), Some(read)) => {
                    piece_need(steps, j, &mut need, |i| {
                        read[a + i] || (i < size && w[woff + i])
                    });
                    Some(need.as_slice())
                }
                _ => None,
            };
            let lo = a.saturating_sub(rule.anchor_s);
            let back = mean_difference(
                &trusted[lo..a],
                &out.sensor_c[lo..a],
                rule.anchor_min_readings,
            );
            if let Some(m) = back {
                shift = m;
                reference += shift;
                anchor = ANCHOR_BEFORE;
                self.run_piece(
                    stepper, model, steps, j, reference, &xi, lag_last, rule, t_first, seg_need,
                    &mut piece,
                );
            } else {
                self.run_piece(
                    stepper, model, steps, j, reference, &xi, lag_last, rule, t_first, seg_need,
                    &mut piece,
                );
                let length = rule.anchor_s.min(piece.sensor.len());
                let own = mean_difference(
                    &trusted[a..a + length],
                    &piece.sensor[..length],
                    rule.anchor_min_readings,
                );
                if let Some(m) = own.filter(|m| m.abs() > rule.tolerance_k) {
                    shift = m;
                    reference += shift;
                    if anchor == ANCHOR_NONE {
                        anchor = ANCHOR_AFTER;
                    }
                    self.run_piece(
                        stepper, model, steps, j, reference, &xi, lag_last, rule, t_first,
                        seg_need, &mut piece,
                    );
                }
            }
            t_ref = Some(reference);
            out.anchor[j] = anchor;
            out.shift_k[j] = shift;
            out.reference_c[j] = reference;
            if size > 0 {
                let own = size.min(piece.sensor.len());
                out.window_sensor_c.extend_from_slice(&piece.sensor[..own]);
                out.window_mean_c.extend_from_slice(&piece.mean[..own]);
                out.window_max_c.extend_from_slice(&piece.max[..own]);
                let c = steps.seg_cont[j];
                if own < size && c != usize::MAX {
                    // its row i is the window's second own + i - 1 (row 0: the segment's end)
                    let more_need = windows.map(|w| {
                        piece_need(steps, c, &mut need, |i| {
                            i >= 1 && own + i - 1 < size && w[woff + own + i - 1]
                        });
                        need.as_slice()
                    });
                    self.run_piece(
                        stepper,
                        model,
                        steps,
                        c,
                        reference,
                        &piece.xi,
                        piece.lag_last,
                        rule,
                        t_first,
                        more_need,
                        &mut more,
                    );
                    let rest = (size - own).min(more.sensor.len() - 1);
                    out.window_sensor_c
                        .extend_from_slice(&more.sensor[1..=rest]);
                    out.window_mean_c.extend_from_slice(&more.mean[1..=rest]);
                    out.window_max_c.extend_from_slice(&more.max[1..=rest]);
                }
            }
            std::mem::swap(&mut xi, &mut piece.xi);
            lag_last = piece.lag_last;
            out.sensor_c[a..=b].copy_from_slice(&piece.sensor);
            if !trimmed {
                out.contact_mean_c[a..=b].copy_from_slice(&piece.mean);
                out.contact_max_c[a..=b].copy_from_slice(&piece.max);
            }
        }
        out
    }
}

/// The distinct step systems of a chain's steps and each step's among them (see
/// [`step_systems`]).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct StepSystems {
    /// (K, F) row-major: each system's convection change from nominal per face set.
    pub dh: Vec<f64>,
    /// (K) each system's time step.
    pub dt_s: Vec<f64>,
    /// (T) each step's system.
    pub index: Vec<usize>,
}

/// `rint(x)` (numpy's rounding: to the nearest integer, half way to even) without a call:
/// `f64::round_ties_even` is a library call on a CPU baseline without SSE4.1, this the
/// classic `2^52` sum (exact: below `2^52` the sum's rounding is the integer's, from `2^52`
/// on every float is an integer), the sign kept (`-0.3` gives `-0.0`), NaN and infinities as
/// they are.
#[inline(always)]
fn rint(x: f64) -> f64 {
    const TWO_52: f64 = 4_503_599_627_370_496.0;
    let a = x.abs();
    if a < TWO_52 {
        ((a + TWO_52) - TWO_52).copysign(x)
    } else {
        x
    }
}

/// `numpy.round(x, 12)`: `rint(x 1e12) / 1e12`, as numpy computes it.
#[inline(always)]
fn round_12(x: f64) -> f64 {
    rint(x * 1e12) / 1e12
}

/// The step systems of a chain's steps, as `fleetbrake.model.rom.ReducedModel.simulate_chain`
/// keys its propagators: each step's convection change from nominal per face set, `dh =
/// round(h - h_nominal, 12)` (numpy's rounding, bit for bit), with its piece's time step
/// (`piece_dt`, the steps `step_off[p] .. step_off[p+1]` of piece `p`). Returns the
/// distinct (dh, dt) in the order they first come (zeros told apart by their sign: either
/// is the nominal system) and each step's index among them; one pass over the steps, a
/// step with the convection and time step of the one before taking its index. `h` (T, F)
/// row-major, `h_nominal` (F).
pub fn step_systems(
    h: &[f64],
    h_nominal: &[f64],
    piece_dt: &[f64],
    step_off: &[usize],
) -> Result<StepSystems> {
    let t = step_off.last().copied().unwrap_or(0);
    let mut index = vec![0; t];
    let (dh, dt_s) = systems_with(h, h_nominal, piece_dt, step_off, |s, k| index[s] = k)?;
    Ok(StepSystems { dh, dt_s, index })
}

/// [`step_systems`] with each step's system written into `index` (T, as the int64 Python
/// reads; the caller's buffer: no fresh pages); the distinct (dh, dt) returned.
pub fn step_systems_into(
    h: &[f64],
    h_nominal: &[f64],
    piece_dt: &[f64],
    step_off: &[usize],
    index: &mut [i64],
) -> Result<(Vec<f64>, Vec<f64>)> {
    let t = step_off.last().copied().unwrap_or(0);
    if index.len() != t {
        return Err(ThermalError::LengthMismatch {
            name: "step system index".into(),
            expected: t,
            got: index.len(),
        });
    }
    systems_with(h, h_nominal, piece_dt, step_off, |s, k| index[s] = k as i64)
}

/// [`step_systems`]' pass: each step's system handed to `set(step, system)`; the distinct
/// (dh (K, F), dt (K)) returned.
fn systems_with(
    h: &[f64],
    h_nominal: &[f64],
    piece_dt: &[f64],
    step_off: &[usize],
    mut set: impl FnMut(usize, usize),
) -> Result<(Vec<f64>, Vec<f64>)> {
    use std::collections::HashMap;
    let f = h_nominal.len();
    let t = step_off.last().copied().unwrap_or(0);
    if step_off.len() != piece_dt.len() + 1 {
        return Err(ThermalError::LengthMismatch {
            name: "step offsets".into(),
            expected: piece_dt.len() + 1,
            got: step_off.len(),
        });
    }
    if let Some(p) = step_off.windows(2).position(|w| w[1] < w[0]) {
        return Err(ThermalError::InvalidParameter {
            name: "step offsets".into(),
            value: p as f64,
            reason: "must not decrease".into(),
        });
    }
    if h.len() != t * f || step_off.first().is_some_and(|&s| s != 0) {
        return Err(ThermalError::LengthMismatch {
            name: "step convection".into(),
            expected: t * f,
            got: h.len(),
        });
    }
    let mut out = StepSystems::default();
    let mut seen: HashMap<Vec<u64>, usize> = HashMap::new();
    let mut key = vec![0u64; f + 1];
    let mut row = vec![0.0; f];
    // the step before: its convection (bits) and time step, and its system
    let mut before: Option<(usize, u64, usize)> = None;
    for (p, &dt) in piece_dt.iter().enumerate() {
        let dt_bits = dt.to_bits();
        for s in step_off[p]..step_off[p + 1] {
            let hs = &h[s * f..(s + 1) * f];
            if let Some((prev, prev_dt, k)) = before {
                let same = prev_dt == dt_bits
                    && hs
                        .iter()
                        .zip(&h[prev * f..(prev + 1) * f])
                        .all(|(a, b)| a.to_bits() == b.to_bits());
                if same {
                    set(s, k);
                    before = Some((s, dt_bits, k));
                    continue;
                }
            }
            for ((d, kb), (&hv, &h0)) in row
                .iter_mut()
                .zip(key.iter_mut())
                .zip(hs.iter().zip(h_nominal))
            {
                *d = round_12(hv - h0);
                *kb = d.to_bits();
            }
            key[f] = dt_bits;
            let k = match seen.get(key.as_slice()) {
                Some(&k) => k,
                None => {
                    let k = out.dt_s.len();
                    seen.insert(key.clone(), k);
                    out.dh.extend_from_slice(&row);
                    out.dt_s.push(dt);
                    k
                }
            };
            set(s, k);
            before = Some((s, dt_bits, k));
        }
    }
    Ok((out.dh, out.dt_s))
}

/// A chain's convection per step (T, F) row-major from the per-sample convection of its
/// sources (`fleetbrake.closeloop.fitdata`: the fine samples, then each coarse grid), as
/// `ReducedModel.simulate_chain`'s callers form it: each source's step means `0.5 (h_k +
/// h_k+1)` concatenated, the chain's step `t` taking step `gather[t]` of them, and on every
/// piece (steps `step_off[p] .. step_off[p+1]`) where a face set's convection varies, that
/// face's steps rounded to `quantum` (`round(h / quantum) quantum`, numpy's rounding, half to
/// even); bit for bit numpy's. `samples[f * S + i]`: face set `f`'s series on source `i` (S
/// sources, each face's the same lengths).
pub fn chain_step_convection(
    samples: &[&[f64]],
    n_faces: usize,
    gather: &[usize],
    step_off: &[usize],
    quantum: f64,
) -> Result<Vec<f64>> {
    let mut h = vec![0.0; gather.len() * n_faces];
    chain_step_convection_into(samples, n_faces, gather, step_off, quantum, &mut h)?;
    Ok(h)
}

/// [`chain_step_convection`] into the caller's `h` (T, F) row-major (a buffer whose pages
/// are there already: a fresh vector's cost the kernel's time in page faults).
pub fn chain_step_convection_into(
    samples: &[&[f64]],
    n_faces: usize,
    gather: &[usize],
    step_off: &[usize],
    quantum: f64,
    h: &mut [f64],
) -> Result<()> {
    let sources = samples.len().checked_div(n_faces).unwrap_or(0);
    if sources * n_faces != samples.len() {
        return Err(ThermalError::LengthMismatch {
            name: "convection series (faces x sources)".into(),
            expected: sources * n_faces,
            got: samples.len(),
        });
    }
    let lengths: Vec<usize> = samples[..sources].iter().map(|x| x.len()).collect();
    for (f, face) in samples.chunks_exact(sources.max(1)).enumerate() {
        if let Some(i) = (0..sources).find(|&i| face[i].len() != lengths[i]) {
            return Err(ThermalError::LengthMismatch {
                name: format!("convection of face set {f} on source {i}"),
                expected: lengths[i],
                got: face[i].len(),
            });
        }
    }
    if let Some(i) = lengths.iter().position(|&len| len < 2) {
        return Err(ThermalError::InvalidParameter {
            name: "convection source".into(),
            value: i as f64,
            reason: "needs two samples or more".into(),
        });
    }
    let t = gather.len();
    let total: usize = lengths.iter().map(|len| len - 1).sum();
    if step_off.first().is_some_and(|&s| s != 0)
        || step_off.last().is_some_and(|&s| s != t)
        || step_off.windows(2).any(|w| w[1] < w[0])
    {
        return Err(ThermalError::InvalidParameter {
            name: "step offsets".into(),
            value: t as f64,
            reason: "must rise from 0 to the number of steps".into(),
        });
    }
    if let Some(&bad) = gather.iter().find(|&&g| g >= total) {
        return Err(ThermalError::InvalidParameter {
            name: "step gather".into(),
            value: bad as f64,
            reason: format!("only {total} source steps"),
        });
    }
    // each source's first step among the concatenated ones
    let mut first_step = Vec::with_capacity(sources + 1);
    first_step.push(0);
    for len in &lengths {
        first_step.push(first_step.last().copied().unwrap_or(0) + len - 1);
    }
    if h.len() != t * n_faces {
        return Err(ThermalError::LengthMismatch {
            name: "step convection".into(),
            expected: t * n_faces,
            got: h.len(),
        });
    }
    let mut i = 0; // the source of the step before (the gather runs through a source in order)
    for (row, &g) in h.chunks_exact_mut(n_faces.max(1)).zip(gather) {
        if !(first_step[i] <= g && g < first_step[i + 1]) {
            i = first_step.partition_point(|&s| s <= g) - 1;
        }
        let k = g - first_step[i];
        for (f, v) in row.iter_mut().enumerate() {
            let x = samples[f * sources + i];
            *v = 0.5 * (x[k] + x[k + 1]);
        }
    }
    for piece in step_off.windows(2) {
        let (s0, s1) = (piece[0], piece[1]);
        if s1 == s0 {
            continue;
        }
        let rows = &mut h[s0 * n_faces..s1 * n_faces];
        for f in 0..n_faces {
            let first = rows[f];
            // numpy's max != min over the piece: NaN counts as varying
            let varying =
                first.is_nan() || rows.iter().skip(f).step_by(n_faces).any(|&v| v != first);
            if varying {
                for v in rows.iter_mut().skip(f).step_by(n_faces) {
                    *v = rint(*v / quantum) * quantum;
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The former step of propagator `k` (kept as the tests' reference): a rotated one
    /// rotates in and out every step, `ξ ← Q [e ⊙ (Qᵀ ξ) + g ⊙ (Qᵀ u)]`.
    fn apply_step_by_step(
        props: &Propagators,
        k: usize,
        xi: &mut [f64],
        u: &[f64],
        w: &mut [f64],
        v: &mut [f64],
    ) {
        let r = props.order;
        let e = &props.e[k * r..(k + 1) * r];
        let g = &props.g[k * r..(k + 1) * r];
        if !props.rotated[k] {
            for i in 0..r {
                xi[i] = e[i] * xi[i] + g[i] * u[i];
            }
            return;
        }
        let q = &props.q[k * r * r..(k + 1) * r * r];
        w.fill(0.0);
        v.fill(0.0);
        for (row, (&x, &ui)) in q.chunks_exact(r).zip(xi.iter().zip(u)) {
            for j in 0..r {
                w[j] += row[j] * x;
                v[j] += row[j] * ui;
            }
        }
        for j in 0..r {
            w[j] = e[j] * w[j] + g[j] * v[j];
        }
        for (row, x) in q.chunks_exact(r).zip(xi.iter_mut()) {
            *x = row.iter().zip(w.iter()).map(|(a, b)| a * b).sum();
        }
    }

    /// The chain's former piece stepping, in modal coordinates step by step: the reference.
    struct StepByStep<'a> {
        props: &'a Propagators,
        model: ChainModel<'a>,
    }

    impl PieceStepper for StepByStep<'_> {
        fn run(&mut self, job: &StepsJob, xi: &mut [f64], rows: &mut PieceRows) {
            let (props, model, steps, t_ref) = (self.props, &self.model, job.steps, job.t_ref);
            let r = props.order;
            let n_faces = model.b_faces.len() / r;
            let n_out = model.c.len() / r;
            let np = model.n_probes;
            let (mut w, mut v, mut u) = (vec![0.0; r], vec![0.0; r], vec![0.0; r]);
            let mut y = vec![0.0; n_out];
            let mut emit = |xi: &[f64], wanted: bool| {
                if !wanted {
                    rows.sensor.push(f64::NAN);
                    rows.mean.push(f64::NAN);
                    rows.max.push(f64::NAN);
                    return;
                }
                for (yo, row) in y.iter_mut().zip(model.c.chunks_exact(r)) {
                    *yo = row.iter().zip(xi).map(|(a, b)| a * b).sum();
                }
                let top = y[np + 1..].iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v));
                rows.sensor.push(y[0] + t_ref);
                rows.mean.push(y[np] + t_ref);
                rows.max.push(top + t_ref);
            };
            emit(xi, job.wants(0));
            for s in job.s0..job.s1 {
                let q = steps.flux[s];
                let air = steps.ambient[s] - t_ref;
                for (ui, &b) in u.iter_mut().zip(model.b_flux) {
                    *ui = q * b;
                }
                for f in 0..n_faces {
                    let d = steps.h[s * n_faces + f] * air;
                    for (ui, &b) in u.iter_mut().zip(&model.b_faces[f * r..(f + 1) * r]) {
                        *ui += d * b;
                    }
                }
                apply_step_by_step(props, steps.prop[s], xi, &u, &mut w, &mut v);
                emit(xi, job.wants(s + 1 - job.s0));
            }
        }
    }

    /// An orthogonal 4 x 4 basis (row-major): plane rotations by `angles` in (0,1), (1,2),
    /// (2,3), (0,3).
    fn basis4(angles: [f64; 4]) -> Vec<f64> {
        let mut q = vec![0.0; 16];
        for i in 0..4 {
            q[i * 4 + i] = 1.0;
        }
        for (&(a, b), &t) in [(0, 1), (1, 2), (2, 3), (0, 3)].iter().zip(&angles) {
            let (c, s) = (t.cos(), t.sin());
            for row in q.chunks_exact_mut(4) {
                let (x, y) = (row[a], row[b]);
                row[a] = c * x - s * y;
                row[b] = s * x + c * y;
            }
        }
        q
    }

    /// Six propagators of four modes: nominal and rotated (three bases) at 1 s, one rotated
    /// and the nominal at 5 s.
    fn switching_propagators() -> Propagators {
        let lam = [0.002, 0.02, 0.1, 0.5];
        let shifted = |f: f64, add: f64| -> Vec<f64> { lam.iter().map(|l| l * f + add).collect() };
        let table: [(Vec<f64>, Option<Vec<f64>>, f64); 6] = [
            (lam.to_vec(), None, 1.0),
            (
                shifted(1.3, 0.004),
                Some(basis4([0.3, -0.2, 0.5, 0.1])),
                1.0,
            ),
            (
                shifted(1.7, 0.011),
                Some(basis4([-0.4, 0.6, 0.2, -0.3])),
                1.0,
            ),
            (
                shifted(1.3, 0.004),
                Some(basis4([0.3, -0.2, 0.5, 0.1])),
                5.0,
            ),
            (lam.to_vec(), None, 5.0),
            (shifted(2.1, 0.02), Some(basis4([0.7, 0.1, -0.6, 0.4])), 1.0),
        ];
        let (mut e, mut g, mut q, mut rotated) = (vec![], vec![], vec![], vec![]);
        for (l, basis, dt) in table {
            let (ek, gk) = exact_propagator(&l, dt);
            e.extend(ek);
            g.extend(gk);
            rotated.push(basis.is_some());
            q.extend(basis.unwrap_or(vec![0.0; 16]));
        }
        Propagators::new(4, e, g, q, rotated).unwrap()
    }

    fn max_difference(a: &[f64], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| {
                assert_eq!(x.is_nan(), y.is_nan());
                if x.is_nan() {
                    0.0
                } else {
                    (x - y).abs()
                }
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn a_chain_kept_in_its_rotated_bases_equals_stepping_by_the_formula() {
        // three segments (the last on a 5 s grid), a window continued past the second,
        // readings that shift the second from before it and the third from its own first
        // seconds, a sensor lag; the propagators switch every few steps among the nominal
        // and three rotated bases, and runs of one propagator cross the pieces' ends
        let props = switching_propagators();
        let model = ChainModel {
            b_flux: &[2e-6, 1e-5, 5e-5, 1e-4],
            b_faces: &[-0.02, 0.01, -0.03, 0.005, 0.004, -0.015, 0.02, -0.01],
            c: &[
                1.0, 0.6, 0.3, -0.2, 0.9, 0.4, 0.1, 0.2, 1.1, 0.8, -0.3, 0.5, 0.7, 1.2, 0.2, -0.1,
                0.95, 0.3, 0.6, 0.4,
            ],
            n_probes: 1,
        };
        let n = 121;
        let t = 118;
        let fine = [0usize, 1, 1, 1, 2, 2, 1, 0, 2, 2, 5, 5];
        let coarse = [3usize, 3, 4, 3, 3, 3, 4, 4];
        let prop: Vec<usize> = (0..t)
            .map(|s| match s {
                80..=87 => coarse[s - 80],
                _ => fine[(s / 3) % fine.len()],
            })
            .collect();
        let flux: Vec<f64> = (0..t)
            .map(|s| if (s / 10) % 3 == 0 { 4e4 } else { 0.0 })
            .collect();
        let ambient: Vec<f64> = (0..t).map(|s| 8.0 + 0.05 * s as f64).collect();
        let h: Vec<f64> = (0..2 * t).map(|k| 15.0 + ((k * 7) % 11) as f64).collect();
        let at: Vec<f64> = (0..9).map(|k| (80 + 5 * k) as f64).collect();
        let steps = ChainSteps {
            flux: &flux,
            ambient: &ambient,
            h: &h,
            prop: &prop,
            piece_a: &[0, 40, 80, 80],
            piece_b: &[40, 80, 120, 110],
            piece_dt: &[1.0, 1.0, 5.0, 1.0],
            step_off: &[0, 40, 80, 88, 118],
            at: &at,
            at_off: &[0, 0, 0, 9, 9],
            seg_cont: &[usize::MAX, 3, usize::MAX],
            seg_window: &[0, 60, 0],
        };
        let mut trusted = vec![f64::NAN; n];
        trusted[..3].fill(21.0);
        trusted[35..40].fill(60.0);
        trusted[80..86].fill(20.0);
        let air = vec![9.0; n];
        let rule = AnchorRule {
            anchor_s: 5,
            anchor_min_readings: 3,
            window_s: 10,
            tolerance_k: 1e-3,
            lag_tau_s: Some(20.0),
        };
        let kept = props
            .simulate_chain(&model, &steps, &trusted, &air, &rule)
            .unwrap();
        let mut by_formula = StepByStep {
            props: &props,
            model,
        };
        let reference = props.chain(&mut by_formula, &model, &steps, &trusted, &air, &rule, None);
        // the chain exercises what it should: a start, a shift from before, one from after,
        // a window continued past its segment
        assert_eq!(
            reference.anchor,
            vec![ANCHOR_START, ANCHOR_BEFORE, ANCHOR_AFTER]
        );
        assert_eq!(reference.window_sensor_c.len(), 60);
        assert_eq!(kept.anchor, reference.anchor);
        let spread = reference
            .sensor_c
            .iter()
            .filter(|v| v.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        assert!(spread.1 - spread.0 > 5.0, "a chain that heats: {spread:?}");
        for (name, a, b) in [
            ("sensor", &kept.sensor_c, &reference.sensor_c),
            (
                "contact mean",
                &kept.contact_mean_c,
                &reference.contact_mean_c,
            ),
            ("contact max", &kept.contact_max_c, &reference.contact_max_c),
            ("shift", &kept.shift_k, &reference.shift_k),
            ("reference", &kept.reference_c, &reference.reference_c),
            (
                "window sensor",
                &kept.window_sensor_c,
                &reference.window_sensor_c,
            ),
            ("window mean", &kept.window_mean_c, &reference.window_mean_c),
            ("window max", &kept.window_max_c, &reference.window_max_c),
        ] {
            let d = max_difference(a, b);
            assert!(d <= 1e-10, "{name}: {d:e} K from the step-by-step formula");
        }
        // the sensor and the face mean only (the close loop's fits: two output rows, one
        // small block): the same sums, bit for bit; no maximum
        let two = ChainModel {
            c: &model.c[..2 * 4],
            ..model
        };
        let few = props
            .simulate_chain(&two, &steps, &trusted, &air, &rule)
            .unwrap();
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for (name, a, b) in [
            ("sensor", &few.sensor_c, &kept.sensor_c),
            ("contact mean", &few.contact_mean_c, &kept.contact_mean_c),
            ("shift", &few.shift_k, &kept.shift_k),
            ("reference", &few.reference_c, &kept.reference_c),
            ("window sensor", &few.window_sensor_c, &kept.window_sensor_c),
            ("window mean", &few.window_mean_c, &kept.window_mean_c),
        ] {
            assert_eq!(bits(a), bits(b), "{name}");
        }
        assert_eq!(few.anchor, kept.anchor);
        assert!(few.contact_max_c.iter().all(|v| v.is_nan()));
        assert!(few.window_max_c.iter().all(|v| v.is_nan()));
        assert_eq!(few.window_max_c.len(), kept.window_max_c.len());
        // the outputs only where they are read: the wanted window seconds (in the braking
        // segment and in its continuation) bit for bit, the others NaN; the anchoring (from
        // the seconds before the second segment, from the first ones of the first) the same
        let wanted: Vec<bool> = (0..60).map(|i| i % 7 == 2 || i == 0 || i == 59).collect();
        for lag in [None, Some(20.0)] {
            let rule = AnchorRule {
                lag_tau_s: lag,
                ..rule
            };
            let full = props
                .simulate_chain(&two, &steps, &trusted, &air, &rule)
                .unwrap();
            let read = props
                .simulate_chain_reading(&two, &steps, &trusted, &air, &rule, Some(&wanted))
                .unwrap();
            assert_eq!(read.anchor, full.anchor);
            assert_eq!(bits(&read.shift_k), bits(&full.shift_k));
            assert_eq!(bits(&read.reference_c), bits(&full.reference_c));
            for (i, &w) in wanted.iter().enumerate() {
                for (a, b) in [
                    (read.window_sensor_c[i], full.window_sensor_c[i]),
                    (read.window_mean_c[i], full.window_mean_c[i]),
                ] {
                    // under a lag every output is computed (the filter runs through them);
                    // without, the wanted ones and those the anchoring reads: window second
                    // i is sample 40 + i, of the second segment up to 40, of its
                    // continuation after
                    let anchoring = i <= 40 && (35..45).chain(75..85).any(|k| k == 40 + i);
                    if w || anchoring || lag.is_some() {
                        assert_eq!(a.to_bits(), b.to_bits(), "window second {i}");
                    } else {
                        assert!(a.is_nan(), "window second {i} not wanted: {a}");
                    }
                }
            }
            assert!(read.contact_mean_c.is_empty() && read.contact_max_c.is_empty());
            assert_eq!(read.sensor_c.len(), n);
            if lag.is_none() {
                // the timeline where the anchoring reads it, at the wanted window seconds
                // and on the coarse piece (80 ..= 120) only
                for (k, v) in read.sensor_c.iter().enumerate() {
                    let window = (40..=80).contains(&k) && wanted[k - 40];
                    let expected = k < 5 || (35..45).contains(&k) || k >= 75 || window;
                    assert_eq!(v.is_finite(), expected, "sample {k}: {v}");
                }
                for k in 35..40 {
                    assert_eq!(read.sensor_c[k].to_bits(), full.sensor_c[k].to_bits());
                }
            } else {
                assert_eq!(bits(&read.sensor_c), bits(&full.sensor_c));
            }
        }
        assert!(props
            .simulate_chain_reading(&two, &steps, &trusted, &air, &rule, Some(&wanted[1..]))
            .is_err());
        // nominal steps are the former ones operation for operation: bit for bit
        let nominal: Vec<usize> = prop.iter().map(|&k| if k < 3 { 0 } else { 4 }).collect();
        let steps = ChainSteps {
            prop: &nominal,
            ..steps
        };
        let kept = props
            .simulate_chain(&model, &steps, &trusted, &air, &rule)
            .unwrap();
        let reference = props.chain(&mut by_formula, &model, &steps, &trusted, &air, &rule, None);
        assert_eq!(kept, reference);
    }

    #[test]
    fn rint_is_round_ties_even() {
        let mut x = 0.123_f64;
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            1.5,
            2.5,
            -0.5,
            -1.5,
            -2.5,
            0.49999999999999994,
            -0.3,
            4_503_599_627_370_495.5,
            4_503_599_627_370_497.0,
            1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::MIN_POSITIVE,
            5e-324,
        ];
        for _ in 0..20_000 {
            x = (x * 3.7 + 0.31).fract();
            values.push((x - 0.5) * 1e3);
            values.push(((x - 0.5) * 1e3).floor() + 0.5);
            values.push((x - 0.5) * 1e17);
        }
        for v in values {
            assert_eq!(rint(v).to_bits(), v.round_ties_even().to_bits(), "{v:e}");
        }
        assert!(rint(f64::NAN).is_nan());
    }

    #[test]
    fn step_convection_is_the_sources_step_means_gathered_and_rounded_where_it_varies() {
        // two face sets on a fine source (7 samples) and a coarse one (4): the chain's steps
        // take the fine steps 0..3, the coarse 0..2 (a piece of their own), the fine 3..5
        let fine_air = [10.0, 10.3, 10.9, 11.0, 10.25, 10.0, 10.0];
        let fine_friction = [0.0; 7];
        let coarse_air = [12.1, 12.1, 12.1, 12.1];
        let coarse_friction = [1.0, 2.0, 3.0, 3.6];
        let samples: [&[f64]; 4] = [&fine_air, &coarse_air, &fine_friction, &coarse_friction];
        let gather = [0usize, 1, 2, 6, 7, 8, 3, 4, 5];
        let step_off = [0usize, 3, 6, 9];
        let h = chain_step_convection(&samples, 2, &gather, &step_off, 0.25).unwrap();
        let air: Vec<f64> = h.iter().step_by(2).copied().collect();
        let friction: Vec<f64> = h.iter().skip(1).step_by(2).copied().collect();
        // numpy: 0.5 (h_k + h_k+1), np.round(h / 0.25) * 0.25 on a piece where it varies
        let round = |v: f64| (v / 0.25).round_ties_even() * 0.25;
        let mean = |x: &[f64], k: usize| 0.5 * (x[k] + x[k + 1]);
        let expect_air: Vec<f64> = [
            round(mean(&fine_air, 0)),
            round(mean(&fine_air, 1)),
            round(mean(&fine_air, 2)),
            mean(&coarse_air, 0), // constant on its piece: as it is (12.1, not rounded)
            mean(&coarse_air, 1),
            mean(&coarse_air, 2),
            round(mean(&fine_air, 3)),
            round(mean(&fine_air, 4)),
            round(mean(&fine_air, 5)),
        ]
        .to_vec();
        assert_eq!(air, expect_air);
        assert_eq!(air[3], 12.1);
        // half way rounds to even: 10.625 / 0.25 = 42.5 -> 42, 10.125 / 0.25 = 40.5 -> 40
        assert_eq!((air[6], air[7]), (10.5, 10.0));
        assert_eq!(&friction[..3], &[0.0; 3]);
        assert_eq!(&friction[3..6], &[1.5, 2.5, 3.25]);
        // a step gathered from the wrong source step, or pieces cut elsewhere, differ
        let shifted = [1usize, 2, 3, 6, 7, 8, 3, 4, 5];
        assert_ne!(
            chain_step_convection(&samples, 2, &shifted, &step_off, 0.25).unwrap(),
            h
        );
        let merged = [0usize, 6, 9];
        assert_ne!(
            chain_step_convection(&samples, 2, &gather, &merged, 0.25).unwrap(),
            h
        );
        assert!(chain_step_convection(&samples, 2, &[0, 9], &[0, 2], 0.25).is_err());
        assert!(chain_step_convection(&samples[..3], 2, &gather, &step_off, 0.25).is_err());
    }

    #[test]
    fn step_systems_are_numpys_rounded_keys_in_the_order_they_come() {
        let h_nominal = [10.0, 0.0];
        // piece 0 at 1 s (5 steps), piece 1 at 5 s (3 steps)
        let rows: [[f64; 2]; 8] = [
            [10.0, 0.0],              // nominal
            [10.0, 0.0],              // the same as the step before
            [12.5, 0.3],              // new
            [10.0 + 1e-14, 0.0],      // rounds to the nominal's change (0): the first system
            [12.5, 0.3],              // seen before, not the step before
            [12.5, 0.3],              // the same convection at 5 s: a system of its own
            [11.23456789012345, 0.0], // rounded to 12 decimals
            [10.0, 0.0],              // the nominal at 5 s
        ];
        let h: Vec<f64> = rows.concat();
        let out = step_systems(&h, &h_nominal, &[1.0, 5.0], &[0, 5, 8]).unwrap();
        assert_eq!(out.index, vec![0, 0, 1, 0, 1, 2, 3, 4]);
        assert_eq!(out.dt_s, vec![1.0, 1.0, 5.0, 5.0, 5.0]);
        assert_eq!(
            out.dh,
            vec![0.0, 0.0, 2.5, 0.3, 2.5, 0.3, 1.234567890123, 0.0, 0.0, 0.0]
        );
        // a piece without steps, and no steps at all
        let out = step_systems(&h[..4], &h_nominal, &[1.0, 2.0, 1.0], &[0, 1, 1, 2]).unwrap();
        assert_eq!(out.index, vec![0, 0]);
        let none = step_systems(&[], &h_nominal, &[], &[0]).unwrap();
        assert!(none.index.is_empty() && none.dt_s.is_empty());
        // lengths that do not fit
        assert!(step_systems(&h[..6], &h_nominal, &[1.0], &[0, 2]).is_err());
        assert!(step_systems(&h, &h_nominal, &[1.0, 5.0], &[0, 5]).is_err());
        assert!(step_systems(&h, &h_nominal, &[1.0, 5.0], &[0, 6, 5]).is_err());
    }

    #[test]
    fn a_switched_run_kept_in_its_rotated_bases_equals_stepping_by_the_formula() {
        let props = switching_propagators();
        let r = 4;
        let c = [1.0, 0.6, 0.3, -0.2, 0.9, 0.4, 0.1, 0.2, 1.1, 0.8, -0.3, 0.5];
        let s = 60;
        let index: Vec<usize> = (0..s)
            .map(|k| [1, 1, 2, 0, 0, 2, 2, 5, 3, 1][(k / 2) % 10])
            .collect();
        let repeats: Vec<u32> = (0..s).map(|k| 1 + (k % 3) as u32).collect();
        let u: Vec<f64> = (0..s * r).map(|k| ((k * 13) % 7) as f64 - 2.5).collect();
        let xi0 = [3.0, -1.0, 0.5, 2.0];
        let (y, xi) = props.simulate(&index, &repeats, &u, &xi0, &c).unwrap();
        let mut x = xi0.to_vec();
        let (mut w, mut v) = (vec![0.0; r], vec![0.0; r]);
        let outputs = |x: &[f64]| -> Vec<f64> {
            c.chunks_exact(r)
                .map(|row| row.iter().zip(x).map(|(a, b)| a * b).sum())
                .collect()
        };
        let mut expected = outputs(&x);
        for k in 0..s {
            for _ in 0..repeats[k] {
                apply_step_by_step(
                    &props,
                    index[k],
                    &mut x,
                    &u[k * r..(k + 1) * r],
                    &mut w,
                    &mut v,
                );
            }
            expected.extend(outputs(&x));
        }
        assert!(max_difference(&y, &expected) <= 1e-10);
        assert!(max_difference(&xi, &x) <= 1e-10);
        assert!(x.iter().any(|v| v.abs() > 1.0));
    }

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

    #[test]
    fn one_mode_matches_the_exact_exponential_response() {
        // θ' = −λ θ + b q: from rest under constant q, θ(t) = b q (1 − e^{−λ t}) / λ
        let (lam, b, q) = (0.05, 2.0, 3.0);
        let c = vec![1.0, 1.0, 1.0]; // probe, mean, one face node: all read the mode
        let s = ModalStepper::new(&[lam], &[b], &[0.0], c, 1, 1.0).unwrap();
        let n = 50;
        let out = s
            .simulate_batch(&vec![q; n], &vec![0.0; n], &[20.0], n)
            .unwrap();
        for k in 0..=n {
            let exact = 20.0 + b * q * (1.0 - (-lam * k as f64).exp()) / lam;
            assert!((out.probe_c[k] - exact).abs() < 1e-12);
            assert!((out.face_max_c[k] - exact).abs() < 1e-12);
        }
    }

    #[test]
    fn a_constant_drive_per_event_is_the_same_as_a_series() {
        let c = vec![1.0, 0.5, 1.0, 0.2, -0.3, 0.7, 0.1, 0.9, 0.4];
        let s = ModalStepper::new(
            &[0.01, 0.2, 1.5],
            &[1.0, 2.0, 0.5],
            &[0.3, -0.2, 0.1],
            c,
            1,
            1.0,
        )
        .unwrap();
        let n = 30;
        let flux: Vec<f64> = (0..3 * n).map(|k| (k % 7) as f64).collect();
        let drive = [-5.0, 2.0, 0.5];
        let series: Vec<f64> = drive.iter().flat_map(|&d| vec![d; n]).collect();
        let t_ref = [20.0, 30.0, 40.0];
        let a = s.simulate_batch(&flux, &drive, &t_ref, n).unwrap();
        let b = s.simulate_batch(&flux, &series, &t_ref, n).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn a_rotated_propagator_is_its_matrix_exponential() {
        // two modes coupled by a symmetric operator A = Q diag(λ) Qᵀ; exact step for held u:
        // ξ ← Q [e ⊙ Qᵀξ + g ⊙ Qᵀu]; checked against the nominal (unrotated) form in Q's basis
        let (c30, s30) = (3f64.sqrt() / 2.0, 0.5);
        let q = vec![c30, -s30, s30, c30];
        let (lam, dt) = ([0.1, 0.7], 1.0);
        let e: Vec<f64> = lam.iter().map(|l: &f64| (-l * dt).exp()).collect();
        let g: Vec<f64> = lam.iter().map(|l: &f64| -(-l * dt).exp_m1() / l).collect();
        let rotated = Propagators::new(2, e.clone(), g.clone(), q.clone(), vec![true]).unwrap();
        let plain = Propagators::new(2, e, g, vec![0.0; 4], vec![false]).unwrap();
        let to_q = |x: &[f64]| vec![q[0] * x[0] + q[2] * x[1], q[1] * x[0] + q[3] * x[1]];
        let n = 20;
        let u: Vec<f64> = (0..2 * n).map(|k| ((k * 7) % 5) as f64 - 2.0).collect();
        let uq: Vec<f64> = u.chunks(2).flat_map(to_q).collect();
        let xi0 = [1.0, -0.5];
        let c = vec![1.0, 0.0, 0.0, 1.0];
        let (ya, xa) = rotated
            .simulate(&vec![0; n], &vec![1; n], &u, &xi0, &c)
            .unwrap();
        let (_, xb) = plain
            .simulate(&vec![0; n], &vec![1; n], &uq, &to_q(&xi0), &c)
            .unwrap();
        let back = [q[0] * xb[0] + q[1] * xb[1], q[2] * xb[0] + q[3] * xb[1]];
        assert!((xa[0] - back[0]).abs() < 1e-12 && (xa[1] - back[1]).abs() < 1e-12);
        assert_eq!(ya.len(), (n + 1) * 2);
        assert_eq!(&ya[2 * n..], &xa[..]);
        // repeats apply the step again; a bad index is an error, not a panic
        let (_, twice) = plain
            .simulate(&[0], &[2], &uq[..2], &[0.0, 0.0], &c)
            .unwrap();
        let (_, one) = plain
            .simulate(
                &[0, 0],
                &[1, 1],
                &[uq[0], uq[1], uq[0], uq[1]],
                &[0.0, 0.0],
                &c,
            )
            .unwrap();
        assert_eq!(twice, one);
        assert!(plain
            .simulate(&[1], &[1], &uq[..2], &[0.0, 0.0], &c)
            .is_err());
    }

    #[test]
    fn bad_lengths_are_errors() {
        let s = ModalStepper::new(&[1.0], &[1.0], &[1.0], vec![1.0, 1.0, 1.0], 1, 1.0).unwrap();
        assert!(s.simulate_batch(&[1.0; 5], &[0.0; 4], &[0.0], 5).is_err());
        assert!(ModalStepper::new(&[1.0], &[1.0], &[1.0], vec![1.0], 1, 1.0).is_err());
        assert!(ModalStepper::new(&[1.0], &[1.0], &[1.0], vec![1.0; 3], 1, 0.0).is_err());
    }

    #[test]
    fn a_chain_without_readings_is_one_run_and_anchors_to_the_readings_before() {
        // two modes, one face set; outputs: probe, mean, two face nodes
        let (c30, s30) = (3f64.sqrt() / 2.0, 0.5);
        let lam = [0.02, 0.3];
        let (e, g) = exact_propagator(&lam, 1.0);
        let props = Propagators::new(2, e, g, vec![c30, -s30, s30, c30], vec![false]).unwrap();
        let model = ChainModel {
            b_flux: &[1e-3, 2e-3],
            b_faces: &[0.01, -0.02],
            c: &[1.0, 0.5, 0.8, 0.1, 1.0, -0.2, 0.3, 0.9],
            n_probes: 1,
        };
        let n = 40;
        let flux: Vec<f64> = (0..n - 1).map(|k| if k < 10 { 5e3 } else { 0.0 }).collect();
        let ambient = vec![5.0; n - 1];
        let h = vec![10.0; n - 1];
        let prop = vec![0usize; n - 1];
        let steps = ChainSteps {
            flux: &flux,
            ambient: &ambient,
            h: &h,
            prop: &prop,
            piece_a: &[0, 20],
            piece_b: &[20, n - 1],
            piece_dt: &[1.0, 1.0],
            step_off: &[0, 20, n - 1],
            at: &[],
            at_off: &[0, 0, 0],
            seg_cont: &[usize::MAX, usize::MAX],
            seg_window: &[0, 0],
        };
        let rule = AnchorRule {
            anchor_s: 5,
            anchor_min_readings: 3,
            window_s: 10,
            tolerance_k: 1e-3,
            lag_tau_s: None,
        };
        let none = vec![f64::NAN; n];
        let air = vec![7.0; n];
        let out = props
            .simulate_chain(&model, &steps, &none, &air, &rule)
            .unwrap();
        // no readings: uniform at the ambient, never shifted, the same as one run of both
        assert_eq!(out.anchor, vec![ANCHOR_START, ANCHOR_NONE]);
        assert_eq!(out.reference_c, vec![7.0, 7.0]);
        let u: Vec<f64> = (0..n - 1)
            .flat_map(|k| {
                let d = h[k] * (ambient[k] - 7.0);
                [
                    flux[k] * model.b_flux[0] + d * model.b_faces[0],
                    flux[k] * model.b_flux[1] + d * model.b_faces[1],
                ]
            })
            .collect();
        let (y, _) = props
            .simulate(&prop, &vec![1; n - 1], &u, &[0.0, 0.0], model.c)
            .unwrap();
        for k in 0..n {
            assert!((out.sensor_c[k] - (y[4 * k] + 7.0)).abs() < 1e-12);
            assert!((out.contact_mean_c[k] - (y[4 * k + 1] + 7.0)).abs() < 1e-12);
            let top = y[4 * k + 2].max(y[4 * k + 3]) + 7.0;
            assert!((out.contact_max_c[k] - top).abs() < 1e-12);
        }
        // readings 1 K above the prediction before the second segment: shifted by 1 K there
        let mut trusted = vec![f64::NAN; n];
        for (t, p) in trusted.iter_mut().zip(&out.sensor_c).skip(15).take(5) {
            *t = p + 1.0;
        }
        trusted[0] = 7.0;
        let shifted = props
            .simulate_chain(&model, &steps, &trusted, &air, &rule)
            .unwrap();
        assert_eq!(shifted.anchor, vec![ANCHOR_START, ANCHOR_BEFORE]);
        assert!((shifted.shift_k[1] - 1.0).abs() < 1e-12);
        assert!((shifted.sensor_c[20] - out.sensor_c[20] - 1.0).abs() < 1e-12);
        // a piece that does not fit its steps is an error, not a panic
        let bad = ChainSteps {
            step_off: &[0, 19, n - 1],
            ..steps
        };
        assert!(props
            .simulate_chain(&model, &bad, &none, &air, &rule)
            .is_err());
    }
}
