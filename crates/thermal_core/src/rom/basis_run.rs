//! A run of propagators kept in the basis of the propagator that stepped it last: O(r) a
//! step, as a nominal step, instead of three r x r products a step for a rotated one.

use super::propagators::Propagators;

/// Where a run's state is kept when no rotated propagator holds it: the modal coordinates,
/// the basis of every nominal propagator.
pub(super) const MODAL: usize = usize::MAX;

/// A propagator's basis as a run steps in it: the input vectors `Qᵀ b` (m, r) row-major,
/// the output rows `C Q` in blocks ([`out_blocks`]), and `Qᵀ` (r, r) row-major, with which
/// the state leaves the basis. The modal basis: the vectors `b` and `C` themselves, no `Qᵀ`.
#[derive(Debug, Clone, Default)]
pub(super) struct Basis {
    pub(super) b: Vec<f64>,
    pub(super) ct: Vec<f64>,
    pub(super) qt: Vec<f64>,
}

/// `out = Mᵀ x`, `M` row-major (len(x), len(out)), its rows accumulated in order.
#[inline(always)]
pub(super) fn transpose_times(m: &[f64], x: &[f64], out: &mut [f64]) {
    out.fill(0.0);
    for (row, &xi) in m.chunks_exact(out.len()).zip(x) {
        for (o, &a) in out.iter_mut().zip(row) {
            *o += a * xi;
        }
    }
}

/// Output rows summed together, mode by mode, in registers (four AVX2 vectors): each
/// output's sum runs over the modes in order, as a row-by-row product would.
pub(super) const OUT_BLOCK: usize = 16;

/// The block of a run with at most this many output rows (the close loop's fits read the
/// sensor and the face mean only): one AVX2 vector instead of four, the same sums.
pub(super) const SMALL_OUT_BLOCK: usize = 4;

/// The output block of `n_out` rows: [`SMALL_OUT_BLOCK`] for a few, else [`OUT_BLOCK`].
pub(super) fn out_block(n_out: usize) -> usize {
    if n_out <= SMALL_OUT_BLOCK {
        SMALL_OUT_BLOCK
    } else {
        OUT_BLOCK
    }
}

/// Output rows `c` (n_out, r) row-major in blocks of `block` rows, each block stored mode by
/// mode (`[(b r + i) block + j] = c[b block + j, i]`), the rows padded with zeros to a whole
/// number of blocks.
pub(super) fn out_blocks(c: &[f64], r: usize, block: usize) -> Vec<f64> {
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
pub(super) fn blocks_times<const B: usize>(blocks: &[f64], w: &[f64], y: &mut [f64]) {
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
pub(super) fn largest(y: &[f64]) -> f64 {
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
/// comes (once per run, not per step). Nominal steps are the formula's `ξ ← e ⊙ ξ + g ⊙ u`
/// operation for operation (bit for bit); rotated ones equal the formula to rounding.
pub(super) struct BasisRun<'a> {
    pub(super) props: &'a Propagators,
    /// The input vectors (m, r) and output rows (n_out, r) in modal coordinates.
    pub(super) inputs: Vec<f64>,
    pub(super) c: &'a [f64],
    pub(super) modal: Basis,
    /// Per propagator: its basis once built (rotated ones only).
    pub(super) rotated: Vec<Option<Basis>>,
    /// The state, in the basis `at` (a propagator's index, or `MODAL`).
    pub(super) w: Vec<f64>,
    pub(super) at: usize,
    /// Scratch: the state in modal coordinates (r), the step's input (r), the outputs.
    pub(super) x: Vec<f64>,
    pub(super) u: Vec<f64>,
    /// The outputs, padded to whole blocks of `block` rows; `n_out` of them are the model's.
    pub(super) y: Vec<f64>,
    pub(super) n_out: usize,
    pub(super) block: usize,
}

/// The basis `at` of a run (a free function: the caller borrows the run's other fields).
#[inline(always)]
pub(super) fn basis_at<'b>(modal: &'b Basis, rotated: &'b [Option<Basis>], at: usize) -> &'b Basis {
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
    pub(super) fn new(props: &'a Propagators, inputs: Vec<f64>, c: &'a [f64]) -> Self {
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
    pub(super) fn start(&mut self, xi: &[f64]) {
        self.w.copy_from_slice(xi);
        self.at = MODAL;
    }

    /// The state in modal coordinates, `ξ = Q w`.
    #[inline(always)]
    pub(super) fn state(&self, xi: &mut [f64]) {
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
    pub(super) fn enter(&mut self, k: usize) {
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
    pub(super) fn build(&self, k: usize) -> Basis {
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
    pub(super) fn outputs(&mut self) {
        let ct = &basis_at(&self.modal, &self.rotated, self.at).ct;
        if self.block == SMALL_OUT_BLOCK {
            blocks_times::<SMALL_OUT_BLOCK>(ct, &self.w, &mut self.y);
        } else {
            blocks_times::<OUT_BLOCK>(ct, &self.w, &mut self.y);
        }
    }
}
