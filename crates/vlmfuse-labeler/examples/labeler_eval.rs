//! Evaluates the local labelers on the test split of `tests/data/labeler/answers.jsonl`.
//!
//! ```text
//! cargo run -p vlmfuse-labeler --example labeler_eval --release -- [--tune] [--only embedding|gguf]
//!     [--gguf-train N] [--gguf-test N]
//! ```
//! `--tune` fits thresholds (and the embedding clause margin) on the training split and prints
//! them as the constants to paste into the source; without it the built-in defaults are scored.
//! The remote (OpenAI-compatible) labeler is not evaluated: there is no real server here.

use std::time::Instant;
use vlmfuse_labeler::{
    BlockingLabeler, EmbeddingConfig, EmbeddingLabeler, GgufConfig, GgufLabeler, Ontology,
};
use vlmfuse_testkit::assets::{ensure_assets, AssetsUnavailable};
use vlmfuse_testkit::labeler_eval::{
    default_dataset_path, f1_scores, load_dataset, to_mask, tune_thresholds, Example,
};

fn arg_value(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

fn grid(lo: f32, hi: f32, step: f32) -> Vec<f32> {
    let n = ((hi - lo) / step).round() as usize;
    (0..=n).map(|i| lo + i as f32 * step).collect()
}

fn apply(scores: &[Vec<f32>], th: &[f32]) -> Vec<Vec<bool>> {
    scores
        .iter()
        .map(|r| r.iter().zip(th).map(|(s, t)| s >= t).collect())
        .collect()
}

fn per_label(ontology: &Ontology, truth: &[Vec<bool>], pred: &[Vec<bool>]) {
    for (k, l) in ontology.labels().iter().enumerate() {
        let col = |m: &[Vec<bool>]| m.iter().map(|r| vec![r[k]]).collect::<Vec<_>>();
        let pos = truth.iter().filter(|r| r[k]).count();
        println!(
            "  {:<28} F1 {:.3} ({pos} positives)",
            l.id,
            f1_scores(&col(truth), &col(pred)).micro
        );
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let tune = args.iter().any(|a| a == "--tune");
    let only = arg_value(&args, "--only");
    let gguf_train: usize = arg_value(&args, "--gguf-train").map_or(60, |v| v.parse().unwrap());
    let gguf_test: usize =
        arg_value(&args, "--gguf-test").map_or(usize::MAX, |v| v.parse().unwrap());

    let assets = match ensure_assets() {
        Ok(a) => a,
        Err(AssetsUnavailable::RegistryUnreachable(r)) => {
            eprintln!("skipping evaluation: assets cannot be fetched: {r}");
            return Ok(());
        }
        Err(e) => anyhow::bail!("{e}"),
    };
    let ontology = Ontology::default_driving();
    let data = load_dataset(&default_dataset_path())?;
    let (train, test): (Vec<_>, Vec<_>) = data.iter().partition(|e| e.split == "train");
    let truth = |xs: &[&Example]| -> anyhow::Result<Vec<Vec<bool>>> {
        Ok(xs
            .iter()
            .map(|e| to_mask(&ontology, &e.labels))
            .collect::<Result<_, _>>()?)
    };
    let (train_y, test_y) = (truth(&train)?, truth(&test)?);
    println!(
        "data set: {} train / {} test answers, {} labels",
        train.len(),
        test.len(),
        ontology.len()
    );
    let mut table = Vec::new();

    if only.as_deref().is_none_or(|o| o == "embedding") {
        let t0 = Instant::now();
        let lab =
            EmbeddingLabeler::load(ontology.clone(), EmbeddingConfig::new(&assets.minilm_dir))?;
        println!("embedding: loaded in {:.2?}", t0.elapsed());
        if tune {
            let sims_tr: Vec<_> = train
                .iter()
                .map(|e| lab.clause_sims(&e.text))
                .collect::<Result<_, _>>()?;
            let sims_te: Vec<_> = test
                .iter()
                .map(|e| lab.clause_sims(&e.text))
                .collect::<Result<_, _>>()?;
            let g = grid(0.30, 0.90, 0.01);
            let mut best: Option<(f64, f32, f32, Vec<f32>)> = None;
            for &margin in &[0.0f32, 0.02, 0.04, 0.06, 0.08, 0.1, 0.15, 0.2, 1.0] {
                let s: Vec<Vec<f32>> = sims_tr
                    .iter()
                    .map(|c| c.scores(ontology.len(), margin))
                    .collect();
                let (glob, per) = tune_thresholds(&s, &train_y, &g, 8);
                let f = f1_scores(&train_y, &apply(&s, &per)).micro;
                let fg = f1_scores(&train_y, &apply(&s, &vec![glob; ontology.len()])).micro;
                let s_te: Vec<Vec<f32>> = sims_te
                    .iter()
                    .map(|c| c.scores(ontology.len(), margin))
                    .collect();
                let te = f1_scores(&test_y, &apply(&s_te, &per));
                println!(
                    "  margin {margin:.2}: global {glob:.2} train micro {fg:.3}; per-label train micro {f:.3} (test micro {:.3} macro {:.3})",
                    te.micro, te.macro_
                );
                if best.as_ref().is_none_or(|b| f > b.0 + 1e-9) {
                    best = Some((f, margin, glob, per));
                }
            }
            let (f, margin, glob, per) = best.unwrap();
            println!("best on train: micro {f:.3}, margin {margin}, global threshold {glob:.2}");
            println!("const DEFAULT_THRESHOLDS: &[(&str, f32)] = &[");
            for (l, t) in ontology.labels().iter().zip(&per) {
                println!("    (\"{}\", {t:.2}),", l.id);
            }
            println!("];");
        }
        let t0 = Instant::now();
        let mut pred = Vec::new();
        for e in &test {
            let out = lab.label_blocking(&e.text)?;
            pred.push(to_mask(&ontology, &out.labels)?);
        }
        let ms = t0.elapsed().as_secs_f64() * 1e3 / test.len() as f64;
        let f = f1_scores(&test_y, &pred);
        per_label(&ontology, &test_y, &pred);
        if args.iter().any(|a| a == "--errors") {
            // Errors on the TRAIN split only: the test split stays unseen while iterating.
            let mut tr_pred = Vec::new();
            for e in &train {
                tr_pred.push(to_mask(&ontology, &lab.label_blocking(&e.text)?.labels)?);
            }
            for ((e, y), p) in train.iter().zip(&train_y).zip(&tr_pred) {
                if y != p {
                    let name = |m: &Vec<bool>, want: bool, other: &Vec<bool>| -> Vec<&str> {
                        ontology
                            .labels()
                            .iter()
                            .enumerate()
                            .filter(|(k, _)| m[*k] == want && other[*k] != want)
                            .map(|(_, l)| l.id.as_str())
                            .collect()
                    };
                    println!(
                        "--- {}: missed {:?} extra {:?}",
                        e.id,
                        name(y, true, p),
                        name(p, true, y)
                    );
                    let cs = lab.clause_sims(&e.text)?;
                    for (c, row) in cs.clauses.iter().zip(&cs.sims) {
                        let (k, s) =
                            row.iter()
                                .enumerate()
                                .fold(
                                    (0, f32::NEG_INFINITY),
                                    |b, (k, &s)| if s > b.1 { (k, s) } else { b },
                                );
                        println!(
                            "    [{}] {c:?} -> {} {s:.2}",
                            if vlmfuse_labeler::is_negated(c) {
                                "neg"
                            } else {
                                "   "
                            },
                            ontology.labels()[k].id
                        );
                    }
                }
            }
        }
        table.push((
            "embedding (all-MiniLM-L6-v2)".to_string(),
            f,
            ms,
            test.len(),
        ));
    }

    if only.as_deref().is_none_or(|o| o == "gguf") {
        let t0 = Instant::now();
        let mut cfg = GgufConfig::new(&assets.gemma_gguf);
        let lab = GgufLabeler::load(ontology.clone(), cfg.clone())?;
        println!("gguf: loaded and calibrated in {:.2?}", t0.elapsed());
        let test_n = test.len().min(gguf_test);
        let lab = if tune {
            let n = train.len().min(gguf_train);
            let mut s = Vec::new();
            for e in &train[..n] {
                let out = lab.label_blocking(&e.text)?;
                s.push(out.scores.iter().map(|x| x.score).collect::<Vec<f32>>());
            }
            let (glob, per) = tune_thresholds(&s, &train_y[..n], &grid(0.02, 0.98, 0.02), 8);
            println!("gguf tuned on {n} train answers: global threshold {glob:.2}");
            println!(
                "  per-label: {:?}",
                per.iter().map(|t| format!("{t:.2}")).collect::<Vec<_>>()
            );
            cfg.threshold = glob;
            GgufLabeler::load(ontology.clone(), cfg)?
        } else {
            lab
        };
        let t0 = Instant::now();
        let mut pred = Vec::new();
        for e in &test[..test_n] {
            let out = lab.label_blocking(&e.text)?;
            pred.push(to_mask(&ontology, &out.labels)?);
        }
        let ms = t0.elapsed().as_secs_f64() * 1e3 / test_n as f64;
        let f = f1_scores(&test_y[..test_n], &pred);
        per_label(&ontology, &test_y[..test_n], &pred);
        table.push((
            "gguf (gemma-3-270m Q4_K_M, yes/no)".to_string(),
            f,
            ms,
            test_n,
        ));
    }

    println!("\n| labeler | micro-F1 | macro-F1 | ms/answer | test answers |");
    println!("|---|---|---|---|---|");
    for (name, f, ms, n) in &table {
        println!(
            "| {name} | {:.3} | {:.3} | {ms:.1} | {n} |",
            f.micro, f.macro_
        );
    }
    println!("(macro-F1: a label with no true and no predicted positive scores F1 = 1)");
    println!(
        "openai-compatible labeler: not evaluated (no real server here; tested against a fake one)"
    );
    Ok(())
}
