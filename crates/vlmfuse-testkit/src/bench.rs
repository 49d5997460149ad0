//! Engine benchmarks shared by `vlmfuse bench` and `cargo run --release -p vlmfuse-fusion
//! --example bench`: fuse-then-feedback per round at several bank sizes, and batched GEMM
//! against per-query similarity. They print to stdout, which is why they live here and not in
//! the engine's crate (no I/O there).

use crate::rng::SplitMix64 as Rng;
use faer::{Accum, MatMut, MatRef, Par};
use std::collections::BTreeMap;
use std::io::Write;
use std::time::Instant;
use vlmfuse_fusion::replay::{prepare, replay, ReplayOptions};
use vlmfuse_fusion::{Engine, FusionConfig, LabelledRound, Method, Ontology, Round, RoundRecord};

/// What to measure.
#[derive(Debug, Clone)]
pub struct EngineBenchArgs {
    pub banks: Vec<usize>,
    pub dim: usize,
    pub reporters: usize,
    pub rounds: usize,
}

/// Synthetic rounds with cluster structure: (context, present, reports n*L, truth L).
struct Synth {
    rng: Rng,
    centres: Vec<Vec<f64>>,
    n: usize,
    l: usize,
}

impl Synth {
    fn new(seed: u64, d: usize, n: usize, l: usize) -> Self {
        let mut rng = Rng::new(seed);
        let centres = (0..12)
            .map(|_| (0..d).map(|_| rng.f() - 0.5).collect())
            .collect();
        Self { rng, centres, n, l }
    }

    fn round(&mut self) -> (Vec<f64>, Vec<bool>, Vec<u8>, Vec<u8>) {
        let c = (self.rng.next_u64() % self.centres.len() as u64) as usize;
        let x: Vec<f64> = self.centres[c]
            .iter()
            .map(|v| v + 0.4 * (self.rng.f() - 0.5))
            .collect();
        let norm = x.iter().map(|v| v * v).sum::<f64>().sqrt();
        let x = x.iter().map(|v| v / norm).collect();
        let y: Vec<u8> = (0..self.l)
            .map(|k| (self.rng.f() < 0.1 + 0.3 * (c + k).is_multiple_of(5) as u8 as f64) as u8)
            .collect();
        let present = vec![true; self.n];
        let mut r = vec![0u8; self.n * self.l];
        for i in 0..self.n {
            for k in 0..self.l {
                let flip = self.rng.f() < 0.08 + 0.07 * i as f64;
                r[i * self.l + k] = y[k] ^ flip as u8;
            }
        }
        (x, present, r, y)
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() as f64 * p).ceil() as usize).clamp(1, sorted.len()) - 1]
}

/// One method's fuse-then-feedback latencies (µs) over `args.rounds` live rounds after a bank
/// of `bank` labelled rounds. Under `adaptive` each live round is also observed (it joins the
/// pool at fuse time, as in the service) before its feedback.
fn fuse_feedback_latencies(
    method: Method,
    bank: usize,
    args: &EngineBenchArgs,
) -> anyhow::Result<(Vec<f64>, f64, f64)> {
    let ontology = Ontology::paper();
    let l = ontology.len();
    let names: Vec<String> = (0..args.reporters).map(|i| format!("m{i}")).collect();
    let cfg = FusionConfig {
        method,
        ..FusionConfig::default()
    };
    let mut engine = Engine::new(cfg, ontology, names)?;
    let mut synth = Synth::new(42, args.dim, args.reporters, l);
    let fill = Instant::now();
    for s in 0..bank {
        let (x, present, r, y) = synth.round();
        let lr = LabelledRound {
            seq: s as u64,
            round: Round {
                context: x,
                present,
                reports: r,
            },
            q: y.iter().map(|&v| 0.3 + 0.4 * v as f64).collect(),
            truth: y,
        };
        engine.apply(&lr, None)?;
    }
    let fill_s = fill.elapsed().as_secs_f64();
    let mut lat = Vec::with_capacity(args.rounds);
    let mut scan = 0.0;
    for t in 0..args.rounds {
        let (x, present, r, y) = synth.round();
        let round = Round {
            context: x,
            present,
            reports: r,
        };
        let s0 = Instant::now();
        std::hint::black_box(engine.bank().top_exact(&round.context, 50));
        scan += s0.elapsed().as_secs_f64();
        let seq = (bank + t) as u64;
        let start = Instant::now();
        let inf = engine.infer(&round);
        let t1 = Instant::now();
        engine.observe(seq, &round, &inf)?;
        let t2 = Instant::now();
        let outcome = engine.credit(&inf.signals, &inf.w_used, &y, seq);
        let t3 = Instant::now();
        if std::env::var_os("VLMFUSE_BENCH_PARTS").is_some() && t % 50 == 0 {
            eprintln!(
                "{method}: infer {:?} observe {:?} credit {:?}",
                t1 - start,
                t2 - t1,
                t3 - t2
            );
        }
        let lr = LabelledRound {
            seq,
            round,
            truth: y,
            q: inf.q,
        };
        engine.apply(&lr, Some(&outcome))?;
        lat.push(start.elapsed().as_secs_f64() * 1e6);
    }
    lat.sort_by(f64::total_cmp);
    Ok((lat, scan / args.rounds as f64 * 1e6, fill_s))
}

