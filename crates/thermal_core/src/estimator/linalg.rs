//! Small dense kernels on row-major matrices: dot products, row sums held in AVX2 registers,
//! blocked products on padded matrices, and the steady tests' element-wise comparison.
//! `FMA`: fused multiply-adds, only where the caller enables the CPU feature (without it
//! `mul_add` is a call into libm). Each vectorised kernel sums in the order of its scalar
//! code, so both give the same bits.

use crate::simd::madd;

/// `Σ a_i b_i` in four partial sums.
#[inline(always)]
pub(super) fn dot<const FMA: bool>(a: &[f64], b: &[f64]) -> f64 {
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
pub(super) fn axpy<const FMA: bool>(alpha: f64, x: &[f64], y: &mut [f64]) {
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi = madd::<FMA>(alpha, *xi, *yi);
    }
}

/// Four dot products of `x` in one pass: `[x·a, x·b, x·c, x·d]`, each summed as `dot` sums
/// it (four lanes, `(l0 + l1) + (l2 + l3)`, then the tail), so equal to four `dot`s to the
/// bit. With FMA: one AVX2 register per product (written out: the compiler's own
/// vectorisation of sixteen scalar accumulators spilled them to the stack).
#[inline(always)]
pub(super) fn dot4<const FMA: bool>(
    x: &[f64],
    a: &[f64],
    b: &[f64],
    c: &[f64],
    d: &[f64],
) -> [f64; 4] {
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
pub(super) fn gemv_rows<const FMA: bool>(
    a: &[f64],
    sign: f64,
    rows: &[f64],
    stride: usize,
    out: &mut [f64],
) {
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
pub(super) unsafe fn gemv_rows_avx2(
    a: &[f64],
    sign: f64,
    rows: &[f64],
    stride: usize,
    out: &mut [f64],
) {
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
pub(super) fn gemv_rows3<const FMA: bool>(
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
pub(super) unsafe fn gemv_rows3_avx2(
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
pub(super) fn transpose(a: &[f64], rows: usize, cols: usize, width: usize) -> Vec<f64> {
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
pub(super) fn padded(n: usize) -> usize {
    n.next_multiple_of(8)
}

/// `dst = src` by chunks of 8 (moved in registers: a call of `memcpy` per short row of the
/// padded matrices costs more than the copy).
#[inline(always)]
pub(super) fn copy_row(dst: &mut [f64], src: &[f64]) {
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
pub(super) fn gemm_padded<const FMA: bool>(
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
pub(super) unsafe fn gemm_padded_avx2(
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
pub(super) unsafe fn block_avx2<const H: usize>(
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
pub(super) fn converged(new: &[f64], old: &[f64], n: usize, tol: f64, d: &mut [f64]) -> bool {
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
pub(super) fn first_change(
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

#[cfg(test)]
// the reference implementations index as the textbook writes them
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use crate::estimator::testing::Rng;
    use crate::simd::has_avx2_fma;

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
}
