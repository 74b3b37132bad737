//! A chain's step systems (the distinct convection changes and time steps its propagators
//! are keyed by) and its convection per step, as numpy forms them, bit for bit.

use crate::error::{Result, ThermalError};

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
pub(super) fn rint(x: f64) -> f64 {
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
pub(super) fn round_12(x: f64) -> f64 {
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
pub(super) fn systems_with(
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
}
