//! The covariance paths of a step: computed in full, frozen at a steady state of its key
//! (`Steady`), or replayed from a recorded excursion (`Memo`); the steady tests that decide
//! between them, and the filter's checkpoints the smoother resumes from.

use super::basis::Rotation;
use super::kernel::{Kernel, Work};
use super::linalg::{converged, dot, first_change, transpose};

/// Step `t`'s covariance mode: computed in full, or the steady cache `id`.
pub(super) const FULL: u32 = u32::MAX;

/// What the covariance step into a second depends on: the transition, a reading or not, the
/// power's noise mode.
pub(super) type Key = (u32, bool, bool);

/// What stays constant while the filter is steady for one key.
#[derive(Debug, Clone)]
pub(super) struct Steady {
    pub(super) key: Key,
    pub(super) cov: Vec<f64>,
    pub(super) gain: Vec<f64>,
    pub(super) s_var: f64,
    pub(super) mean_var: f64,
    /// Filtered variance of every face node.
    pub(super) node_var: Vec<f64>,
    pub(super) power_var: f64,
    /// `P`'s own variance (the manoeuvre mode's hold test; `power_var` without `P_b`).
    pub(super) hold_var: f64,
    /// `Σ c_mean`, `Σ c_node` (m x n), `Σ e` (the reported power's): the smoother's products
    /// with Σ.
    pub(super) sig_mean: Vec<f64>,
    pub(super) sig_nodes: Vec<f64>,
    /// `sig_nodes` transposed (n x m, m padded to a multiple of 4).
    pub(super) sig_nodes_t: Vec<f64>,
    pub(super) sig_power: Vec<f64>,
}

/// The filter's checkpoint at the start of a smoother block.
#[derive(Debug, Clone)]
pub(super) struct Checkpoint {
    pub(super) x: Vec<f64>,
    /// Empty when the step was steady (the cache has it).
    pub(super) cov: Vec<f64>,
    pub(super) gain: Vec<f64>,
    pub(super) nu: f64,
    pub(super) s_var: f64,
    /// The pass's state at the checkpoint besides these (a second pass resumes from it):
    /// where the filtered covariance is, the steady cache in force, and how many caches and
    /// recorded excursion steps there were.
    pub(super) last: Last,
    pub(super) steady: Option<usize>,
    pub(super) n_caches: usize,
    pub(super) n_nodes: usize,
}

/// One recorded step of an excursion from a steady state: the filtered covariance after a
/// step with `key` from its parent (a steady cache or the node before).
#[derive(Debug, Clone)]
pub(super) struct MemoNode {
    pub(super) cov: Vec<f64>,
    pub(super) gain: Vec<f64>,
    pub(super) s_var: f64,
    pub(super) mean_var: f64,
    pub(super) power_var: f64,
    pub(super) hold_var: f64,
    /// Filtered variance of each face node, NaN until asked for.
    pub(super) node_var: Vec<f64>,
    pub(super) children: Vec<(Key, u32)>,
    /// The steady cache the step entered (its convergence test passed there).
    pub(super) steady: Option<usize>,
}

/// Excursions from steady states, recorded the first time and replayed after: leaving steady
/// cache `c` with the keys `k1, k2, ...` gives the same covariances, gains and steady cache
/// every time (the same operations on the same numbers), so a missing reading in a steady
/// stretch, a switch of convection and back, the first seconds after them, cost the mean's
/// step only the second time. Bounded by `cap` nodes.
pub(super) struct Memo {
    pub(super) roots: Vec<Vec<(Key, u32)>>,
    pub(super) nodes: Vec<MemoNode>,
    pub(super) cap: usize,
}

/// Where the last filtered covariance is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Last {
    /// The forward pass's own buffer (`cov`).
    Buf,
    /// A steady cache (a frozen step).
    Cache(usize),
    /// A recorded excursion's node.
    Node(usize),
}

/// Memory for the recorded excursions of one forward pass.
pub(super) const MEMO_BYTES: usize = 32 << 20;

