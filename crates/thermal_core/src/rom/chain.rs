//! A span's chain: every segment run from the state the one before left, re-anchored to the
//! readings, and the event windows continued past their braking segments.

use super::basis_run::BasisRun;
use super::piece::{piece_need, Piece, PieceStepper};
use super::propagators::Propagators;
use crate::error::{Result, ThermalError};

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

/// Mean of `trusted - predicted` over `lo .. hi` where both are finite, if at least
/// `min_count` are.
pub(super) fn mean_difference(trusted: &[f64], predicted: &[f64], min_count: usize) -> Option<f64> {
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
    pub(super) fn chain<S: PieceStepper>(
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
        let anchored = windows.map(|_| anchored_samples(steps, rule, n));
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
                    let v = start_reference(trusted, ambient, a, rule.window_s);
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
                out.extend_windows(&piece, 0..own);
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
                    out.extend_windows(&more, 1..rest + 1);
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

/// The samples of a chain's timeline its anchoring reads: the `anchor_s` before each segment
/// and its first `anchor_s` (n samples).
fn anchored_samples(steps: &ChainSteps, rule: &AnchorRule, n: usize) -> Vec<bool> {
    let mut read = vec![false; n];
    for j in 0..steps.seg_cont.len() {
        let (a, b) = (steps.piece_a[j], steps.piece_b[j]);
        read[a.saturating_sub(rule.anchor_s)..(a + rule.anchor_s).min(b + 1)].fill(true);
    }
    read
}

/// The reference temperature of a chain's start at sample `a`: the first reading within
/// `window_s` samples, else the air temperature there.
fn start_reference(trusted: &[f64], ambient: &[f64], a: usize, window_s: usize) -> f64 {
    let ahead = &trusted[a..(a + window_s).min(trusted.len())];
    let first = ahead.iter().copied().find(|v| v.is_finite());
    first.unwrap_or(ambient[a])
}

impl ChainOutputs {
    /// The rows `rows` of a piece onto the event windows.
    fn extend_windows(&mut self, piece: &Piece, rows: std::ops::Range<usize>) {
        self.window_sensor_c
            .extend_from_slice(&piece.sensor[rows.clone()]);
        self.window_mean_c
            .extend_from_slice(&piece.mean[rows.clone()]);
        self.window_max_c.extend_from_slice(&piece.max[rows]);
    }
}

#[cfg(test)]
// the reference implementations index as the textbook writes them
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;
    use crate::rom::exact_propagator;
    use crate::rom::piece::{PieceRows, StepsJob};
    use crate::rom::testing::*;

    /// The chain's pieces stepped in modal coordinates, step by step by the formula: the
    /// reference.
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

    /// The chain read at the `wanted` window seconds only (`simulate_chain_reading`) against
    /// the whole chain, without and with the sensor's lag: the wanted seconds and those the
    /// anchoring reads bit for bit, the others NaN; the timeline the sensor's only.
    fn check_reading_only(
        props: &Propagators,
        two: &ChainModel,
        steps: &ChainSteps,
        trusted: &[f64],
        air: &[f64],
        rule: &AnchorRule,
        wanted: &[bool],
    ) {
        let n = trusted.len();
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for lag in [None, Some(20.0)] {
            let rule = AnchorRule {
                lag_tau_s: lag,
                ..*rule
            };
            let full = props
                .simulate_chain(two, steps, trusted, air, &rule)
                .unwrap();
            let read = props
                .simulate_chain_reading(two, steps, trusted, air, &rule, Some(wanted))
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
        check_reading_only(&props, &two, &steps, &trusted, &air, &rule, &wanted);
        assert!(props
            .simulate_chain_reading(&two, &steps, &trusted, &air, &rule, Some(&wanted[1..]))
            .is_err());
        // nominal steps are the formula's operation for operation: bit for bit
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
