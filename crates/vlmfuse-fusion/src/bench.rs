//! Synthetic workloads and timed loops for the engine's benchmarks: `vlmfuse bench` (which
//! prints the tables) and the criterion benches in `benches/`. Nothing here prints or touches a
//! file; the timings come back as values.
//!
//! The workload: rounds whose contexts cluster around 12 scene centres on the unit sphere, with
//! scene-dependent label rates and reporters that flip each label with a probability growing
//! with their index (8 %, 15 %, 22 %, ...). Seeded, so every run measures the same rounds.

use crate::replay::{prepare, replay, ReplayOptions};
use crate::{
    Engine, FeedbackOutcome, FusionConfig, FusionError, Inference, LabelledRound, Method, Ontology,
    Round, RoundRecord,
};
use faer::{Accum, MatMut, MatRef, Par};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// One synthetic round: the round itself and its true label bits.
#[derive(Debug, Clone)]
pub struct SynthRound {
    pub round: Round,
    pub truth: Vec<u8>,
}

/// The seeded generator of clustered rounds (see the module docs).
pub struct Synth {
    rng: ChaCha8Rng,
    centres: Vec<Vec<f64>>,
    /// Per centre, the directions its scenes vary along ([`Synth::scenes`]); empty: isotropic
    /// noise only.
    factors: Vec<Vec<Vec<f64>>>,
    reporters: usize,
    labels: usize,
}

/// Directions of variation per scene type in [`Synth::scenes`].
pub const SCENE_FACTORS: usize = 8;

impl Synth {
    /// Rounds of context dimension `dim`, `reporters` reporters (all present) and `labels` labels.
    pub fn new(seed: u64, dim: usize, reporters: usize, labels: usize) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let centres = (0..12)
            .map(|_| (0..dim).map(|_| rng.random::<f64>() - 0.5).collect())
            .collect();
        Self {
            rng,
            centres,
            factors: Vec::new(),
            reporters,
            labels,
        }
    }

    /// Like [`Synth::new`], but contexts as image embeddings are: each of the twelve scene
    /// types varies along [`SCENE_FACTORS`] directions of its own (light, traffic, road, ...),
    /// with a little isotropic noise on top, so that a round's nearest neighbours are the rounds
    /// of similar scenes. `new`'s contexts are a centre plus noise in every one of the `dim`
    /// directions: there the exact neighbours are decided by noise, and no index can find them
    /// without reading most of a cluster.
    pub fn scenes(seed: u64, dim: usize, reporters: usize, labels: usize) -> Self {
        let mut s = Self::new(seed, dim, reporters, labels);
        s.factors = (0..s.centres.len())
            .map(|_| {
                (0..SCENE_FACTORS)
                    .map(|_| (0..dim).map(|_| s.rng.random::<f64>() - 0.5).collect())
                    .collect()
            })
            .collect();
        s
    }

    /// The same scene types (centres and factors), another stream of rounds.
    pub fn reseeded(&self, seed: u64) -> Self {
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
            centres: self.centres.clone(),
            factors: self.factors.clone(),
            reporters: self.reporters,
            labels: self.labels,
        }
    }

    pub fn round(&mut self) -> SynthRound {
        let c = self.rng.random_range(0..self.centres.len());
        let noise = if self.factors.is_empty() { 0.4 } else { 0.05 };
        let mut x: Vec<f64> = self.centres[c]
            .iter()
            .map(|v| v + noise * (self.rng.random::<f64>() - 0.5))
            .collect();
        if let Some(fs) = self.factors.get(c) {
            for f in fs {
                let z = 0.6 * (self.rng.random::<f64>() - 0.5);
                for (d, v) in x.iter_mut().zip(f) {
                    *d += z * v;
                }
            }
        }
        let norm = x.iter().map(|v| v * v).sum::<f64>().sqrt();
        let context = x.iter().map(|v| v / norm).collect();
        let truth: Vec<u8> = (0..self.labels)
            .map(|k| {
                let rate = if (c + k).is_multiple_of(5) { 0.4 } else { 0.1 };
                u8::from(self.rng.random::<f64>() < rate)
            })
            .collect();
        let mut reports = vec![0u8; self.reporters * self.labels];
        for i in 0..self.reporters {
            for k in 0..self.labels {
                let flip = self.rng.random::<f64>() < 0.08 + 0.07 * i as f64;
                reports[i * self.labels + k] = truth[k] ^ u8::from(flip);
            }
        }
        SynthRound {
            round: Round {
                context,
                present: vec![true; self.reporters],
                reports,
            },
            truth,
        }
    }
}