impl Memo {
    pub(super) fn new(n: usize, replay: bool) -> Self {
        Memo {
            roots: Vec::new(),
            nodes: Vec::new(),
            cap: if replay {
                MEMO_BYTES / (8 * (n * n + 2 * n + 64))
            } else {
                0
            },
        }
    }

    pub(super) fn children(&self, last: Last) -> Option<&Vec<(Key, u32)>> {
        match last {
            Last::Buf => None,
            Last::Cache(c) => self.roots.get(c),
            Last::Node(u) => Some(&self.nodes[u].children),
        }
    }

    pub(super) fn child(&self, last: Last, key: Key) -> Option<usize> {
        self.children(last)?
            .iter()
            .find(|(k, _)| *k == key)
            .map(|&(_, u)| u as usize)
    }

    /// Back to the memo as it was with `n_nodes` nodes and `n_caches` steady caches (nodes and
    /// children are only ever appended).
    pub(super) fn truncate(&mut self, n_nodes: usize, n_caches: usize) {
        self.nodes.truncate(n_nodes);
        self.roots.truncate(n_caches);
        let keep = |list: &mut Vec<(Key, u32)>| list.retain(|&(_, u)| (u as usize) < n_nodes);
        self.roots.iter_mut().for_each(keep);
        self.nodes
            .iter_mut()
            .for_each(|node| keep(&mut node.children));
    }

    /// Whether a child of `last` would be recorded: `last` is recorded and the memory is not
    /// spent.
    pub(super) fn can_record(&self, last: Last) -> bool {
        self.nodes.len() < self.cap && !matches!(last, Last::Buf)
    }

    /// Record `node` as the child of `last` for `key`; None when `last` is not recorded or
    /// the memory is spent.
    pub(super) fn record(&mut self, last: Last, key: Key, node: MemoNode) -> Option<usize> {
        if !self.can_record(last) {
            return None;
        }
        let id = self.nodes.len();
        let list = match last {
            Last::Cache(c) => {
                if self.roots.len() <= c {
                    self.roots.resize(c + 1, Vec::new());
                }
                &mut self.roots[c]
            }
            Last::Node(u) => &mut self.nodes[u].children,
            Last::Buf => unreachable!(),
        };
        list.push((key, id as u32));
        self.nodes.push(node);
        Some(id)
    }
}

