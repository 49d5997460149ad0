//! The label stage's cost per round, on the held-out test split: each round is
//! `ROUND_ANSWERS` (5) consecutive test answers labelled in one `label_batch` call, as
//! `/v1/infer` labels a round, with the candle and the ONNX Runtime encoder under the same
//! matcher, interleaved round by round so that both see the same machine load.
//!
//! ```text
//! cargo build --release -p vlmfuse-labeler --example label_bench
//! ${CARGO_TARGET_DIR:-target}/release/examples/label_bench [--passes N] [--threads N]
//! ```
//! Reported, in one run: per engine the median and p95 of the batched call (and its CPU time,
//! all threads, which a loaded machine inflates less than wall time), and the same
//! answers labelled one call each; the rules alone (reading and rules, no encoder); and how many
//! items per round reach the encoder (advice items no rule explained) against all items (what
//! embedding every clause, as the previous matcher did, would cost).

use std::sync::Arc;
use std::time::Instant;
use vlmfuse_labeler::{
    rules, text, BlockingLabeler, EmbeddingConfig, EmbeddingLabeler, OnnxEncoderConfig,
    OnnxSentenceEncoder, Ontology,
};
use vlmfuse_ort::SessionOptions;
use vlmfuse_testkit_models::assets::require_assets;
use vlmfuse_testkit_models::labeler_eval::{
    default_dataset_path, eval_embedding_labeler, load_dataset, test_split, ROUND_ANSWERS,
};

fn arg(name: &str, default: usize) -> usize {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map_or(default, |v| {
            v.parse()
                .unwrap_or_else(|_| panic!("{name} takes a number"))
        })
}

fn pct(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn ms(t0: Instant) -> f64 {
    t0.elapsed().as_secs_f64() * 1e3
}

/// CPU time of the whole process (every thread, the ONNX pool's included), ms: the work a call
/// did, which other processes on a shared machine inflate far less than its wall time.
fn cpu_ms() -> f64 {
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage only writes into the struct we own.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| t.tv_sec as f64 * 1e3 + t.tv_usec as f64 / 1e3;
    tv(u.ru_utime) + tv(u.ru_stime)
}

/// The 1-minute load average: on a shared machine, what the timings must be read against.
fn load() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().map(str::to_string))
        .unwrap_or_else(|| "?".into())
}

fn main() {
    let load_before = load();
    let passes = arg("--passes", 3);
    let threads = arg(
        "--threads",
        std::thread::available_parallelism().map_or(1, |n| n.get()),
    );
    let a = require_assets();
    let data = load_dataset(&default_dataset_path()).expect("labeler data set");
    let test: Vec<&str> = test_split(&data).iter().map(|e| e.text.as_str()).collect();
    let rounds: Vec<&[&str]> = test.chunks(ROUND_ANSWERS).collect();

    let candle = eval_embedding_labeler(&a).expect("candle labeler");
    let onnx = EmbeddingLabeler::with_encoder(
        Ontology::default_driving(),
        EmbeddingConfig::new(&a.minilm_dir),
        Arc::new(
            OnnxSentenceEncoder::load(&OnnxEncoderConfig {
                session: SessionOptions {
                    threads: Some(threads),
                    library: Some(a.onnxruntime.clone()),
                },
                ..OnnxEncoderConfig::new(&a.minilm_onnx_dir)
            })
            .expect("onnx encoder"),
        ),
    )
    .expect("onnx labeler");
    let engines: [(&str, &EmbeddingLabeler); 2] = [("candle", &candle), ("onnx", &onnx)];

    // Warm-up: every engine labels a few rounds first.
    for (_, l) in &engines {
        for r in rounds.iter().take(3) {
            l.label_batch_blocking(r).unwrap();
        }
    }
    let mut batched = vec![Vec::new(); engines.len()];
    let mut batched_cpu = vec![Vec::new(); engines.len()];
    let mut separate = vec![Vec::new(); engines.len()];
    let mut rules_only = Vec::new();
    let (mut items, mut encoded, mut words) = (0usize, 0usize, 0usize);
    for pass in 0..passes {
        for r in &rounds {
            for (e, (_, l)) in engines.iter().enumerate() {
                let (t0, c0) = (Instant::now(), cpu_ms());
                l.label_batch_blocking(r).unwrap();
                batched[e].push(ms(t0));
                batched_cpu[e].push(cpu_ms() - c0);
                let t0 = Instant::now();
                for t in r.iter() {
                    l.label_blocking(t).unwrap();
                }
                separate[e].push(ms(t0));
            }
            let t0 = Instant::now();
            let mut n_items = 0;
            let mut n_encoded = 0;
            for t in r.iter() {
                let sn = text::sentences(t);
                let m = rules::mentions(&sn);
                rules::decide(&sn, &m);
                for (si, x) in sn.iter().enumerate() {
                    for (a, b) in rules::items(x) {
                        n_items += 1;
                        let explained = m.iter().any(|y| y.sentence == si && y.a < b && a < y.b);
                        let (_, hedged, other) = rules::item_polarity(x, a, b);
                        if b - a >= 2
                            && !explained
                            && rules::advice_item(x, a, b)
                            && !hedged
                            && !other
                        {
                            n_encoded += 1;
                        }
                    }
                }
            }
            rules_only.push(ms(t0));
            if pass == 0 {
                items += n_items;
                encoded += n_encoded;
                words += r
                    .iter()
                    .map(|t| t.split_whitespace().count())
                    .sum::<usize>();
            }
        }
    }
    let n = rounds.len() as f64;
    println!(
        "{} rounds of {ROUND_ANSWERS} test answers ({:.0} words per round) x {passes} passes, \
         onnx on {threads} threads, {} cores, load average {load_before} -> {}",
        rounds.len(),
        words as f64 / n,
        std::thread::available_parallelism().map_or(1, |n| n.get()),
        load()
    );
    println!(
        "  items per round: {:.1}, of which {:.1} reach the encoder (advice no rule explained)",
        items as f64 / n,
        encoded as f64 / n
    );
    let mut medians = Vec::new();
    for (e, (name, _)) in engines.iter().enumerate() {
        let (p50, p95) = (pct(&mut batched[e], 0.5), pct(&mut batched[e], 0.95));
        medians.push(p50);
        let cpu = pct(&mut batched_cpu[e], 0.5);
        println!("  {name:<6} label_batch (the service's call)   median {p50:>6.2} ms   p95 {p95:>6.2} ms   (CPU median {cpu:>6.2} ms)");
        let (p50, p95) = (pct(&mut separate[e], 0.5), pct(&mut separate[e], 0.95));
        println!("  {name:<6} {ROUND_ANSWERS} separate label calls         median {p50:>6.2} ms   p95 {p95:>6.2} ms");
    }
    let (p50, p95) = (pct(&mut rules_only, 0.5), pct(&mut rules_only, 0.95));
    println!("  rules alone (no encoder)             median {p50:>6.2} ms   p95 {p95:>6.2} ms");
    println!(
        "  candle / onnx (batched medians): {:.2}x; target <= 30 ms per round: candle {}, onnx {}",
        medians[0] / medians[1],
        if medians[0] <= 30.0 { "met" } else { "MISSED" },
        if medians[1] <= 30.0 { "met" } else { "MISSED" },
    );
}
