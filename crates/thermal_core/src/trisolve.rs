//! The two triangular solves `L y = b`, `Lᵀ x = y` with a supernodal Cholesky factor, for one
//! right-hand side: the time stepper's inner loop.
//!
//! A supernode is a dense column-major block: its `size` diagonal rows (lower triangle used),
//! then the rows of its pattern (ancestors). Each solve reads every value of the factor once,
//! so a step is bound by memory traffic; the kernels below stream each supernode's columns
//! in panels of eight (then four, then one: one pass over the rows below a panel for all its
//! columns), with AVX2 fused multiply-adds where the CPU has them, reading the values in
//! double or single precision ([`FactorValue`]). The permutation is applied around them as
//! faer does (`x[i] = b[fwd[i]]`, result `b[i] = x[inv[i]]`).

use std::ops::Range;

use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;

use crate::simd::{has_avx2_fma, madd};

/// How a factor's values may be stored: in double precision, or in single precision and
/// widened to double as they are read (half the memory traffic of a solve; the arithmetic
/// stays in double).
pub trait FactorValue: Copy + Send + Sync + 'static {
    fn get(self) -> f64;

    /// Four values from `p` on, widened to double.
    ///
    /// # Safety
    /// `p..p + 4` must be readable, and the CPU must have AVX.
    #[cfg(target_arch = "x86_64")]
    unsafe fn load4(p: *const Self) -> std::arch::x86_64::__m256d;
}

impl FactorValue for f64 {
    #[inline(always)]
    fn get(self) -> f64 {
        self
    }

    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn load4(p: *const Self) -> std::arch::x86_64::__m256d {
        std::arch::x86_64::_mm256_loadu_pd(p)
    }
}