impl Kernel<'_> {
    /// `converged(new, old)` for two symmetric matrices in basis `b`, as in the problem's own
    /// basis: the steady tests decide as they would on a transition stepped dense (the
    /// answer does not depend on the basis a step is made in). First the tests that need
    /// no rotation, each a consequence of `converged` there (the entries off the modes are
    /// the same in every basis; the modes' traces, their Frobenius norms and each border
    /// column's norm too) and the element that failed there the last time (three products
    /// with an n x n matrix): where one fails, `converged` there fails; else both matrices
    /// rotated (two blocked products).
    #[inline(always)]
    pub(super) fn converged_own<const FMA: bool>(
        &self,
        b: u32,
        new: &[f64],
        old: &[f64],
        tol: f64,
        w: &mut Work,
    ) -> bool {
        let n = self.d.n;
        match self.rotation(b, 0) {
            None => converged(new, old, n, tol, &mut w.d),
            Some(rot) => self.converged_rotated::<FMA>(rot, new, old, tol, w),
        }
    }

    /// `converged_own` in a basis of a dense transition (out of line).
    #[inline(never)]
    pub(super) fn converged_rotated<const FMA: bool>(
        &self,
        rot: &Rotation,
        new: &[f64],
        old: &[f64],
        tol: f64,
        w: &mut Work,
    ) -> bool {
        let (r, n) = (self.d.r, self.d.n);
        let diag = |i: usize| new[i * n + i].abs();
        // the entries off the modes
        for i in r..n {
            for j in r..n {
                let dij = (new[i * n + j] - old[i * n + j]).abs();
                if dij > tol * diag(i).sqrt() * diag(j).sqrt() {
                    return false;
                }
            }
        }
        // |Δ_ii| <= tol Σ_ii on the modes: |tr Δ| <= tol tr Σ; |Δ_ij| <= tol √(Σ_ii Σ_jj):
        // ‖Δ‖_F <= tol tr Σ on the modes, ‖Δ_mj‖² <= tol² Σ_jj tr Σ for a border column j
        let trace: f64 = (0..r).map(diag).sum();
        let trace_d: f64 = (0..r).map(|i| new[i * n + i] - old[i * n + i]).sum();
        if trace_d.abs() > tol * trace {
            return false;
        }
        // the element that failed last time, alone (three products with n x n), ...
        let (fi, fj) = w.fail;
        let [vi, vj, u, ui] = &mut w.four;
        for (v, i) in [(&mut *vi, fi), (&mut *vj, fj)] {
            v.fill(0.0);
            if i < r {
                v[..r].copy_from_slice(&rot.r[i * r..(i + 1) * r]);
            } else {
                v[i] = 1.0;
            }
        }
        self.times::<FMA>(new, vj, u);
        let (new_ij, d_j) = (dot::<FMA>(vi, u), dot::<FMA>(vj, u));
        self.times::<FMA>(new, vi, ui);
        let d_i = dot::<FMA>(vi, ui);
        self.times::<FMA>(old, vj, u);
        let old_ij = dot::<FMA>(vi, u);
        if (new_ij - old_ij).abs() > tol * d_i.abs().sqrt() * d_j.abs().sqrt() {
            return false;
        }
        // ... the norms, then every element
        let mut frob = 0.0;
        for i in 0..r {
            for j in 0..r {
                let dij = new[i * n + j] - old[i * n + j];
                frob += dij * dij;
            }
        }
        if frob > tol * tol * trace * trace {
            return false;
        }
        for j in r..n {
            let col: f64 = (0..r)
                .map(|i| (new[i * n + j] - old[i * n + j]).powi(2))
                .sum();
            if col > tol * tol * diag(j) * trace {
                return false;
            }
        }
        let [a, c] = &mut w.own;
        rot.forward_cov::<FMA>(&self.d, new, a, &mut w.pad);
        rot.forward_cov::<FMA>(&self.d, old, c, &mut w.pad);
        match first_change(a, c, n, tol, &mut w.d) {
            Some(ij) => {
                w.fail = ij;
                false
            }
            None => true,
        }
    }

    #[inline(always)]
    pub(super) fn key(&self, t: usize, manoeuvre: bool) -> Option<Key> {
        // a step whose power noise follows the declared power is never steady
        (t > 0 && self.power_noise(t) == 0.0).then(|| {
            (
                self.p.index[t - 1],
                self.p.reading_c[t].is_finite(),
                manoeuvre,
            )
        })
    }

    /// The steady tests' tolerances (the filter's, the smoother's inside the filter's steady
    /// state) for a step with `key`.
    #[inline(always)]
    pub(super) fn tols_of(&self, key: Key) -> (f64, f64) {
        self.tols[usize::from(key.2)]
    }

    #[inline(always)]
    pub(super) fn make_steady<const FMA: bool>(
        &self,
        key: Key,
        cov: &[f64],
        gain: &[f64],
        s_var: f64,
        smooth: bool,
    ) -> Steady {
        let (r, n) = (self.d.r, self.d.n);
        // the key's transition's basis
        let rows = &self.rows[self.basis[key.0 as usize] as usize];
        let mut sig_mean = vec![0.0; n];
        self.times::<FMA>(cov, &rows.cm, &mut sig_mean);
        let mut sig_nodes = vec![0.0; self.m * n];
        let mut node_var = Vec::with_capacity(self.m);
        for (j, out) in sig_nodes.chunks_exact_mut(n).enumerate() {
            self.times::<FMA>(cov, rows.node_row(j), out);
            node_var.push(dot::<FMA>(rows.node_row(j), &out[..r]));
        }
        let mean_var = dot::<FMA>(&rows.cm, &sig_mean[..r]);
        let mut sig_power = vec![0.0; n];
        self.sig_power_into(cov, &mut sig_power);
        if !smooth {
            sig_nodes.clear();
        }
        let sig_nodes_t = if smooth {
            transpose(&sig_nodes, self.m, n, self.m.next_multiple_of(4))
        } else {
            Vec::new()
        };
        Steady {
            key,
            cov: cov.to_vec(),
            gain: gain.to_vec(),
            s_var,
            mean_var,
            node_var,
            power_var: self.power_var_of(cov),
            hold_var: cov[r * n + r],
            sig_mean,
            sig_nodes,
            sig_nodes_t,
            sig_power,
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::estimator::run;
    use crate::estimator::testing::*;
    use crate::estimator::Outputs;

    #[test]
    fn the_braking_power_state_keeps_the_fast_paths_exact() {
        for lag in [false, true] {
            let mut p = brake_problem(lag, 6000, 11);
            // forgotten at the release (τ_b = 0): its variance exactly 0 there, so the
            // released stretches settle (a geometric decay never passes the relative test)
            for t in &mut p.transitions {
                if t.brake_q == 0.0 {
                    t.brake_phi = 0.0;
                }
            }
            // a reading missing every 400 s: excursions from the steady states, replayed
            for t in (200..6000).step_by(400) {
                p.reading_c.to_mut()[t] = f64::NAN;
            }
            let exact = run(&p, SWITCHING, &settings(0.0, 256)).unwrap();
            let fast = run(&p, SWITCHING, &settings(1e-7, 256)).unwrap();
            assert!(
                fast.frozen_steps > 0 && fast.memo_steps > 0,
                "{} {}",
                fast.frozen_steps,
                fast.memo_steps
            );
            assert_estimates("filtered", &fast.filtered, &exact.filtered, 1e-4);
            let mut no_replay = settings(1e-7, 256);
            no_replay.replay = false;
            let computed = run(&p, SWITCHING, &no_replay).unwrap();
            assert_estimates(
                "filtered, replayed",
                &fast.filtered,
                &computed.filtered,
                0.0,
            );
            assert_estimates(
                "smoothed, replayed",
                fast.smoothed.as_ref().unwrap(),
                computed.smoothed.as_ref().unwrap(),
                0.0,
            );
        }
    }

    #[test]
    fn steady_stretches_change_nothing_but_the_cost() {
        for lag in [false, true] {
            let p = problem(lag, 3000, 11);
            let exact = run(&p, NOISE, &settings(0.0, 128)).unwrap();
            let fast = run(&p, NOISE, &settings(1e-12, 128)).unwrap();
            assert!(fast.frozen_steps > 1000, "{} frozen", fast.frozen_steps);
            assert_estimates("filtered", &fast.filtered, &exact.filtered, 1e-9);
            assert_estimates(
                "smoothed",
                fast.smoothed.as_ref().unwrap(),
                exact.smoothed.as_ref().unwrap(),
                1e-9,
            );
        }
    }

    #[test]
    fn replayed_excursions_are_the_computed_ones() {
        // the problem repeats every 1,500 steps (missing readings, a dense stretch, a gap):
        // the same excursions from the same steady states, recorded once, replayed after
        for (lag, noise) in [(false, NOISE), (true, NOISE), (false, SWITCHING)] {
            let p = problem(lag, 9000, 13);
            for tol in [1e-12, 1e-7] {
                let replayed = run(&p, noise, &settings(tol, 128)).unwrap();
                let mut s = settings(tol, 128);
                s.replay = false;
                let computed = run(&p, noise, &s).unwrap();
                assert_eq!(computed.memo_steps, 0);
                assert!(
                    replayed.memo_steps > 100,
                    "{} replayed at {tol}",
                    replayed.memo_steps
                );
                assert_eq!(replayed.frozen_steps, computed.frozen_steps);
                assert_eq!(replayed.manoeuvre, computed.manoeuvre);
                // the same operations on the same numbers, but the face node's variance (a
                // different order of summation where the replay asks for another node)
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&replayed.innovation_k), bits(&computed.innovation_k));
                assert_eq!(replayed.filtered.mean_c, computed.filtered.mean_c);
                assert_eq!(replayed.final_cov, computed.final_cov);
                assert_estimates("filtered", &replayed.filtered, &computed.filtered, 1e-13);
                assert_estimates(
                    "smoothed",
                    replayed.smoothed.as_ref().unwrap(),
                    computed.smoothed.as_ref().unwrap(),
                    1e-13,
                );
            }
        }
    }

    #[test]
    fn the_default_tolerances_move_estimates_by_nothing_that_matters() {
        let p = problem(false, 3000, 5);
        let exact = run(&p, NOISE, &settings(0.0, 128)).unwrap();
        let mut s = settings(1e-8, 128);
        s.smoother_tolerance = 1e-6;
        let fast = run(&p, NOISE, &s).unwrap();
        assert!(fast.frozen_steps > 1500 && fast.smoother_frozen_steps > 1000);
        let (a, b) = (&fast.filtered, &exact.filtered);
        assert_close("mean", &a.mean_c, &b.mean_c, 1e-7);
        assert_close("power", &a.power_w, &b.power_w, 1e-6);
        assert_close("mean sd", &a.mean_sd_k, &b.mean_sd_k, 1e-6);
        let (a, b) = (fast.smoothed.unwrap(), exact.smoothed.unwrap());
        assert_close("smoothed mean", &a.mean_c, &b.mean_c, 1e-7);
        assert_close("smoothed mean sd", &a.mean_sd_k, &b.mean_sd_k, 1e-4);
        assert_close("smoothed power sd", &a.power_sd_w, &b.power_sd_w, 1e-4);
    }

    #[test]
    fn the_manoeuvre_modes_own_tolerances_apply_to_its_steps_only() {
        let p = problem(false, 3000, 5);
        let with = |tol: f64, manoeuvre: Option<(f64, f64)>| {
            let mut s = settings(tol, 128);
            s.manoeuvre_tolerances = manoeuvre;
            run(&p, SWITCHING, &s).unwrap()
        };
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let frozen = |o: &Outputs| (o.frozen_steps, o.smoother_frozen_steps);
        let loose = with(1e-3, None);
        assert!(loose.manoeuvre_steps > 100, "{}", loose.manoeuvre_steps);
        // the quiet mode's tolerances given again for the manoeuvre mode: the same run
        let again = with(1e-3, Some((1e-3, 1e-3)));
        assert_eq!(frozen(&again), frozen(&loose));
        assert_eq!(again.manoeuvre, loose.manoeuvre);
        assert_eq!(bits(&again.filtered.mean_c), bits(&loose.filtered.mean_c));
        assert_eq!(
            bits(&again.smoothed.as_ref().unwrap().power_sd_w),
            bits(&loose.smoothed.as_ref().unwrap().power_sd_w)
        );
        // the manoeuvre mode held to 0: fewer steady steps, filter and smoother (1,769 and
        // 1,094 against 1,882 and 1,262 on this problem)
        let held = with(1e-3, Some((0.0, 0.0)));
        assert!(
            held.frozen_steps < loose.frozen_steps,
            "{:?}",
            frozen(&held)
        );
        assert!(held.smoother_frozen_steps < loose.smoother_frozen_steps);
        // the quiet mode exact and the manoeuvre mode loose: more (240 and 187 against 127
        // and 3)
        let exact = with(0.0, None);
        let mixed = with(0.0, Some((1e-3, 1e-3)));
        assert!(
            mixed.frozen_steps > exact.frozen_steps,
            "{:?}",
            frozen(&mixed)
        );
        assert!(mixed.smoother_frozen_steps > exact.smoother_frozen_steps);
        // the settings are checked
        let mut s = settings(1e-7, 128);
        s.manoeuvre_tolerances = Some((1e-7, -1.0));
        assert!(run(&p, SWITCHING, &s).is_err());
    }
}
