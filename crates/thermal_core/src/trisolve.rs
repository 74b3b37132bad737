//! The two triangular solves `L y = b`, `Lᵀ x = y` with a supernodal Cholesky factor, for one
//! right-hand side: the time stepper's inner loop.
//!
//! A supernode is a dense column-major block: its `size` diagonal rows (lower triangle used),
//! then the rows of its pattern (ancestors). Each solve reads every value of the factor once,
//! so a step is bound by memory traffic; the kernels below stream each column block once,
//! four columns at a time (one pass over the rows below the block instead of four), with
//! fused multiply-adds where the CPU has them. The permutation is applied around them as
//! faer does (`x[i] = b[fwd[i]]`, result `b[i] = x[inv[i]]`).

use std::ops::Range;

use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;

use crate::simd::{has_avx2_fma, madd};

/// Where each supernode lives in the factor's arrays.
#[derive(Debug, Clone)]
pub struct SupernodePlan {
    /// Per supernode: first column, number of columns, offset of its values, and the range
    /// of its pattern in `pattern`.
    nodes: Vec<Node>,
    pattern: Vec<usize>,
    max_rows: usize,
    /// Two independent groups of subtrees of the elimination tree, solved on two threads,
    /// and the supernodes above them (from `top`), solved after (forward) or before
    /// (backward) them; None when the tree has no such split.
    split: Option<Split>,
}

#[derive(Debug, Clone)]
struct Split {
    groups: [Vec<Range<usize>>; 2],
    /// First supernode above the groups: every pattern row of the groups at or past its
    /// first column is shared.
    top: usize,
}

#[derive(Debug, Clone, Copy)]
struct Node {
    start: usize,
    size: usize,
    val: usize,
    pat: usize,
    pat_len: usize,
}

impl SupernodePlan {
    pub fn new(symbolic: &SymbolicSupernodalCholesky<usize>) -> Self {
        let begin = symbolic.supernode_begin();
        let end = symbolic.supernode_end();
        let val_ptr = symbolic.col_ptr_for_val();
        let row_ptr = symbolic.col_ptr_for_row_idx();
        let rows = symbolic.row_idx();
        let mut nodes = Vec::with_capacity(symbolic.n_supernodes());
        let mut pattern = Vec::new();
        let mut max_rows = 0;
        for s in 0..symbolic.n_supernodes() {
            let size = end[s] - begin[s];
            let val_len = val_ptr[s + 1] - val_ptr[s];
            // values are (size + pattern) x size, column-major
            let pat_len = val_len / size - size;
            let own = &rows[row_ptr[s]..row_ptr[s] + pat_len];
            nodes.push(Node {
                start: begin[s],
                size,
                val: val_ptr[s],
                pat: pattern.len(),
                pat_len,
            });
            pattern.extend_from_slice(own);
            max_rows = max_rows.max(size + pat_len);
        }
        let split = find_split(&nodes, &pattern);
        SupernodePlan {
            nodes,
            pattern,
            max_rows,
            split,
        }
    }

    /// Whether the solves run on two threads (two independent halves of the tree).
    pub fn is_split(&self) -> bool {
        self.split.is_some()
    }

    /// (supernodes, mean columns per supernode, stored pattern rows): how much index
    /// traffic a solve has on top of the values.
    pub fn stats(&self) -> (usize, f64, usize) {
        let n = self.nodes.len();
        let cols: usize = self.nodes.iter().map(|s| s.size).sum();
        (n, cols as f64 / n.max(1) as f64, self.pattern.len())
    }

    /// Solve `L Lᵀ x = b` in the factor's own (permuted) numbering, in place; on two
    /// threads (rayon) where the tree splits and `parallel` is set.
    pub fn solve_permuted(&self, values: &[f64], x: &mut [f64], parallel: bool) {
        match (&self.split, parallel) {
            (Some(split), true) => self.solve_split(split, values, x),
            _ => {
                let mut work = vec![0.0; self.max_rows];
                let all = 0..self.nodes.len();
                self.sweep(Sweep::Forward, values, x, &mut work, all.clone());
                self.sweep(Sweep::Backward, values, x, &mut work, all);
            }
        }
    }

    fn solve_split(&self, split: &Split, values: &[f64], x: &mut [f64]) {
        let top_col = self.nodes[split.top].start;
        // forward: each group on its own copy of x (its columns are its own; the rows at
        // and past top_col gather both groups' updates), then the top
        let (a, b) = rayon::join(
            || self.sweep_copy(Sweep::Forward, values, &split.groups[0], x),
            || self.sweep_copy(Sweep::Forward, values, &split.groups[1], x),
        );
        self.copy_groups(split, [&a, &b], x);
        for ((xi, ai), bi) in x[top_col..]
            .iter_mut()
            .zip(&a[top_col..])
            .zip(&b[top_col..])
        {
            *xi = *ai + *bi - *xi;
        }
        let mut work = vec![0.0; self.max_rows];
        let top = split.top..self.nodes.len();
        self.sweep(Sweep::Forward, values, x, &mut work, top.clone());
        // backward: the top, then the groups (each reads the top rows, writes its own)
        self.sweep(Sweep::Backward, values, x, &mut work, top);
        let (a, b) = rayon::join(
            || self.sweep_copy(Sweep::Backward, values, &split.groups[0], x),
            || self.sweep_copy(Sweep::Backward, values, &split.groups[1], x),
        );
        self.copy_groups(split, [&a, &b], x);
    }

