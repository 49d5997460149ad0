//! The label stage's cost for one round: three reporters' answers labelled together.
//!
//! ```text
//! CARGO_TARGET_DIR=/work/target-release cargo build --release -p vlmfuse-labeler --example label_bench
//! /work/target-release/release/examples/label_bench [ROUNDS]
//! ```
//! Rounds are three answers drawn (fixed seed) from the TRAIN split, so they look like what VLMs
//! write. Reported, in one run: the batched call the service makes (one encoder pass), the same
//! answers labelled one call each, the rules alone, and one encoder pass over every item of the
//! three answers (what embedding every clause, as the previous matcher did, costs).

use std::time::Instant;
use vlmfuse_labeler::{
    rules, text, BlockingLabeler, CandleEncoder, EmbeddingConfig, EmbeddingLabeler, Ontology,
    SentenceEncoder,
};
use vlmfuse_testkit::assets::ensure_assets;
use vlmfuse_testkit::labeler_eval::{default_dataset_path, load_dataset};

fn pct(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let rounds: usize = std::env::args()
        .nth(1)
        .map_or(200, |v| v.parse().expect("ROUNDS is a number"));
    let a = ensure_assets().expect("assets (scripts/fetch-assets.sh)");
    let data = load_dataset(&default_dataset_path()).unwrap();
    let train: Vec<&str> = data
        .iter()
        .filter(|e| e.split == "train")
        .map(|e| e.text.as_str())
        .collect();
    let lab = EmbeddingLabeler::load(
        Ontology::default_driving(),
        EmbeddingConfig::new(&a.minilm_dir),
    )
    .unwrap();
    let enc = CandleEncoder::load(&a.minilm_dir).unwrap();
    let mut seed = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed % train.len() as u64) as usize
    };
    let sets: Vec<[&str; 3]> = (0..rounds)
        .map(|_| [train[next()], train[next()], train[next()]])
        .collect();
    // Warm-up.
    for s in sets.iter().take(5) {
        lab.label_batch_blocking(s).unwrap();
    }
    let (mut batched, mut separate, mut rules_only, mut all_items) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut words = 0usize;
    let (mut n_items, mut unexplained) = (0usize, 0usize);
    for s in &sets {
        words += s
            .iter()
            .map(|t| t.split_whitespace().count())
            .sum::<usize>();
        let t0 = Instant::now();
        lab.label_batch_blocking(s).unwrap();
        batched.push(t0.elapsed().as_secs_f64() * 1e3);
        let t0 = Instant::now();
        for t in s {
            lab.label_blocking(t).unwrap();
        }
        separate.push(t0.elapsed().as_secs_f64() * 1e3);
        let t0 = Instant::now();
        let mut items = Vec::new();
        for t in s {
            let sn = text::sentences(t);
            let m = rules::mentions(&sn);
            rules::decide(&sn, &m);
            for (si, x) in sn.iter().enumerate() {
                for (a, b) in rules::items(x) {
                    if b - a >= 2 && !m.iter().any(|y| y.sentence == si && y.a < b && a < y.b) {
                        unexplained += 1;
                    }
                    items.push((a..b).map(|k| x.w(k)).collect::<Vec<_>>().join(" "));
                }
            }
        }
        n_items += items.len();
        rules_only.push(t0.elapsed().as_secs_f64() * 1e3);
        let refs: Vec<&str> = items.iter().map(String::as_str).collect();
        let t0 = Instant::now();
        enc.encode(&refs).unwrap();
        all_items.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    println!(
        "{rounds} rounds of 3 answers ({:.0} words per round), candle encoder, {} threads",
        words as f64 / rounds as f64,
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    println!(
        "  items per round: {:.1}, of which {:.1} have no rule mention",
        n_items as f64 / rounds as f64,
        unexplained as f64 / rounds as f64
    );
    for (name, v) in [
        ("label_batch (the service's call)", &mut batched),
        ("3 separate label calls", &mut separate),
        ("rules alone (no encoder)", &mut rules_only),
        ("encoder pass over every item", &mut all_items),
    ] {
        let (p50, p95) = (pct(v, 0.5), pct(v, 0.95));
        println!("  {name:<36} median {p50:>7.2} ms   p95 {p95:>7.2} ms");
    }
}
