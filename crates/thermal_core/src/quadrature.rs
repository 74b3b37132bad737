//! Gauss–Legendre rules on [-1, 1] and their tensor products on the reference square and cube.

/// A 1D Gauss–Legendre rule with `n` points (1 to 5), exact for polynomials of degree 2n − 1.
pub fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    match n {
        1 => (vec![0.0], vec![2.0]),
        2 => {
            let a = 1.0 / 3f64.sqrt();
            (vec![-a, a], vec![1.0, 1.0])
        }
        3 => {
            let a = (3.0f64 / 5.0).sqrt();
            (vec![-a, 0.0, a], vec![5.0 / 9.0, 8.0 / 9.0, 5.0 / 9.0])
        }
        4 => {
            let s = (6.0f64 / 5.0).sqrt();
            let a = ((3.0 - 2.0 * s) / 7.0).sqrt();
            let b = ((3.0 + 2.0 * s) / 7.0).sqrt();
            let wa = (18.0 + 30f64.sqrt()) / 36.0;
            let wb = (18.0 - 30f64.sqrt()) / 36.0;
            (vec![-b, -a, a, b], vec![wb, wa, wa, wb])
        }
        _ => {
            let s = 2.0 * (10.0f64 / 7.0).sqrt();
            let a = (5.0 - s).sqrt() / 3.0;
            let b = (5.0 + s).sqrt() / 3.0;
            let w0 = 128.0 / 225.0;
            let wa = (322.0 + 13.0 * 70f64.sqrt()) / 900.0;
            let wb = (322.0 - 13.0 * 70f64.sqrt()) / 900.0;
            (vec![-b, -a, 0.0, a, b], vec![wb, wa, w0, wa, wb])
        }
    }
}

/// Tensor-product rule on the cube [-1, 1]^3: points and weights.
pub fn cube_rule(n: usize) -> Vec<([f64; 3], f64)> {
    let (x, w) = gauss_legendre(n);
    let mut out = Vec::with_capacity(n * n * n);
    for (i, xi) in x.iter().enumerate() {
        for (j, xj) in x.iter().enumerate() {
            for (k, xk) in x.iter().enumerate() {
                out.push(([*xi, *xj, *xk], w[i] * w[j] * w[k]));
            }
        }
    }
    out
}

/// Tensor-product rule on the square [-1, 1]^2: points and weights.
pub fn square_rule(n: usize) -> Vec<([f64; 2], f64)> {
    let (x, w) = gauss_legendre(n);
    let mut out = Vec::with_capacity(n * n);
    for (i, xi) in x.iter().enumerate() {
        for (j, xj) in x.iter().enumerate() {
            out.push(([*xi, *xj], w[i] * w[j]));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rules_integrate_their_degree_exactly() {
        for n in 1..=5 {
            let (x, w) = gauss_legendre(n);
            for degree in 0..(2 * n) {
                let approx: f64 = x
                    .iter()
                    .zip(&w)
                    .map(|(x, w)| w * x.powi(degree as i32))
                    .sum();
                let exact = if degree % 2 == 1 {
                    0.0
                } else {
                    2.0 / (degree as f64 + 1.0)
                };
                assert!((approx - exact).abs() < 1e-14, "n={n} degree={degree}");
            }
            // and not one degree more (even degrees only are non-trivial)
            let degree = 2 * n;
            let approx: f64 = x
                .iter()
                .zip(&w)
                .map(|(x, w)| w * x.powi(degree as i32))
                .sum();
            assert!(
                (approx - 2.0 / (degree as f64 + 1.0)).abs() > 1e-6,
                "n={n} too exact"
            );
        }
    }

    #[test]
    fn cube_rule_weights_sum_to_volume() {
        let s: f64 = cube_rule(4).iter().map(|(_, w)| w).sum();
        assert!((s - 8.0).abs() < 1e-13);
        let s: f64 = square_rule(3).iter().map(|(_, w)| w).sum();
        assert!((s - 4.0).abs() < 1e-13);
    }
}