impl FactorValue for f32 {
    #[inline(always)]
    fn get(self) -> f64 {
        f64::from(self)
    }

    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn load4(p: *const Self) -> std::arch::x86_64::__m256d {
        use std::arch::x86_64::{_mm256_cvtps_pd, _mm_loadu_ps};
        _mm256_cvtps_pd(_mm_loadu_ps(p))
    }
}

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
    pub fn solve_permuted<V: FactorValue>(&self, values: &[V], x: &mut [f64], parallel: bool) {
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

    fn solve_split<V: FactorValue>(&self, split: &Split, values: &[V], x: &mut [f64]) {
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
    fn sweep_copy<V: FactorValue>(
        &self,
        dir: Sweep,
        values: &[V],
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

    fn sweep<V: FactorValue>(
        &self,
        dir: Sweep,
        values: &[V],
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
        self.sweep_generic::<V, false>(dir, values, x, work, range);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn sweep_avx2<V: FactorValue>(
        &self,
        dir: Sweep,
        values: &[V],
        x: &mut [f64],
        work: &mut [f64],
        range: Range<usize>,
    ) {
        self.sweep_generic::<V, true>(dir, values, x, work, range);
    }

    /// The forward solve over the supernodes of `range` in order, or the backward solve
    /// over them in reverse.
    #[inline(always)]
    fn sweep_generic<V: FactorValue, const FMA: bool>(
        &self,
        dir: Sweep,
        values: &[V],
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
                    forward::<V, FMA>(l, w.len(), node.size, w);
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
                    backward::<V, FMA>(l, w.len(), node.size, w);
                    x[own].copy_from_slice(&w[..node.size]);
                }
            }
        }
    }

    /// A supernode's values, its pattern and the part of `work` for its rows.
    #[inline(always)]
    fn parts<'a, V: FactorValue>(
        &'a self,
        node: &Node,
        values: &'a [V],
        work: &'a mut [f64],
    ) -> (&'a [V], &'a [usize], &'a mut [f64]) {
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

/// Forward solve with one supernode `l` (`rows` x `size`, column-major): on entry `w` holds
/// the right-hand side's own rows then zeros for the pattern rows; on exit the solution's
/// own rows then the updates to add to the pattern rows.
///
/// Column panels of eight, then four, then one: each panel's columns are read in one pass
/// over the rows below it (the pass reads and writes `w` once for all of them).
#[inline(always)]
fn forward<V: FactorValue, const FMA: bool>(l: &[V], rows: usize, size: usize, w: &mut [f64]) {
    let mut j0 = 0;
    while j0 < size {
        let nb = panel_width(size - j0);
        // the panel's triangle
        for j in j0..j0 + nb {
            let col = &l[j * rows..(j + 1) * rows];
            let xj = w[j] / col[j].get();
            w[j] = xj;
            for i in j + 1..j0 + nb {
                w[i] -= col[i].get() * xj;
            }
        }
        let below = j0 + nb;
        let col = |j: usize| &l[j * rows + below..(j + 1) * rows];
        let (head, tail) = w.split_at_mut(below);
        match nb {
            8 => update::<V, 8, FMA>(std::array::from_fn(|k| col(j0 + k)), neg(head, j0), tail),
            4 => update::<V, 4, FMA>(std::array::from_fn(|k| col(j0 + k)), neg(head, j0), tail),
            _ => update::<V, 1, FMA>([col(j0)], [-head[j0]], tail),
        }
        j0 += nb;
    }
}

/// Backward solve with one supernode: on entry `w` holds the own rows of `y` then the
/// solution at the pattern rows; on exit the own rows are the solution. Column panels from
/// the last column, as wide as [`forward`]'s.
#[inline(always)]
fn backward<V: FactorValue, const FMA: bool>(l: &[V], rows: usize, size: usize, w: &mut [f64]) {
    let mut j1 = size;
    while j1 > 0 {
        let nb = panel_width(j1);
        let j0 = j1 - nb;
        let col = |j: usize| &l[j * rows + j1..(j + 1) * rows];
        let (head, tail) = w.split_at_mut(j1);
        match nb {
            8 => subtract(
                &mut head[j0..j1],
                dots::<V, 8, FMA>(std::array::from_fn(|k| col(j0 + k)), tail),
            ),
            4 => subtract(
                &mut head[j0..j1],
                dots::<V, 4, FMA>(std::array::from_fn(|k| col(j0 + k)), tail),
            ),
            _ => subtract(&mut head[j0..j1], dots::<V, 1, FMA>([col(j0)], tail)),
        }
        // the panel's triangle, transposed
        for j in (j0..j1).rev() {
            let col = &l[j * rows..(j + 1) * rows];
            let mut v = head[j];
            for i in j + 1..j1 {
                v -= col[i].get() * head[i];
            }
            head[j] = v / col[j].get();
        }
        j1 = j0;
    }
}

/// The widest panel (8, 4 or 1 columns) that fits in `remaining` columns.
#[inline(always)]
fn panel_width(remaining: usize) -> usize {
    if remaining >= 8 {
        8
    } else if remaining >= 4 {
        4
    } else {
        1
    }
}

/// `−x[j0..j0 + W]`.
#[inline(always)]
fn neg<const W: usize>(x: &[f64], j0: usize) -> [f64; W] {
    std::array::from_fn(|k| -x[j0 + k])
}

#[inline(always)]
fn subtract<const W: usize>(x: &mut [f64], d: [f64; W]) {
    for (xi, di) in x.iter_mut().zip(d) {
        *xi -= di;
    }
}

/// `t += Σ_k x[k] cols[k]` (every column as long as `t`), on AVX2 + FMA where `FMA` says
/// the CPU has them.
#[inline(always)]
fn update<V: FactorValue, const W: usize, const FMA: bool>(
    cols: [&[V]; W],
    x: [f64; W],
    t: &mut [f64],
) {
    #[cfg(target_arch = "x86_64")]
    if FMA && cols.iter().all(|c| c.len() == t.len()) {
        // SAFETY: FMA is set only on the path taken when the CPU has AVX2 and FMA; the
        // columns are as long as t.
        unsafe { update_avx2(cols, x, t) };
        return;
    }
    for (r, tr) in t.iter_mut().enumerate() {
        let mut a = *tr;
        for (c, xk) in cols.iter().zip(&x) {
            a = madd::<FMA>(c[r].get(), *xk, a);
        }
        *tr = a;
    }
}

/// The dot products `cols[k] · t` (every column as long as `t`), on AVX2 + FMA where `FMA`
/// says the CPU has them.
#[inline(always)]
fn dots<V: FactorValue, const W: usize, const FMA: bool>(cols: [&[V]; W], t: &[f64]) -> [f64; W] {
    #[cfg(target_arch = "x86_64")]
    if FMA && cols.iter().all(|c| c.len() == t.len()) {
        // SAFETY: as in `update`.
        return unsafe { dots_avx2(cols, t) };
    }
    let mut out = [0.0; W];
    for (o, c) in out.iter_mut().zip(&cols) {
        for (&a, &b) in c.iter().zip(t) {
            *o = madd::<FMA>(a.get(), b, *o);
        }
    }
    out
}

/// [`update`], four rows a vector.
///
/// # Safety
/// The CPU must have AVX2 and FMA; every column must be as long as `t`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn update_avx2<V: FactorValue, const W: usize>(cols: [&[V]; W], x: [f64; W], t: &mut [f64]) {
    use std::arch::x86_64::*;
    let n = t.len();
    let mut xs = [_mm256_setzero_pd(); W];
    for k in 0..W {
        xs[k] = _mm256_set1_pd(x[k]);
    }
    let tp = t.as_mut_ptr();
    let mut r = 0;
    while r + 4 <= n {
        // SAFETY: r + 4 <= n, the length of t and of every column.
        let mut acc = _mm256_loadu_pd(tp.add(r));
        for k in 0..W {
            acc = _mm256_fmadd_pd(V::load4(cols[k].as_ptr().add(r)), xs[k], acc);
        }
        _mm256_storeu_pd(tp.add(r), acc);
        r += 4;
    }
    for i in r..n {
        let mut a = t[i];
        for k in 0..W {
            a = cols[k][i].get().mul_add(x[k], a);
        }
        t[i] = a;
    }
}

/// [`dots`], four rows a vector, one vector of partial sums per column (the compiler keeps
/// the order of floating-point adds, so a plain loop would be one chain of dependent adds).
///
/// # Safety
/// The CPU must have AVX2 and FMA; every column must be as long as `t`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn dots_avx2<V: FactorValue, const W: usize>(cols: [&[V]; W], t: &[f64]) -> [f64; W] {
    use std::arch::x86_64::*;
    let n = t.len();
    let mut acc = [_mm256_setzero_pd(); W];
    let tp = t.as_ptr();
    let mut r = 0;
    while r + 4 <= n {
        // SAFETY: r + 4 <= n, the length of t and of every column.
        let tv = _mm256_loadu_pd(tp.add(r));
        for k in 0..W {
            acc[k] = _mm256_fmadd_pd(V::load4(cols[k].as_ptr().add(r)), tv, acc[k]);
        }
        r += 4;
    }
    let mut out = [0.0; W];
    for k in 0..W {
        let mut lanes = [0.0; 4];
        _mm256_storeu_pd(lanes.as_mut_ptr(), acc[k]);
        let mut s = (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
        for i in r..n {
            s = cols[k][i].get().mul_add(t[i], s);
        }
        out[k] = s;
    }
    out
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
