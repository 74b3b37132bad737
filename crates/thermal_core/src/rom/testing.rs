//! What the reduced model's tests share: the step-by-step formula the kernels must equal, and
//! propagators that switch among rotated bases.

use super::exact_propagator;
use super::propagators::Propagators;

/// A step of propagator `k` by the formula (the tests' reference): a rotated one
/// rotates in and out every step, `ξ ← Q [e ⊙ (Qᵀ ξ) + g ⊙ (Qᵀ u)]`.
pub(super) fn apply_step_by_step(
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

/// An orthogonal 4 x 4 basis (row-major): plane rotations by `angles` in (0,1), (1,2),
/// (2,3), (0,3).
pub(super) fn basis4(angles: [f64; 4]) -> Vec<f64> {
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
pub(super) fn switching_propagators() -> Propagators {
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

pub(super) fn max_difference(a: &[f64], b: &[f64]) -> f64 {
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
