//! The engine's benchmarks under criterion: `cargo bench -p vlmfuse-fusion` (one group with
//! `cargo bench -p vlmfuse-fusion -- infer`). The workloads are `vlmfuse_fusion::bench`'s, the
//! same that `vlmfuse bench` prints as tables (one run, both methods, ratios).
//!
//! * `infer`: one round's inference at bank 1k and 10k, d = 512, under each method (pure: the
//!   state does not change between iterations);
//! * `fuse_feedback`: a whole live round (infer, observe, credit, apply). Each iteration adds the
//!   round to the bank, so the bank grows by the iteration count (a few thousand) during a
//!   measurement; the sizes named are where it starts;
//! * `similarities`: 64 queries against a 10k bank, per-query dot products against one GEMM;
//! * `replay`: 2,000 synthetic rounds replayed (70 % history), per-query against batched kNN.

use criterion::{criterion_group, criterion_main, BatchSize, BenchmarkId, Criterion};
use std::hint::black_box;
use std::time::Duration;
use vlmfuse_fusion::bench::{
    filled_engine, fuse_feedback_round, similarities_gemm, similarities_per_query,
    similarity_inputs, synthetic_records, Synth,
};
use vlmfuse_fusion::replay::{prepare, replay, ReplayOptions};
use vlmfuse_fusion::{FusionConfig, Method, Ontology};

const DIM: usize = 512;
const REPORTERS: usize = 3;
const BANKS: [usize; 2] = [1_000, 10_000];
const METHODS: [Method; 2] = [Method::Paper, Method::Adaptive];

fn infer(c: &mut Criterion) {
    let mut g = c.benchmark_group("infer");
    for bank in BANKS {
        for method in METHODS {
            let mut synth = Synth::new(42, DIM, REPORTERS, Ontology::paper().len());
            let engine = filled_engine(method, bank, REPORTERS, &mut synth).expect("engine");
            let rounds: Vec<_> = (0..64).map(|_| synth.round().round).collect();
            let mut k = 0;
            g.bench_function(BenchmarkId::new(method.name(), bank), |b| {
                b.iter(|| {
                    k = (k + 1) % rounds.len();
                    black_box(engine.infer(&rounds[k]))
                })
            });
        }
    }
    g.finish();
}

fn fuse_feedback(c: &mut Criterion) {
    let mut g = c.benchmark_group("fuse_feedback");
    g.sample_size(30);
    for bank in BANKS {
        for method in METHODS {
            let mut synth = Synth::new(42, DIM, REPORTERS, Ontology::paper().len());
            let mut engine = filled_engine(method, bank, REPORTERS, &mut synth).expect("engine");
            let mut seq = bank as u64;
            g.bench_function(BenchmarkId::new(method.name(), bank), |b| {
                b.iter_batched(
                    || synth.round(),
                    |s| {
                        seq += 1;
                        fuse_feedback_round(&mut engine, s, seq).expect("round")
                    },
                    BatchSize::SmallInput,
                )
            });
        }
    }
    g.finish();
}

fn similarities(c: &mut Criterion) {
    let mut g = c.benchmark_group("similarities");
    let (q, bank) = (64, 10_000);
    let (queries, keys) = similarity_inputs(q, bank, DIM, 7);
    let mut out = vec![0.0; q * bank];
    g.bench_function("per_query", |b| {
        b.iter(|| black_box(similarities_per_query(&queries, &keys, DIM)))
    });
    g.bench_function("gemm", |b| {
        b.iter(|| {
            similarities_gemm(&queries, &keys, DIM, &mut out);
            black_box(out[0])
        })
    });
    g.finish();
}

fn replay_rounds(c: &mut Criterion) {
    let mut g = c.benchmark_group("replay");
    g.sample_size(10).measurement_time(Duration::from_secs(20));
    let records = synthetic_records(2_000, DIM, REPORTERS, 11);
    let (engine, rounds) =
        prepare(&FusionConfig::default(), &Ontology::paper(), &records).expect("records");
    for (name, batch_knn) in [("per_query_knn", false), ("batched_knn", true)] {
        let opts = ReplayOptions {
            split: 0.7,
            frozen: false,
            batch_knn,
        };
        g.bench_function(name, |b| {
            b.iter_batched(
                || engine.clone(),
                |e| replay(e, &rounds, &opts, &mut |_| {}).expect("replay"),
                BatchSize::LargeInput,
            )
        });
    }
    g.finish();
}

criterion_group!(benches, infer, fuse_feedback, similarities, replay_rounds);
criterion_main!(benches);
