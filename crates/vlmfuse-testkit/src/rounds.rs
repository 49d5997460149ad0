//! docs/PAPER-METHOD.md §8 rounds for tests: a generator with learnable structure, and JSON Lines files.

use crate::rng::Lcg;
use serde_json::Value;
use std::io::Write;
use std::path::Path;

pub use vlmfuse_core::PAPER_LABELS as LABELS;

pub const REPORTERS: [&str; 3] = ["vlaad", "videollama2", "videollava"];

/// A docs/PAPER-METHOD.md §8 rounds stream with structure the method can learn: contexts cluster around a few
/// scene centres, each scene has typical labels, and each reporter is reliable in some scenes
/// and noisy in others. About 1 round in 8 is unlabelled and 1 in 10 misses a reporter.
pub fn generate_rounds(n: usize, d: usize, seed: u64) -> Vec<Value> {
    let mut g = Lcg(seed);
    let mut next = move || g.f();
    let scenes = 5;
    let centres: Vec<Vec<f64>> = (0..scenes)
        .map(|_| (0..d).map(|_| next() - 0.5).collect())
        .collect();
    let typical: Vec<Vec<usize>> = (0..scenes)
        .map(|c| vec![(2 * c) % 14, (3 * c + 1) % 14, (5 * c + 4) % 14])
        .collect();
    (0..n)
        .map(|i| {
            let c = (next() * scenes as f64) as usize % scenes;
            let context: Vec<f64> = centres[c]
                .iter()
                .map(|v| v + 0.3 * (next() - 0.5))
                .collect();
            let truth: Vec<&str> = typical[c]
                .iter()
                .filter(|_| next() < 0.6)
                .map(|&k| LABELS[k])
                .collect();
            let mut reports = serde_json::Map::new();
            for (r, name) in REPORTERS.iter().enumerate() {
                if next() < 0.1 {
                    continue;
                }
                let noise = if (r + c).is_multiple_of(3) { 0.4 } else { 0.08 };
                let mut labs: Vec<&str> = Vec::new();
                for (k, lab) in LABELS.iter().enumerate() {
                    let on = truth.contains(lab);
                    let flip = next() < if on { noise } else { noise / 4.0 };
                    if on != flip {
                        labs.push(LABELS[k]);
                    }
                }
                reports.insert((*name).into(), labs.into());
            }
            if reports.is_empty() {
                reports.insert("vlaad".into(), Value::Array(vec![]));
            }
            let mut v = serde_json::json!({
                "id": format!("g-{i:05}"),
                "context": context,
                "reports": reports,
            });
            if next() >= 0.125 {
                v["truth"] = truth.into();
            }
            v
        })
        .collect()
}

/// The reporters of a rounds list, sorted, as `eval` orders them.
pub fn sorted_reporters(rounds: &[Value]) -> Vec<String> {
    let mut names: Vec<String> = rounds
        .iter()
        .flat_map(|r| r["reports"].as_object().unwrap().keys().cloned())
        .collect();
    names.sort();
    names.dedup();
    names
}

pub fn write_jsonl(path: &Path, rounds: &[Value]) {
    let mut f = std::fs::File::create(path).unwrap();
    for r in rounds {
        writeln!(f, "{}", serde_json::to_string(r).unwrap()).unwrap();
    }
}

pub fn read_jsonl(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}