/// The reporter names the synthetic rounds use: `m0`, `m1`, ...
pub fn reporter_names(n: usize) -> Vec<String> {
    (0..n).map(|i| format!("m{i}")).collect()
}

/// `n_rounds` synthetic rounds as rounds-file records (line numbers from 1), all labelled, over
/// the paper's ontology.
pub fn synthetic_records(
    n_rounds: usize,
    dim: usize,
    reporters: usize,
    seed: u64,
) -> Vec<(usize, RoundRecord)> {
    let ontology = Ontology::paper();
    let l = ontology.len();
    let names = reporter_names(reporters);
    let mut synth = Synth::new(seed, dim, reporters, l);
    (0..n_rounds)
        .map(|t| {
            let s = synth.round();
            let reports: BTreeMap<String, Vec<String>> = names
                .iter()
                .enumerate()
                .map(|(i, name)| {
                    let bits = &s.round.reports[i * l..(i + 1) * l];
                    (name.clone(), ontology.decode(bits))
                })
                .collect();
            (
                t + 1,
                RoundRecord {
                    id: Some(format!("r{t}")),
                    context: s.round.context,
                    reports,
                    truth: Some(ontology.decode(&s.truth)),
                },
            )
        })
        .collect()
}

/// An engine of `method` over the paper's ontology and `reporters` reporters whose bank holds
/// `bank` labelled rounds from `synth` (applied without credit, as a fast way to fill it).
pub fn filled_engine(
    method: Method,
    bank: usize,
    reporters: usize,
    synth: &mut Synth,
) -> Result<Engine, FusionError> {
    let cfg = FusionConfig {
        method,
        ..FusionConfig::default()
    };
    let mut engine = Engine::new(cfg, Ontology::paper(), reporter_names(reporters))?;
    for s in 0..bank {
        let SynthRound { round, truth } = synth.round();
        let lr = LabelledRound {
            seq: s as u64,
            round,
            q: truth.iter().map(|&v| 0.3 + 0.4 * f64::from(v)).collect(),
            truth,
        };
        engine.apply(&lr, None)?;
    }
    Ok(engine)
}

/// How long each step of one fuse-then-feedback round took.
#[derive(Debug, Clone, Copy, Default)]
pub struct RoundTimes {
    pub infer: Duration,
    pub observe: Duration,
    pub credit: Duration,
    pub apply: Duration,
}

impl RoundTimes {
    pub fn total(&self) -> Duration {
        self.infer + self.observe + self.credit + self.apply
    }
}

/// One live round as the service runs it: infer, observe (the round joins the pool at fuse time;
/// a no-op under `paper`), credit against its truth, apply.
pub fn fuse_feedback_round(
    engine: &mut Engine,
    s: SynthRound,
    seq: u64,
) -> Result<RoundTimes, FusionError> {
    let t0 = Instant::now();
    let inf: Inference = engine.infer(&s.round);
    let t1 = Instant::now();
    engine.observe(seq, &s.round, &inf)?;
    let t2 = Instant::now();
    let outcome: FeedbackOutcome = engine.credit(&inf.signals, &inf.w_used, &s.truth, seq);
    let t3 = Instant::now();
    let lr = LabelledRound {
        seq,
        round: s.round,
        truth: s.truth,
        q: inf.q,
    };
    engine.apply(&lr, Some(&outcome))?;
    let t4 = Instant::now();
    Ok(RoundTimes {
        infer: t1 - t0,
        observe: t2 - t1,
        credit: t3 - t2,
        apply: t4 - t3,
    })
}

