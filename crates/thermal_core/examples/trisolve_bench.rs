//! One-right-hand-side solves with the default block's Crank-Nicolson matrix, side by side:
//! faer's simplicial and supernodal solves and the streaming supernodal kernels of
//! `thermal_core::trisolve`, with the residual of each.
//!
//! `cargo run --release -p thermal_core --example trisolve_bench [repeats]`

use std::time::Instant;

use thermal_core::element::ElementKind;
use thermal_core::mesh::block_mesh;
use thermal_core::model::{convection_off_friction, default_block_model, default_block_spec};
use thermal_core::solver::{relative_residual, CholeskyKind, SymbolicAnalysis};

#[derive(Clone, Copy)]
enum Solve {
    Faer,
    Streaming,
    Mixed,
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let repeats: usize = std::env::args().nth(1).map_or(Ok(100), |s| s.parse())?;
    let model = default_block_model(ElementKind::Hex20)?;
    let values = model.system_values(1.0, 0.5, &convection_off_friction(&model, 10.0));
    let pattern = &model.ops.pattern;
    let (geometry, spec) = default_block_spec(ElementKind::Hex20);
    let nd = block_mesh(&geometry, &spec)?
        .ordering
        .ok_or("no ordering")?;
    let b: Vec<f64> = (0..pattern.n)
        .map(|i| ((i * 37) % 17) as f64 - 8.0)
        .collect();
    println!("nodes {}, {} solves each", pattern.n, repeats);
    for (label, kind) in [
        ("simplicial", CholeskyKind::Simplicial),
        ("supernodal", CholeskyKind::Supernodal),
    ] {
        let analysis = SymbolicAnalysis::with_ordering(pattern, kind, Some(&nd))?;
        let factor = analysis.factorize(pattern, &values, faer::Par::Seq)?;
        let mut scratch = factor.scratch(1);
        let mut run = |name: &str, how: Solve| {
            let mut x = b.clone();
            let t0 = Instant::now();
            for _ in 0..repeats {
                x.copy_from_slice(&b);
                match how {
                    Solve::Faer => factor.solve_in_place_faer(&mut x, &mut scratch),
                    Solve::Streaming => factor.solve_in_place(&mut x, &mut scratch),
                    Solve::Mixed => factor.solve_in_place_mixed(&mut x, &mut scratch),
                }
            }
            let per = t0.elapsed().as_secs_f64() / repeats as f64;
            let r = relative_residual(pattern, &values, &x, &b);
            println!(
                "{label:>10} {name:<9} factor nnz {:>10}  {:7.3} ms/solve  residual {r:.1e}",
                analysis.factor_nnz(),
                per * 1e3
            );
        };
        run("faer", Solve::Faer);
        if let Some(plan) = factor.plan() {
            let (supernodes, mean_cols, pattern_rows) = plan.stats();
            println!(
                "{label:>10} {supernodes} supernodes, {mean_cols:.1} columns each on average, \
                 {pattern_rows} pattern rows; split in two halves: {}",
                plan.is_split()
            );
            run("streaming", Solve::Streaming);
            run("mixed", Solve::Mixed);
        }
    }
    Ok(())
}
