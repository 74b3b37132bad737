//! What the vectorised kernels (reduced-model stepping, triangular solves) share: whether the
//! CPU has AVX2 and FMA, and a multiply-add that is fused only where they are enabled.

/// Whether the kernels may take their AVX2 + FMA paths on this CPU.
#[inline]
pub fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `a b + c`, fused when `FMA` (only inside functions compiled with the feature: without it
/// `mul_add` is a call into libm).
#[inline(always)]
pub fn madd<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}