    /// One group's sweep on a copy of `x` (its ranges in order forward, in reverse
    /// backward); returns the copy.
    fn sweep_copy(
        &self,
        dir: Sweep,
        values: &[f64],
        group: &[Range<usize>],
        x: &[f64],
    ) -> Vec<f64> {
        let mut local = x.to_vec();
        let mut work = vec![0.0; self.max_rows];
        let mut sweep = |range: &Range<usize>| {
            self.sweep(dir, values, &mut local, &mut work, range.clone());
        };
        match dir {
            Sweep::Forward => group.iter().for_each(&mut sweep),
            Sweep::Backward => group.iter().rev().for_each(&mut sweep),
        }
        local
    }

    /// Copy each group's own columns from its thread's copy of the solution.
    fn copy_groups(&self, split: &Split, locals: [&[f64]; 2], x: &mut [f64]) {
        for (local, group) in locals.into_iter().zip(&split.groups) {
            for range in group {
                let c0 = self.nodes[range.start].start;
                let last = self.nodes[range.end - 1];
                let c1 = last.start + last.size;
                x[c0..c1].copy_from_slice(&local[c0..c1]);
            }
        }
    }

    fn sweep(
        &self,
        dir: Sweep,
        values: &[f64],
        x: &mut [f64],
        work: &mut [f64],
        range: Range<usize>,
    ) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            // SAFETY: the CPU has the features the function is compiled for.
            unsafe { self.sweep_avx2(dir, values, x, work, range) };
            return;
        }
        self.sweep_generic::<false>(dir, values, x, work, range);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn sweep_avx2(
        &self,
        dir: Sweep,
        values: &[f64],
        x: &mut [f64],
        work: &mut [f64],
        range: Range<usize>,
    ) {
        self.sweep_generic::<true>(dir, values, x, work, range);
    }

    /// The forward solve over the supernodes of `range` in order, or the backward solve
    /// over them in reverse.
    #[inline(always)]
    fn sweep_generic<const FMA: bool>(
        &self,
        dir: Sweep,
        values: &[f64],
        x: &mut [f64],
        work: &mut [f64],
        range: Range<usize>,
    ) {
        // plain loops, no closure: a closure is a function of its own, compiled without the
        // caller's target features (and `mul_add` there would call libm)
        let nodes = &self.nodes[range];
        match dir {
            Sweep::Forward => {
                for node in nodes {
                    let (l, pattern, w) = self.parts(node, values, work);
                    let own = node.start..node.start + node.size;
                    w[..node.size].copy_from_slice(&x[own.clone()]);
                    w[node.size..].fill(0.0);
                    forward::<FMA>(l, w.len(), node.size, w);
                    x[own].copy_from_slice(&w[..node.size]);
                    // the pattern rows started at zero: they hold −L_bot x_top
                    for (&i, &v) in pattern.iter().zip(&w[node.size..]) {
                        x[i] += v;
                    }
                }
            }
            Sweep::Backward => {
                for node in nodes.iter().rev() {
                    let (l, pattern, w) = self.parts(node, values, work);
                    let own = node.start..node.start + node.size;
                    w[..node.size].copy_from_slice(&x[own.clone()]);
                    for (wi, &i) in w[node.size..].iter_mut().zip(pattern) {
                        *wi = x[i];
                    }
                    backward::<FMA>(l, w.len(), node.size, w);
                    x[own].copy_from_slice(&w[..node.size]);
                }
            }
        }
    }

    /// A supernode's values, its pattern and the part of `work` for its rows.
    #[inline(always)]
    fn parts<'a>(
        &'a self,
        node: &Node,
        values: &'a [f64],
        work: &'a mut [f64],
    ) -> (&'a [f64], &'a [usize], &'a mut [f64]) {
        let rows = node.size + node.pat_len;
        (
            &values[node.val..node.val + rows * node.size],
            &self.pattern[node.pat..node.pat + node.pat_len],
            &mut work[..rows],
        )
    }
}

#[derive(Debug, Clone, Copy)]
enum Sweep {
    Forward,
    Backward,
}

