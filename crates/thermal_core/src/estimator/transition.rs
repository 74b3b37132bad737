//! One transition's structured products: `F x`, `Fᵀ x`, and the covariance steps `F X Fᵀ`
//! and `Fᵀ L̃ F` of a diagonal transition as "diagonal plus a border" (O(n²)), or of a dense
//! one as two blocked products on padded matrices (`DenseF`).

use super::linalg::{axpy, copy_row, dot, gemm_padded, padded};
use super::problem::Transition;
use crate::simd::madd;

pub(super) struct Dims {
    pub(super) r: usize,
    pub(super) n: usize,
    pub(super) lag: bool,
    /// The braking's power `P_b` at index n - 1.
    pub(super) brake: bool,
}

impl Transition {
    /// `out = F x`.
    #[inline(always)]
    pub(super) fn apply<const FMA: bool>(&self, d: &Dims, x: &[f64], out: &mut [f64]) {
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
    pub(super) fn apply_t<const FMA: bool>(&self, d: &Dims, x: &[f64], out: &mut [f64]) {
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
    pub(super) fn predict_cov<const FMA: bool>(
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
            let (t, eg) = (&*t, (ei, gi));
            match (ph.as_mut(), gap) {
                (Some((h, acc)), Some((c, u))) => {
                    mode_row::<FMA, true, true>(o, t, tpow, eg, acc, h[i], c, u)
                }
                (Some((h, acc)), None) => {
                    mode_row::<FMA, true, false>(o, t, tpow, eg, acc, h[i], 0.0, tpow)
                }
                (None, Some((c, u))) => mode_row::<FMA, false, true>(o, t, tpow, eg, z, 0.0, c, u),
                (None, None) => mode_row::<FMA, false, false>(o, t, tpow, eg, z, 0.0, 0.0, tpow),
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
    pub(super) fn back_row<const FMA: bool>(
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
    pub(super) fn back_cov<const FMA: bool>(
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

/// Row i of `F T` for a diagonal transition from a whole row `t` of `T = X Fᵀ`: each entry
/// `v = e_i T_ij + γ_i T_Pj` (`eg` = (e_i, γ_i); `tpow`: `T_P (+ T_Pb)`); `ACC`: `h_i v` added
/// into `acc` (Σh); `GAP`: the entry is `v + c u_j` (the mode row's share of `q_gap u uᵀ`).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn mode_row<const FMA: bool, const ACC: bool, const GAP: bool>(
    o: &mut [f64],
    t: &[f64],
    tpow: &[f64],
    (ei, gi): (f64, f64),
    acc: &mut [f64],
    hi: f64,
    c: f64,
    u: &[f64],
) {
    let n = o.len();
    let (t, tpow, acc, u) = (&t[..n], &tpow[..n], &mut acc[..n], &u[..n]);
    for j in 0..n {
        let v = madd::<FMA>(ei, t[j], gi * tpow[j]);
        if ACC {
            acc[j] = madd::<FMA>(hi, v, acc[j]);
        }
        o[j] = if GAP { madd::<FMA>(c, u[j], v) } else { v };
    }
}

/// Row i of `F X Fᵀ` for a diagonal transition without a lag, in one pass: the mode entries
/// of `T = X Fᵀ` made where they are used, `t` holding its other entries (`P`, `P_b`).
pub(super) struct PredictRow<'a> {
    pub(super) o: &'a mut [f64],
    pub(super) t: &'a [f64],
    pub(super) xi: &'a [f64],
    pub(super) e: &'a [f64],
    pub(super) gamma: &'a [f64],
    pub(super) tpow: &'a [f64],
    pub(super) xp: f64,
    pub(super) ei: f64,
    pub(super) gi: f64,
    pub(super) r: usize,
}

impl PredictRow<'_> {
    /// `ACC`: adds `h_i` times the row into `acc` (Σh); `GAP`: adds `c u` (the mode row's
    /// share of `q_gap u uᵀ`). Each entry: `v = e_i T_ij + γ_i T_Pj`, then those, in the
    /// order of `Transition::predict_cov`'s passes.
    #[inline(always)]
    pub(super) fn run<const FMA: bool, const ACC: bool, const GAP: bool>(
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
pub(super) struct DenseF {
    pub(super) f: Vec<f64>,
    pub(super) ft: Vec<f64>,
}

impl DenseF {
    /// F from `Transition::apply` on the unit vectors (its columns, exactly).
    pub(super) fn new(tr: &Transition, d: &Dims) -> Self {
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
    pub(super) fn unpad_symmetric<const FMA: bool>(
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
    pub(super) fn predict_cov<const FMA: bool>(
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
    pub(super) fn back_cov<const FMA: bool>(
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

#[cfg(test)]
// the reference implementations index as the textbook writes them
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use crate::estimator::kernel::Work;
    use crate::estimator::testing::*;

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