/// What [`fuse_feedback`] measured.
#[derive(Debug, Clone)]
pub struct FuseFeedbackTimes {
    /// Per live round, fuse-then-feedback in microseconds, sorted ascending.
    pub latencies_us: Vec<f64>,
    /// Mean of each step over the live rounds.
    pub mean_parts: RoundTimes,
    /// Mean time of an exact top-50 scan of the bank, in microseconds.
    pub top50_us: f64,
    /// Seconds it took to fill the bank.
    pub fill_s: f64,
    /// Per unlabelled round (infer, then observe: the round is stored and never labelled), in
    /// microseconds, sorted ascending; timed after the labelled rounds, on the same engine.
    pub unlabelled_us: Vec<f64>,
}

impl FuseFeedbackTimes {
    pub fn mean_us(&self) -> f64 {
        self.latencies_us.iter().sum::<f64>() / self.latencies_us.len().max(1) as f64
    }

    /// The `p`-quantile (0..=1) of the latencies, nearest rank.
    pub fn percentile_us(&self, p: f64) -> f64 {
        percentile(&self.latencies_us, p)
    }

    pub fn unlabelled_mean_us(&self) -> f64 {
        self.unlabelled_us.iter().sum::<f64>() / self.unlabelled_us.len().max(1) as f64
    }
}

/// The nearest-rank `p`-quantile of an ascending slice (NaN when empty).
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() as f64 * p).ceil() as usize).clamp(1, sorted.len()) - 1]
}

/// `rounds` live fuse-then-feedback rounds under `method` after a bank of `bank` labelled
/// rounds, context dimension `dim`, `reporters` reporters.
pub fn fuse_feedback(
    method: Method,
    bank: usize,
    dim: usize,
    reporters: usize,
    rounds: usize,
) -> Result<FuseFeedbackTimes, FusionError> {
    let mut synth = Synth::new(42, dim, reporters, Ontology::paper().len());
    let fill = Instant::now();
    let mut engine = filled_engine(method, bank, reporters, &mut synth)?;
    let fill_s = fill.elapsed().as_secs_f64();
    let mut lat = Vec::with_capacity(rounds);
    let mut parts = RoundTimes::default();
    let mut scan = Duration::ZERO;
    for t in 0..rounds {
        let s = synth.round();
        let s0 = Instant::now();
        std::hint::black_box(engine.bank().top_exact(&s.round.context, 50));
        scan += s0.elapsed();
        let times = fuse_feedback_round(&mut engine, s, (bank + t) as u64)?;
        lat.push(times.total().as_secs_f64() * 1e6);
        parts.infer += times.infer;
        parts.observe += times.observe;
        parts.credit += times.credit;
        parts.apply += times.apply;
    }
    lat.sort_by(f64::total_cmp);
    // Rounds that are never labelled: under `paper` an inference against the bank; under
    // `adaptive` the inference, then the round joins the pool and the EM chunk runs.
    let mut unlabelled_us = Vec::with_capacity(rounds);
    for t in 0..rounds {
        let s = synth.round();
        let t0 = Instant::now();
        let inf = engine.infer(&s.round);
        engine.observe((bank + rounds + t) as u64, &s.round, &inf)?;
        unlabelled_us.push(t0.elapsed().as_secs_f64() * 1e6);
    }
    unlabelled_us.sort_by(f64::total_cmp);
    let n = rounds.max(1) as u32;
    Ok(FuseFeedbackTimes {
        latencies_us: lat,
        mean_parts: RoundTimes {
            infer: parts.infer / n,
            observe: parts.observe / n,
            credit: parts.credit / n,
            apply: parts.apply / n,
        },
        top50_us: scan.as_secs_f64() / f64::from(n) * 1e6,
        fill_s,
        unlabelled_us,
    })
}

/// What [`fuse_feedback_paired`] measured: per phase, the two methods' mean cost per round and
/// the median over blocks of the ratio `adaptive / paper`.
#[derive(Debug, Clone, Copy)]
pub struct PairedTimes {
    pub blocks: usize,
    pub paper_labelled_us: f64,
    pub adaptive_labelled_us: f64,
    pub labelled_ratio: f64,
    pub paper_unlabelled_us: f64,
    pub adaptive_unlabelled_us: f64,
    pub unlabelled_ratio: f64,
}

