//! `vlmfuse bench`: the engine's speed, measured in one run so ratios compare like with like.
//! Numbers come from a release build (`cargo run --release -- bench`); a debug build is ~10x
//! slower and says nothing about production. The workloads and timed loops are the engine
//! crate's (`vlmfuse_fusion::bench`, also behind its criterion benches); this module prints.

use crate::eval::{self, EvalArgs};
use clap::Args;
use std::io::Write;
use std::time::Instant;
use vlmfuse_fusion::bench::{fuse_feedback, knn, synthetic_records};
use vlmfuse_fusion::{FusionConfig, Method, Ontology};

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Bank sizes for the fuse-then-feedback benchmark.
    #[arg(long, value_delimiter = ',', default_values_t = [1_000usize, 10_000, 100_000])]
    pub banks: Vec<usize>,
    /// Context dimension.
    #[arg(long, default_value_t = 512)]
    pub dim: usize,
    /// Reporters per round.
    #[arg(long, default_value_t = 3)]
    pub reporters: usize,
    /// Timed rounds per bank size.
    #[arg(long, default_value_t = 300)]
    pub rounds: usize,
    /// Skip the eval end-to-end and batch-kNN parts.
    #[arg(long)]
    pub engine_only: bool,
}

fn eval_bench(args: &BenchArgs) -> anyhow::Result<()> {
    let records = synthetic_records(2000, 103, args.reporters, 5);
    let dir = std::env::temp_dir().join(format!("vlmfuse-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let path = dir.join("rounds-2000-d103.jsonl");
    {
        let mut f = std::io::BufWriter::new(std::fs::File::create(&path)?);
        for (_, r) in &records {
            serde_json::to_writer(&mut f, r)?;
            f.write_all(b"\n")?;
        }
    }
    let eargs = EvalArgs {
        rounds: path.clone(),
        split: 0.7,
        frozen: false,
        ablations: vec![],
        emit_rounds: None,
        report: None,
        plots: None,
        config: None,
        per_query_knn: false,
        method: None,
        labelled: None,
        seed: 0,
        curve: vec![],
        quiet: true,
    };
    let start = Instant::now();
    let recs = eval::read_rounds(&path)?;
    let read = start.elapsed().as_secs_f64();
    let run = eval::evaluate(&FusionConfig::default(), &Ontology::paper(), &recs, &eargs)?;
    let table = eval::format_table(&run);
    std::hint::black_box(table);
    let total = start.elapsed().as_secs_f64();
    println!(
        "\neval end to end, 2,000 rounds, d = 103, n = {} (read + parse {:.0} ms, total {:.0} ms; \
         target < 500 ms)",
        args.reporters,
        read * 1e3,
        total * 1e3
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// Fuse-then-feedback per round under both methods at each bank size, in one run, with the
/// adaptive/paper ratio of the means (issue 9's speed target: at most 1.5x at bank 10k, d 512).
/// `VLMFUSE_BENCH_PARTS=1` adds each step's mean.
fn engine_bench(args: &BenchArgs) -> anyhow::Result<()> {
    let l = Ontology::paper().len();
    println!(
        "fuse-then-feedback per round (infer [+ observe] + Shapley credit + reputation update + \
         bank, window and threshold refit), d = {}, n = {}, L = {l}, one core",
        args.dim, args.reporters
    );
    println!(
        "{:>9} {:>9} {:>12} {:>12} {:>12} {:>14} {:>10} {:>9}",
        "bank", "method", "mean (us)", "p50 (us)", "p95 (us)", "top-50 (us)", "fill (s)", "ratio"
    );
    let parts = std::env::var_os("VLMFUSE_BENCH_PARTS").is_some();
    for &bank in &args.banks {
        let mut paper_mean = f64::NAN;
        for method in [Method::Paper, Method::Adaptive] {
            let t = fuse_feedback(method, bank, args.dim, args.reporters, args.rounds)?;
            let mean = t.mean_us();
            if method == Method::Paper {
                paper_mean = mean;
            }
            println!(
                "{:>9} {:>9} {:>12.1} {:>12.1} {:>12.1} {:>14.1} {:>10.2} {:>8.2}x",
                bank,
                method.name(),
                mean,
                t.percentile_us(0.5),
                t.percentile_us(0.95),
                t.top50_us,
                t.fill_s,
                mean / paper_mean
            );
            if parts {
                let p = t.mean_parts;
                println!(
                    "{:>19} infer {:?}, observe {:?}, credit {:?}, apply {:?}",
                    "", p.infer, p.observe, p.credit, p.apply
                );
            }
            let _ = std::io::stdout().flush();
        }
    }
    Ok(())
}

fn knn_bench(args: &BenchArgs) -> anyhow::Result<()> {
    let t = knn(args.dim, args.reporters)?;
    println!(
        "\nsimilarities, {} queries x {} bank x d {}: per-query dots {:.1} ms, one GEMM {:.1} ms \
         -> GEMM {:.2}x faster",
        t.queries,
        t.bank,
        t.dim,
        t.per_query_s * 1e3,
        t.gemm_s * 1e3,
        t.per_query_s / t.gemm_s
    );
    println!(
        "replay of {} rounds at d = {}: per-query kNN {:.1} ms, batched GEMM kNN {:.1} ms -> {:.2}x",
        t.replay_rounds,
        t.dim,
        t.replay_per_query_s * 1e3,
        t.replay_batched_s * 1e3,
        t.replay_per_query_s / t.replay_batched_s
    );
    Ok(())
}

pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    if cfg!(debug_assertions) {
        eprintln!("warning: a debug build; run `cargo run --release -- bench` for real numbers");
    }
    engine_bench(&args)?;
    if !args.engine_only {
        knn_bench(&args)?;
        eval_bench(&args)?;
    }
    Ok(())
}