/// Fuse-then-feedback per round under both methods at each bank size, in one run, with the
/// adaptive/paper ratio of the means (issue 9's speed target: at most 1.5x at bank 10k, d 512).
pub fn engine_bench(args: &EngineBenchArgs) -> anyhow::Result<()> {
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
    for &bank in &args.banks {
        let mut paper_mean = f64::NAN;
        for method in [Method::Paper, Method::Adaptive] {
            let (lat, scan, fill_s) = fuse_feedback_latencies(method, bank, args)?;
            let mean = lat.iter().sum::<f64>() / lat.len() as f64;
            if method == Method::Paper {
                paper_mean = mean;
            }
            println!(
                "{:>9} {:>9} {:>12.1} {:>12.1} {:>12.1} {:>14.1} {:>10.2} {:>8.2}x",
                bank,
                method.name(),
                mean,
                percentile(&lat, 0.5),
                percentile(&lat, 0.95),
                scan,
                fill_s,
                mean / paper_mean
            );
            let _ = std::io::stdout().flush();
        }
    }
    Ok(())
}

pub fn synthetic_records(
    n_rounds: usize,
    d: usize,
    n: usize,
    seed: u64,
) -> Vec<(usize, RoundRecord)> {
    let ontology = Ontology::paper();
    let mut synth = Synth::new(seed, d, n, ontology.len());
    let l = ontology.len();
    (0..n_rounds)
        .map(|t| {
            let (x, _, r, y) = synth.round();
            let reports: BTreeMap<String, Vec<String>> = (0..n)
                .map(|i| (format!("m{i}"), ontology.decode(&r[i * l..(i + 1) * l])))
                .collect();
            (
                t + 1,
                RoundRecord {
                    id: Some(format!("r{t}")),
                    context: x,
                    reports,
                    truth: Some(ontology.decode(&y)),
                },
            )
        })
        .collect()
}

pub fn knn_bench(args: &EngineBenchArgs) -> anyhow::Result<()> {
    // Raw similarity work: 256 queries against a 10k bank, per-query dots against one GEMM.
    let (q, b, d) = (256usize, 10_000usize, args.dim);
    let mut rng = Rng::new(7);
    let keys: Vec<f64> = (0..b * d).map(|_| rng.f() - 0.5).collect();
    let queries: Vec<f64> = (0..q * d).map(|_| rng.f() - 0.5).collect();
    let start = Instant::now();
    let mut acc = 0.0;
    for qi in 0..q {
        let x = &queries[qi * d..(qi + 1) * d];
        for c in keys.chunks_exact(d) {
            acc += vlmfuse_fusion::bank::dot(x, c);
        }
    }
    std::hint::black_box(acc);
    let per_query = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let mut out = vec![0.0; q * b];
    faer::linalg::matmul::matmul(
        MatMut::from_row_major_slice_mut(&mut out, q, b),
        Accum::Replace,
        MatRef::from_row_major_slice(&queries, q, d),
        MatRef::from_row_major_slice(&keys, b, d).transpose(),
        1.0,
        Par::Seq,
    );
    std::hint::black_box(&out);
    let gemm = start.elapsed().as_secs_f64();
    println!(
        "\nsimilarities, {q} queries x {b} bank x d {d}: per-query dots {:.1} ms, one GEMM {:.1} ms \
         -> GEMM {:.2}x faster",
        per_query * 1e3,
        gemm * 1e3,
        per_query / gemm
    );

    // The same inside a whole replay (2,000 rounds, d = dim).
    let records = synthetic_records(2000, d, args.reporters, 11);
    let (engine, rounds) = prepare(&FusionConfig::default(), &Ontology::paper(), &records)?;
    let mut times = Vec::new();
    for batch in [false, true] {
        let opts = ReplayOptions {
            split: 0.7,
            frozen: false,
            batch_knn: batch,
        };
        let start = Instant::now();
        let (_, outs) = replay(engine.clone(), &rounds, &opts, &mut |_| {})?;
        std::hint::black_box(outs);
        times.push(start.elapsed().as_secs_f64());
    }
    println!(
        "replay of 2,000 rounds at d = {d}: per-query kNN {:.1} ms, batched GEMM kNN {:.1} ms -> {:.2}x",
        times[0] * 1e3,
        times[1] * 1e3,
        times[0] / times[1]
    );
    Ok(())
}