/// [`fuse_feedback`]'s workload under both methods at once: two engines filled from the same
/// rounds, then the same live rounds in blocks of `block`, each block run by `paper` and then by
/// `adaptive` (labelled rounds first, then as many unlabelled ones). Each block gives one ratio
/// of the two times; their median is the figure. A machine that slows down for a second or two
/// (a shared host) inflates one method's whole run in [`fuse_feedback`], but only a block or
/// two here, and the median ignores them.
pub fn fuse_feedback_paired(
    bank: usize,
    dim: usize,
    reporters: usize,
    rounds: usize,
    block: usize,
) -> Result<PairedTimes, FusionError> {
    let block = block.max(1);
    let l = Ontology::paper().len();
    let synth = Synth::new(42, dim, reporters, l);
    let mut engines = [
        filled_engine(Method::Paper, bank, reporters, &mut synth.reseeded(42))?,
        filled_engine(Method::Adaptive, bank, reporters, &mut synth.reseeded(42))?,
    ];
    // The live rounds, drawn once: both engines see the same ones, in the same order.
    let mut live = synth.reseeded(7);
    let labelled: Vec<SynthRound> = (0..rounds).map(|_| live.round()).collect();
    let unlabelled: Vec<SynthRound> = (0..rounds).map(|_| live.round()).collect();
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
    };
    let mut sums = [[0.0f64; 2]; 2];
    let mut ratios = [Vec::new(), Vec::new()];
    for (phase, set) in [&labelled, &unlabelled].into_iter().enumerate() {
        for (b, chunk) in set.chunks(block).enumerate() {
            let mut t = [0.0f64; 2];
            for (m, engine) in engines.iter_mut().enumerate() {
                let start = Instant::now();
                for (i, s) in chunk.iter().enumerate() {
                    let seq = (bank + phase * rounds + b * block + i) as u64;
                    if phase == 0 {
                        fuse_feedback_round(engine, s.clone(), seq)?;
                    } else {
                        let inf = engine.infer(&s.round);
                        engine.observe(seq, &s.round, &inf)?;
                    }
                }
                t[m] = start.elapsed().as_secs_f64();
                sums[phase][m] += t[m];
            }
            ratios[phase].push(t[1] / t[0]);
        }
    }
    let per = |v: f64| v / rounds.max(1) as f64 * 1e6;
    Ok(PairedTimes {
        blocks: ratios[0].len(),
        paper_labelled_us: per(sums[0][0]),
        adaptive_labelled_us: per(sums[0][1]),
        labelled_ratio: median(&mut ratios[0]),
        paper_unlabelled_us: per(sums[1][0]),
        adaptive_unlabelled_us: per(sums[1][1]),
        unlabelled_ratio: median(&mut ratios[1]),
    })
}

/// Random keys and queries for the similarity benchmark: `(queries q x d, keys b x d)`, row-major.
pub fn similarity_inputs(q: usize, b: usize, d: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let keys = (0..b * d).map(|_| rng.random::<f64>() - 0.5).collect();
    let queries = (0..q * d).map(|_| rng.random::<f64>() - 0.5).collect();
    (queries, keys)
}

/// Every query against every key by one dot product each; returns the sum (to keep it alive).
pub fn similarities_per_query(queries: &[f64], keys: &[f64], d: usize) -> f64 {
    let mut acc = 0.0;
    for x in queries.chunks_exact(d) {
        for c in keys.chunks_exact(d) {
            acc += crate::bank::dot(x, c);
        }
    }
    acc
}

/// Every query against every key in one GEMM into `out` (q x b, row-major).
pub fn similarities_gemm(queries: &[f64], keys: &[f64], d: usize, out: &mut [f64]) {
    let (q, b) = (queries.len() / d, keys.len() / d);
    faer::linalg::matmul::matmul(
        MatMut::from_row_major_slice_mut(out, q, b),
        Accum::Replace,
        MatRef::from_row_major_slice(queries, q, d),
        MatRef::from_row_major_slice(keys, b, d).transpose(),
        1.0,
        Par::Seq,
    );
}