/// Two groups of independent subtrees of the supernodal elimination tree with about the same
/// number of values, and the chain of supernodes above them; None when the supernodes are
/// not in postorder or no split leaves each group at least a quarter of the work.
fn find_split(nodes: &[Node], pattern: &[usize]) -> Option<Split> {
    let n = nodes.len();
    if n < 4 {
        return None;
    }
    let n_cols = nodes.last().map(|s| s.start + s.size)?;
    let mut owner = vec![0usize; n_cols];
    for (s, node) in nodes.iter().enumerate() {
        owner[node.start..node.start + node.size].fill(s);
    }
    // parent: the supernode of the first (smallest) pattern row
    let mut children: Vec<Vec<usize>> = vec![Vec::new(); n];
    let mut roots = Vec::new();
    for (s, node) in nodes.iter().enumerate() {
        match pattern[node.pat..node.pat + node.pat_len].iter().min() {
            Some(&row) => children[owner[row]].push(s),
            None => roots.push(s),
        }
    }
    // subtree sizes (postorder: children before parents) and work (values)
    let mut count = vec![1usize; n];
    let mut work = vec![0usize; n];
    for s in 0..n {
        work[s] += (nodes[s].size + nodes[s].pat_len) * nodes[s].size;
        for &c in &children[s] {
            if c >= s {
                return None;
            }
            count[s] += count[c];
            work[s] += work[c];
        }
    }
    // every subtree a contiguous range ending at its root
    for s in 0..n {
        let first = s + 1 - count[s];
        if children[s].iter().any(|&c| c + 1 - count[c] < first) {
            return None;
        }
    }
    if roots.len() != 1 || roots[0] != n - 1 {
        return None;
    }
    let mut node = n - 1;
    while children[node].len() == 1 {
        node = children[node][0];
    }
    if children[node].len() < 2 || node + 1 != count[node] {
        return None;
    }
    let mut subtrees: Vec<usize> = children[node].clone();
    subtrees.sort_by_key(|&c| std::cmp::Reverse(work[c]));
    let mut groups: [Vec<Range<usize>>; 2] = [Vec::new(), Vec::new()];
    let mut load = [0usize; 2];
    for c in subtrees {
        let g = if load[0] <= load[1] { 0 } else { 1 };
        groups[g].push(c + 1 - count[c]..c + 1);
        load[g] += work[c];
    }
    let total = load[0] + load[1];
    if load[0].min(load[1]) * 4 < total {
        return None;
    }
    for g in &mut groups {
        g.sort_by_key(|r| r.start);
    }
    Some(Split { groups, top: node })
}

/// Columns handled together.
const COLS: usize = 4;

/// Forward solve with one supernode `l` (`rows` x `size`, column-major): on entry `w` holds
/// the right-hand side's own rows then zeros for the pattern rows; on exit the solution's
/// own rows then the updates to add to the pattern rows.
#[inline(always)]
fn forward<const FMA: bool>(l: &[f64], rows: usize, size: usize, w: &mut [f64]) {
    let mut j0 = 0;
    while j0 < size {
        let nb = COLS.min(size - j0);
        // the diagonal block
        for j in j0..j0 + nb {
            let col = &l[j * rows..(j + 1) * rows];
            let xj = w[j] / col[j];
            w[j] = xj;
            for i in j + 1..j0 + nb {
                w[i] -= col[i] * xj;
            }
        }
        let below = j0 + nb;
        if nb == COLS {
            let c0 = &l[j0 * rows + below..(j0 + 1) * rows];
            let c1 = &l[(j0 + 1) * rows + below..(j0 + 2) * rows];
            let c2 = &l[(j0 + 2) * rows + below..(j0 + 3) * rows];
            let c3 = &l[(j0 + 3) * rows + below..(j0 + 4) * rows];
            let (x0, x1, x2, x3) = (-w[j0], -w[j0 + 1], -w[j0 + 2], -w[j0 + 3]);
            let tail = &mut w[below..rows];
            for ((((t, &a), &b), &c), &d) in tail.iter_mut().zip(c0).zip(c1).zip(c2).zip(c3) {
                *t = madd::<FMA>(
                    a,
                    x0,
                    madd::<FMA>(b, x1, madd::<FMA>(c, x2, madd::<FMA>(d, x3, *t))),
                );
            }
        } else {
            for j in j0..j0 + nb {
                let col = &l[j * rows + below..(j + 1) * rows];
                let xj = -w[j];
                for (t, &a) in w[below..rows].iter_mut().zip(col) {
                    *t = madd::<FMA>(a, xj, *t);
                }
            }
        }
        j0 += nb;
    }
}

