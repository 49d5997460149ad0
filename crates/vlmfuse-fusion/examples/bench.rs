//! `cargo run --release -p vlmfuse-fusion --example bench [BANKS] [DIM]`: the engine benchmarks
//! without building the whole service (the same code `vlmfuse bench` runs).

fn main() -> Result<(), String> {
    let mut a = std::env::args().skip(1);
    let banks = a
        .next()
        .map(|s| s.split(',').filter_map(|v| v.parse().ok()).collect())
        .unwrap_or_else(|| vec![1_000, 10_000, 100_000]);
    let dim = a.next().and_then(|s| s.parse().ok()).unwrap_or(512);
    let args = vlmfuse_fusion::bench::EngineBenchArgs {
        banks,
        dim,
        reporters: 3,
        rounds: 300,
    };
    vlmfuse_fusion::bench::engine_bench(&args)?;
    vlmfuse_fusion::bench::knn_bench(&args)
}