/// What [`knn`] measured, in seconds.
#[derive(Debug, Clone, Copy)]
pub struct KnnTimes {
    pub queries: usize,
    pub bank: usize,
    pub dim: usize,
    /// `queries x bank` similarities by per-query dot products.
    pub per_query_s: f64,
    /// The same in one GEMM.
    pub gemm_s: f64,
    /// Rounds of the replay below.
    pub replay_rounds: usize,
    /// A whole replay with per-query kNN.
    pub replay_per_query_s: f64,
    /// The same replay with batched (GEMM) kNN.
    pub replay_batched_s: f64,
}

/// Raw similarity work (256 queries against a 10k bank, per-query dots against one GEMM), then
/// the same choice inside a whole replay of 2,000 synthetic rounds.
pub fn knn(dim: usize, reporters: usize) -> Result<KnnTimes, FusionError> {
    let (q, b) = (256usize, 10_000usize);
    let (queries, keys) = similarity_inputs(q, b, dim, 7);
    let start = Instant::now();
    std::hint::black_box(similarities_per_query(&queries, &keys, dim));
    let per_query_s = start.elapsed().as_secs_f64();
    let mut out = vec![0.0; q * b];
    let start = Instant::now();
    similarities_gemm(&queries, &keys, dim, &mut out);
    std::hint::black_box(&out);
    let gemm_s = start.elapsed().as_secs_f64();

    let replay_rounds = 2000;
    let records = synthetic_records(replay_rounds, dim, reporters, 11);
    let (engine, rounds) = prepare(&FusionConfig::default(), &Ontology::paper(), &records)
        .map_err(|e| FusionError::Config(e.to_string()))?;
    let mut times = [0.0; 2];
    for (slot, batch) in times.iter_mut().zip([false, true]) {
        let opts = ReplayOptions {
            split: 0.7,
            frozen: false,
            batch_knn: batch,
        };
        let start = Instant::now();
        let (_, outs) = replay(engine.clone(), &rounds, &opts, &mut |_| {})
            .map_err(|e| FusionError::Config(e.to_string()))?;
        std::hint::black_box(outs);
        *slot = start.elapsed().as_secs_f64();
    }
    Ok(KnnTimes {
        queries: q,
        bank: b,
        dim,
        per_query_s,
        gemm_s,
        replay_rounds,
        replay_per_query_s: times[0],
        replay_batched_s: times[1],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_workloads_run_and_time_every_round() {
        for method in [Method::Paper, Method::Adaptive] {
            let t = fuse_feedback(method, 50, 8, 3, 10).unwrap();
            assert_eq!(t.latencies_us.len(), 10);
            assert!(t.latencies_us.windows(2).all(|w| w[0] <= w[1]));
            assert!(t.mean_us() > 0.0 && t.percentile_us(0.95) >= t.percentile_us(0.5));
        }
        let records = synthetic_records(30, 8, 4, 1);
        assert_eq!(records.len(), 30);
        assert_eq!(records[0].0, 1);
        assert_eq!(records[0].1.reports.len(), 4);
        assert_eq!(records, synthetic_records(30, 8, 4, 1), "seeded");
        let (q, k) = similarity_inputs(3, 5, 4, 2);
        let mut out = vec![0.0; 15];
        similarities_gemm(&q, &k, 4, &mut out);
        let sum: f64 = out.iter().sum();
        assert!((sum - similarities_per_query(&q, &k, 4)).abs() < 1e-12);
        assert!(percentile(&[], 0.5).is_nan());
        let p = fuse_feedback_paired(40, 8, 3, 12, 5).unwrap();
        assert_eq!(p.blocks, 3);
        assert!(p.labelled_ratio > 0.0 && p.unlabelled_ratio > 0.0);
        assert!(p.paper_labelled_us > 0.0 && p.adaptive_unlabelled_us > 0.0);
    }
}