/// Backward solve with one supernode: on entry `w` holds the own rows of `y` then the
/// solution at the pattern rows; on exit the own rows are the solution.
#[inline(always)]
fn backward<const FMA: bool>(l: &[f64], rows: usize, size: usize, w: &mut [f64]) {
    // column blocks from the last; the first block may be short
    let mut j1 = size;
    while j1 > 0 {
        let nb = if j1 % COLS == 0 { COLS } else { j1 % COLS };
        let j0 = j1 - nb;
        let (head, tail) = w.split_at_mut(j1);
        if nb == COLS {
            let c0 = &l[j0 * rows + j1..(j0 + 1) * rows];
            let c1 = &l[(j0 + 1) * rows + j1..(j0 + 2) * rows];
            let c2 = &l[(j0 + 2) * rows + j1..(j0 + 3) * rows];
            let c3 = &l[(j0 + 3) * rows + j1..(j0 + 4) * rows];
            let (mut s0, mut s1, mut s2, mut s3) = (0.0, 0.0, 0.0, 0.0);
            for ((((&t, &a), &b), &c), &d) in tail.iter().zip(c0).zip(c1).zip(c2).zip(c3) {
                s0 = madd::<FMA>(a, t, s0);
                s1 = madd::<FMA>(b, t, s1);
                s2 = madd::<FMA>(c, t, s2);
                s3 = madd::<FMA>(d, t, s3);
            }
            head[j0] -= s0;
            head[j0 + 1] -= s1;
            head[j0 + 2] -= s2;
            head[j0 + 3] -= s3;
        } else {
            for j in j0..j1 {
                let col = &l[j * rows + j1..(j + 1) * rows];
                let mut s = 0.0;
                for (&t, &a) in tail.iter().zip(col) {
                    s = madd::<FMA>(a, t, s);
                }
                head[j] -= s;
            }
        }
        // the diagonal block, transposed
        for j in (j0..j1).rev() {
            let col = &l[j * rows..(j + 1) * rows];
            let mut v = head[j];
            for i in j + 1..j1 {
                v -= col[i] * head[i];
            }
            head[j] = v / col[j];
        }
        j1 = j0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::sparse::linalg::cholesky::supernodal::SupernodalLltRef;

    #[test]
    fn plan_matches_faer_supernodes() {
        let model = crate::model::default_block_model(crate::element::ElementKind::Hex8).unwrap();
        let values = model.system_values(1.0, 0.5, &vec![10.0; model.ops.faces.len()]);
        let analysis = crate::solver::SymbolicAnalysis::new(
            &model.ops.pattern,
            crate::solver::CholeskyKind::Supernodal,
        )
        .unwrap();
        let f = analysis
            .factorize(&model.ops.pattern, &values, faer::Par::Seq)
            .unwrap();
        let (sym, vals) = f.supernodal_parts().unwrap();
        let plan = SupernodePlan::new(sym);
        let llt = SupernodalLltRef::<usize, f64>::new(sym, vals);
        for (s, node) in plan.nodes.iter().enumerate() {
            let sn = llt.supernode(s);
            assert_eq!(sn.start(), node.start);
            assert_eq!(sn.val().ncols(), node.size);
            assert_eq!(
                sn.pattern(),
                &plan.pattern[node.pat..node.pat + node.pat_len],
                "{s}"
            );
            assert_eq!(sn.val()[(0, 0)], vals[node.val]);
        }
    }

    #[test]
    fn the_two_thread_solve_is_the_one_thread_solve() {
        // nested dissection (the mesher's order) splits the tree in two halves
        let geometry = crate::mesh::BlockGeometry::default();
        let spec = crate::mesh::BlockMeshSpec {
            kind: crate::element::ElementKind::Hex8,
            ..Default::default()
        };
        let mesh = crate::mesh::block_mesh(&geometry, &spec).unwrap();
        let order = mesh.ordering.clone().unwrap();
        let model = crate::model::ThermalModel::new(
            mesh,
            crate::assembly::Material::CAST_IRON,
            crate::solver::CholeskyKind::Supernodal,
            "friction",
        )
        .unwrap();
        let pattern = &model.ops.pattern;
        let values = model.system_values(1.0, 0.5, &vec![10.0; model.ops.faces.len()]);
        let analysis = crate::solver::SymbolicAnalysis::with_ordering(
            pattern,
            crate::solver::CholeskyKind::Supernodal,
            Some(&order),
        )
        .unwrap();
        let f = analysis
            .factorize(pattern, &values, faer::Par::Seq)
            .unwrap();
        let (sym, vals) = f.supernodal_parts().unwrap();
        let plan = SupernodePlan::new(sym);
        assert!(plan.is_split());
        let b: Vec<f64> = (0..pattern.n)
            .map(|i| ((i * 13) % 11) as f64 - 5.0)
            .collect();
        let mut one = b.clone();
        let mut two = b.clone();
        plan.solve_permuted(vals, &mut one, false);
        plan.solve_permuted(vals, &mut two, true);
        let scale = one.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let diff = one
            .iter()
            .zip(&two)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(diff <= 1e-13 * scale, "{diff:e}");
    }
}
