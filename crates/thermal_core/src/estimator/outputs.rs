//! What a run returns (`Estimates` per second, `Outputs`) and the kernel's output rows on a
//! state and a covariance: the reported power `P (+ P_b)` and its variance, the largest
//! friction-face node.

use super::basis::Rows;
use super::kernel::Kernel;
use super::linalg::gemv_rows;

/// Per-second estimates of one quantity set (filtered or smoothed).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Estimates {
    pub mean_c: Vec<f64>,
    pub mean_sd_k: Vec<f64>,
    pub max_c: Vec<f64>,
    pub max_sd_k: Vec<f64>,
    pub power_w: Vec<f64>,
    pub power_sd_w: Vec<f64>,
}

impl Estimates {
    pub(super) fn nan(len: usize) -> Self {
        let v = vec![f64::NAN; len];
        Estimates {
            mean_c: v.clone(),
            mean_sd_k: v.clone(),
            max_c: v.clone(),
            max_sd_k: v.clone(),
            power_w: v.clone(),
            power_sd_w: v,
        }
    }
}

/// What a run returns.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Outputs {
    pub filtered: Estimates,
    pub innovation_k: Vec<f64>,
    pub innovation_var_k2: Vec<f64>,
    pub predicted_reading_c: Vec<f64>,
    /// Whether the step into each second used the manoeuvre mode's σ_w (with `switching`;
    /// without, true everywhere).
    pub manoeuvre: Vec<bool>,
    pub manoeuvre_steps: usize,
    pub smoothed: Option<Estimates>,
    pub log_likelihood: f64,
    pub updates: usize,
    pub frozen_steps: usize,
    /// Steps whose covariance was a recorded excursion's (`Memo`), not computed again.
    pub memo_steps: usize,
    pub smoother_frozen_steps: usize,
    pub final_state: Vec<f64>,
    pub final_cov: Vec<f64>,
}

impl Kernel<'_> {
    /// The reported power of a state (or of a covariance's row combination): `P (+ P_b)`.
    #[inline(always)]
    pub(super) fn power_of(&self, x: &[f64]) -> f64 {
        let r = self.d.r;
        if self.d.brake {
            x[r] + x[self.d.n - 1]
        } else {
            x[r]
        }
    }

    /// `Σ e` (e: the reported power's row) into `out`.
    #[inline(always)]
    pub(super) fn sig_power_into(&self, cov: &[f64], out: &mut [f64]) {
        let (r, n) = (self.d.r, self.d.n);
        out.copy_from_slice(&cov[r * n..(r + 1) * n]);
        if self.d.brake {
            for (o, &v) in out.iter_mut().zip(&cov[(n - 1) * n..]) {
                *o += v;
            }
        }
    }

    /// The reported power's variance `eᵀ Σ e`.
    #[inline(always)]
    pub(super) fn power_var_of(&self, cov: &[f64]) -> f64 {
        let (r, n) = (self.d.r, self.d.n);
        if self.d.brake {
            let ib = n - 1;
            cov[r * n + r] + cov[ib * n + ib] + 2.0 * cov[r * n + ib]
        } else {
            cov[r * n + r]
        }
    }

    /// Node values `c_j ξ - s_j·λ` (`minus`: Some((s transposed, n x m, λ))) into `v`, and
    /// the largest with its index.
    #[inline(always)]
    pub(super) fn nodes_max<const FMA: bool>(
        &self,
        rows: &Rows,
        x: &[f64],
        minus: Option<(&[f64], &[f64])>,
        v: &mut [f64],
    ) -> (f64, usize) {
        let (r, m) = (self.d.r, self.m.next_multiple_of(4));
        v.fill(0.0);
        gemv_rows::<FMA>(&x[..r], 1.0, &rows.cn_t, m, &mut v[..m]);
        if let Some((s_t, lam)) = minus {
            gemv_rows::<FMA>(lam, -1.0, s_t, m, &mut v[..m]);
        }
        let mut best = (f64::NEG_INFINITY, 0usize);
        for (j, &vj) in v[..self.m].iter().enumerate() {
            if vj > best.0 {
                best = (vj, j);
            }
        }
        best
    }
}
