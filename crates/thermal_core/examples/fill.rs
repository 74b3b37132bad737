//! Fill of the Cholesky factor of the default block and the time of one solve, under each
//! ordering (AMD, nested dissection), variant (simplicial, supernodal) and thread count,
//! beside the machine's read bandwidth.
//! `cargo run --release -p thermal_core --example fill`
use std::time::Instant;

use faer::Par;
use thermal_core::assembly::{assemble, Material};
use thermal_core::mesh::{block_mesh, BlockGeometry, BlockMeshSpec};
use thermal_core::solver::{CholeskyKind, SymbolicAnalysis};
use thermal_core::ElementKind;

fn read_bandwidth_gb_s() -> f64 {
    let v = vec![1.0f64; 64 << 20]; // 512 MiB
    let mut best = f64::INFINITY;
    let mut sink = 0.0;
    for _ in 0..3 {
        let t = Instant::now();
        sink += v.iter().sum::<f64>();
        best = best.min(t.elapsed().as_secs_f64());
    }
    std::hint::black_box(sink);
    (v.len() * 8) as f64 / best / 1e9
}

fn main() -> thermal_core::Result<()> {
    let bw = read_bandwidth_gb_s();
    println!("read bandwidth {bw:.1} GB/s");
    let g = BlockGeometry::default();
    let kind = ElementKind::Hex20;
    let spec = BlockMeshSpec {
        kind,
        focus_m: Some([0.0, g.wheel_radius_m + 0.055, 0.0]),
        ..Default::default()
    };
    let mesh = block_mesh(&g, &spec)?;
    let ops = assemble(&mesh, &Material::CAST_IRON)?;
    let values = ops
        .pattern
        .combine(&[(1.0, &ops.capacity), (0.5, &ops.conduction)]);
    let b: Vec<f64> = (0..mesh.n_nodes()).map(|i| (i % 13) as f64).collect();
    for (label, order) in [("amd", None), ("nd", mesh.ordering.as_deref())] {
        for chol in [CholeskyKind::Simplicial, CholeskyKind::Supernodal] {
            let an = SymbolicAnalysis::with_ordering(&ops.pattern, chol, order)?;
            let t = Instant::now();
            let f = an.factorize(&ops.pattern, &values, Par::rayon(2))?;
            let tf = t.elapsed().as_secs_f64();
            for par in [Par::Seq, Par::rayon(2)] {
                let mut scratch = f.scratch_par(1, par);
                let mut x = b.clone();
                let reps = 30;
                let t = Instant::now();
                for _ in 0..reps {
                    x.copy_from_slice(&b);
                    let n = x.len();
                    f.solve_mat_in_place_par(
                        faer::MatMut::from_column_major_slice_mut(&mut x, n, 1),
                        &mut scratch,
                        par,
                    );
                }
                let ts = t.elapsed().as_secs_f64() / reps as f64;
                let bound = 2.0 * 8.0 * an.factor_nnz() as f64 / (bw * 1e9);
                println!(
                    "{label:>3} {chol:?} {par:?}: nnzL {} factor {tf:.2}s solve {:.2} ms (values-only bound {:.2} ms, ratio {:.2})",
                    an.factor_nnz(), ts * 1e3, bound * 1e3, ts / bound
                );
            }
        }
    }
    Ok(())
}
