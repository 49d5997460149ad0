//! `cargo run --release -p vlmfuse-fusion --example bench [BANKS] [DIM]`: the engine benchmarks
//! without building the whole service (the same code `vlmfuse bench` runs).

use vlmfuse_testkit::bench::{engine_bench, knn_bench, EngineBenchArgs};

fn main() -> anyhow::Result<()> {
    let mut a = std::env::args().skip(1);
    let banks = a
        .next()
        .map(|s| s.split(',').filter_map(|v| v.parse().ok()).collect())
        .unwrap_or_else(|| vec![1_000, 10_000, 100_000]);
    let dim = a.next().and_then(|s| s.parse().ok()).unwrap_or(512);
    let args = EngineBenchArgs {
        banks,
        dim,
        reporters: 3,
        rounds: 300,
    };
    engine_bench(&args)?;
    knn_bench(&args)
}
