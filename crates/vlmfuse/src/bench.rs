//! `vlmfuse bench`: the engine's speed, measured in one run so ratios compare like with like.
//! Numbers come from a release build (`cargo run --release -- bench`); a debug build is ~10x
//! slower and says nothing about production.

use crate::eval::{self, EvalArgs};
use clap::Args;
use std::io::Write;
use std::time::Instant;
use vlmfuse_fusion::{FusionConfig, Ontology};
use vlmfuse_testkit::bench::{engine_bench, knn_bench, synthetic_records, EngineBenchArgs};

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

pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    if cfg!(debug_assertions) {
        eprintln!("warning: a debug build; run `cargo run --release -- bench` for real numbers");
    }
    let eargs = EngineBenchArgs {
        banks: args.banks.clone(),
        dim: args.dim,
        reporters: args.reporters,
        rounds: args.rounds,
    };
    engine_bench(&eargs)?;
    if !args.engine_only {
        knn_bench(&eargs)?;
        eval_bench(&args)?;
    }
    Ok(())
}
