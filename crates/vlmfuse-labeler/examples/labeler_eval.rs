//! Scores every labeler on the held-out test split of `tests/data/labeler/answers.jsonl`, with
//! per-label F1.
//!
//! ```text
//! cargo run --release -p vlmfuse-labeler \
//!     --example labeler_eval -- [--tune] [--only embedding,onnx,rules,remote,gguf]
//!     [--gguf PATH] [--gguf-test N] [--threads N] [--json FILE] [--data FILE]
//! ```
//! Answers are labelled in rounds of five (`ROUND_ANSWERS`), one `label_batch` call per round as
//! `/v1/infer` makes it, and the label stage's time is reported per round (median and p95, after
//! a warm-up), each engine measured in the same run.
//!
//! * `embedding`: the served default (rules + MiniLM paraphrases, ONNX Runtime encoder), built
//!   by `vlmfuse_testkit_models::labeler_eval::eval_embedding_labeler`, which the service's test holds
//!   the served labeler to;
//! * `candle`: the same matcher on the candle encoder (`encoder = "candle"`);
//! * `rules`: the rules alone (an ablation: what the embeddings add);
//! * `remote`: the OpenAI-compatible labeler against a local fake server that answers with
//!   the embedding labeler, so the number measures the remote client's prompt, transport and
//!   validation path with a known model behind it;
//! * `gguf`: the in-process GGUF labeler (default: the fetched gemma-3-270m, a base model).
//!
//! `--tune` fits the embedding thresholds on the TRAIN split only and prints them as the
//! constants to paste into `embedding.rs`; the test split is only scored.

use std::sync::Arc;
use std::time::Instant;
use vlmfuse_labeler::{
    BlockingLabeler, EmbeddingConfig, EmbeddingLabeler, GgufConfig, GgufLabeler, Labeler, Ontology,
    OpenAiConfig, OpenAiLabeler,
};
use vlmfuse_testkit_models::assets::find_assets;
use vlmfuse_testkit_models::labeler_eval::{
    default_dataset_path, eval_candle_labeler, eval_embedding_labeler, f1_scores, label_f1,
    load_dataset, per_label_f1, to_mask, Example, F1, ROUND_ANSWERS,
};

fn arg_value(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

struct Row {
    name: String,
    f: F1,
    per_label: Vec<f64>,
    /// Label stage per round of `ROUND_ANSWERS` answers: median and p95, ms (None: not timed).
    round_ms: Option<(f64, f64)>,
    n: usize,
}

fn pct(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// Median and p95, ms.
type MedianP95 = (f64, f64);

/// Labels the split in rounds, timing each round after a warm-up round; returns the labels and
/// the median and p95 round time.
fn label_timed(
    l: &dyn BlockingLabeler,
    texts: &[&str],
) -> anyhow::Result<(Vec<Vec<String>>, MedianP95)> {
    l.label_batch_blocking(&texts[..ROUND_ANSWERS.min(texts.len())])?;
    let mut labels = Vec::with_capacity(texts.len());
    let mut times = Vec::new();
    for round in texts.chunks(ROUND_ANSWERS) {
        let t0 = Instant::now();
        let outs = l.label_batch_blocking(round)?;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        labels.extend(outs.into_iter().map(|o| o.labels));
    }
    let ms = (pct(&mut times, 0.5), pct(&mut times, 0.95));
    Ok((labels, ms))
}

fn masks(o: &Ontology, outs: &[Vec<String>]) -> anyhow::Result<Vec<Vec<bool>>> {
    Ok(outs
        .iter()
        .map(|l| to_mask(o, l))
        .collect::<Result<_, _>>()?)
}

/// A fake OpenAI-compatible server whose "model" is the embedding labeler.
async fn fake_server(lab: Arc<EmbeddingLabeler>) -> String {
    use axum::{extract::State, routing::post, Json, Router};
    use serde_json::{json, Value};
    async fn chat(
        State(lab): State<Arc<EmbeddingLabeler>>,
        Json(body): Json<Value>,
    ) -> Json<Value> {
        let user = body["messages"][1]["content"].as_str().unwrap_or_default();
        let text = user
            .split_once("<<<\n")
            .and_then(|(_, r)| r.rsplit_once("\n>>>"))
            .map_or(user, |(t, _)| t)
            .to_string();
        let lab2 = lab.clone();
        let labels = tokio::task::spawn_blocking(move || lab2.label_blocking(&text))
            .await
            .ok()
            .and_then(Result::ok)
            .map(|o| o.labels)
            .unwrap_or_default();
        let content = json!({ "labels": labels }).to_string();
        Json(
            json!({"choices": [{"index": 0, "message": {"role": "assistant", "content": content}}]}),
        )
    }
    let app = Router::new()
        .route("/v1/chat/completions", post(chat))
        .with_state(lab);
    vlmfuse_testkit::server::serve_local(app).await
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let tune = args.iter().any(|a| a == "--tune");
    let only: Vec<String> = arg_value(&args, "--only")
        .map(|s| s.split(',').map(str::to_string).collect())
        .unwrap_or_else(|| {
            vec![
                "embedding".into(),
                "candle".into(),
                "rules".into(),
                "remote".into(),
                "gguf".into(),
            ]
        });
    let want = |n: &str| only.iter().any(|o| o == n);
    let gguf_test: usize =
        arg_value(&args, "--gguf-test").map_or(usize::MAX, |v| v.parse().unwrap());

    let assets = find_assets()?;
    let ontology = Ontology::default_driving();
    // `--data FILE`: another labelled set in the same format (e.g. answers_styles.jsonl).
    let data_path = arg_value(&args, "--data").map_or_else(default_dataset_path, Into::into);
    let data = load_dataset(&data_path)?;
    let (train, test): (Vec<&Example>, Vec<&Example>) =
        data.iter().partition(|e| e.split == "train");
    let truth = |xs: &[&Example]| -> anyhow::Result<Vec<Vec<bool>>> {
        Ok(xs
            .iter()
            .map(|e| to_mask(&ontology, &e.labels))
            .collect::<Result<_, _>>()?)
    };
    let (train_y, test_y) = (truth(&train)?, truth(&test)?);
    println!(
        "data set {}: {} train / {} test answers, {} labels",
        data_path.display(),
        train.len(),
        test.len(),
        ontology.len()
    );
    let test_texts: Vec<&str> = test.iter().map(|e| e.text.as_str()).collect();
    let mut table: Vec<Row> = Vec::new();

    let t0 = Instant::now();
    let emb = Arc::new(eval_embedding_labeler(&assets)?);
    println!("embedding: loaded in {:.2?}", t0.elapsed());

    if tune {
        // Thresholds of the embedding-eligible labels, on TRAIN only: the rules decide first,
        // then each label's paraphrase threshold maximises that label's F1.
        let texts: Vec<&str> = train.iter().map(|e| e.text.as_str()).collect();
        let reads = emb.read_batch(&texts)?;
        let none = vec![2.0f32; ontology.len()];
        println!("const DEFAULT_THRESHOLDS: &[(&str, f32)] = &[");
        for (k, l) in ontology.labels().iter().enumerate() {
            if reads.iter().all(|r| r.best[k].is_none()) {
                continue;
            }
            let y: Vec<bool> = train_y.iter().map(|r| r[k]).collect();
            let f_at = |t: f32| {
                let mut th = none.clone();
                th[k] = t;
                let p: Vec<bool> = reads
                    .iter()
                    .map(|r| emb.decide_with(r, &th).labels.contains(&l.id))
                    .collect();
                let s: Vec<f32> = p.iter().map(|&x| if x { 1.0 } else { 0.0 }).collect();
                label_f1(&s, &y, 0.5)
            };
            let mut best = (f_at(2.0), 2.0f32);
            let mut t = 0.95f32;
            while t >= 0.5 {
                let f = f_at(t);
                // Ties keep the higher threshold: a paraphrase match must earn its place.
                if f > best.0 + 1e-9 {
                    best = (f, t);
                }
                t -= 0.01;
            }
            // How many labels a paraphrase match adds over the rules, and how many are right.
            let base: Vec<bool> = reads
                .iter()
                .map(|r| emb.decide_with(r, &none).labels.contains(&l.id))
                .collect();
            let adds: Vec<String> = [0.95f32, 0.9, 0.85, 0.8, 0.75, 0.7, 0.65]
                .iter()
                .map(|&t| {
                    let mut th = none.clone();
                    th[k] = t;
                    let (mut n, mut ok) = (0, 0);
                    for ((r, &b), &yy) in reads.iter().zip(&base).zip(&y) {
                        let on = emb.decide_with(r, &th).labels.contains(&l.id);
                        if on && !b {
                            n += 1;
                            ok += usize::from(yy);
                        }
                    }
                    format!("{t:.2}:{ok}/{n}")
                })
                .collect();
            println!(
                "    (\"{}\", {:.2}), // train F1 {:.3}; added right/added at t: {}",
                l.id,
                best.1,
                best.0,
                adds.join(" ")
            );
        }
        println!("];");
    }

    let mut engine_labels: Vec<(String, Vec<Vec<String>>)> = Vec::new();
    if want("embedding") {
        let (labels, ms) = label_timed(emb.as_ref(), &test_texts)?;
        let pred = masks(&ontology, &labels)?;
        table.push(Row {
            name: "embedding (served: rules + all-MiniLM-L6-v2 on onnx)".into(),
            f: f1_scores(&test_y, &pred),
            per_label: per_label_f1(&test_y, &pred),
            round_ms: Some(ms),
            n: test.len(),
        });
        // Per style: the paper's three-step shape against the others.
        let mut styles: Vec<&str> = test.iter().map(|e| e.style.as_str()).collect();
        styles.sort_unstable();
        styles.dedup();
        println!("served labeler per style (test split): style, answers, micro-F1, macro-F1");
        for st in styles {
            let idx: Vec<usize> = (0..test.len()).filter(|&i| test[i].style == st).collect();
            let y: Vec<Vec<bool>> = idx.iter().map(|&i| test_y[i].clone()).collect();
            let p: Vec<Vec<bool>> = idx.iter().map(|&i| pred[i].clone()).collect();
            let f = f1_scores(&y, &p);
            println!("  {st:<14} {:>4} {:.3} {:.3}", idx.len(), f.micro, f.macro_);
        }
        engine_labels.push(("onnx".into(), labels));
    }

    if want("candle") {
        let l = eval_candle_labeler(&assets)?;
        let (labels, ms) = label_timed(&l, &test_texts)?;
        let pred = masks(&ontology, &labels)?;
        table.push(Row {
            name: "candle (the same matcher, candle encoder)".into(),
            f: f1_scores(&test_y, &pred),
            per_label: per_label_f1(&test_y, &pred),
            round_ms: Some(ms),
            n: test.len(),
        });
        engine_labels.push(("candle".into(), labels));
    }
    if let [(a, la), (b, lb)] = engine_labels.as_slice() {
        let differ = la.iter().zip(lb).filter(|(x, y)| x != y).count();
        println!(
            "{a} vs {b} encoder: {differ} of {} answers labelled differently",
            la.len()
        );
    }

    if want("rules") {
        let mut cfg = EmbeddingConfig::new(&assets.minilm_dir);
        cfg.label_thresholds = ontology.ids().map(|id| (id.to_string(), 2.0f32)).collect();
        let r = EmbeddingLabeler::load(ontology.clone(), cfg)?;
        let (labels, ms) = label_timed(&r, &test_texts)?;
        let pred = masks(&ontology, &labels)?;
        table.push(Row {
            name: "rules alone (ablation)".into(),
            f: f1_scores(&test_y, &pred),
            per_label: per_label_f1(&test_y, &pred),
            round_ms: Some(ms),
            n: test.len(),
        });
    }

    if want("remote") {
        let rt = tokio::runtime::Runtime::new()?;
        let labels: Vec<Vec<String>> = rt.block_on(async {
            let url = fake_server(emb.clone()).await;
            let remote = OpenAiLabeler::new(
                ontology.clone(),
                OpenAiConfig {
                    base_url: url,
                    model: "fake-embedding".into(),
                    ..Default::default()
                },
            )?;
            let mut out = Vec::new();
            for t in &test_texts {
                out.push(remote.label(t).await?.labels);
            }
            Ok::<_, anyhow::Error>(out)
        })?;
        let pred = masks(&ontology, &labels)?;
        table.push(Row {
            name: "remote (OpenAI-compatible, fake server backed by the embedding labeler)".into(),
            f: f1_scores(&test_y, &pred),
            per_label: per_label_f1(&test_y, &pred),
            round_ms: None,
            n: test.len(),
        });
    }

    if want("gguf") {
        let path = arg_value(&args, "--gguf").map_or(assets.gemma_gguf.clone(), Into::into);
        let t0 = Instant::now();
        let lab = GgufLabeler::load(ontology.clone(), GgufConfig::new(&path))?;
        println!("gguf: {} loaded in {:.2?}", lab.name(), t0.elapsed());
        let n = test.len().min(gguf_test);
        let t0 = Instant::now();
        let mut labels = Vec::new();
        let mut times = Vec::new();
        for (i, round) in test_texts[..n].chunks(ROUND_ANSWERS).enumerate() {
            let t = Instant::now();
            labels.extend(
                lab.label_batch_blocking(round)?
                    .into_iter()
                    .map(|o| o.labels),
            );
            times.push(t.elapsed().as_secs_f64() * 1e3);
            eprintln!(
                "gguf: {}/{n} answers, {:.1?}",
                ((i + 1) * ROUND_ANSWERS).min(n),
                t0.elapsed()
            );
        }
        let pred = masks(&ontology, &labels)?;
        table.push(Row {
            name: format!("gguf ({})", lab.name()),
            f: f1_scores(&test_y[..n], &pred),
            per_label: per_label_f1(&test_y[..n], &pred),
            round_ms: Some((pct(&mut times, 0.5), pct(&mut times, 0.95))),
            n,
        });
    }

    println!(
        "\n| labeler | micro-F1 | macro-F1 | worst label | ms per round of {ROUND_ANSWERS} (median / p95) | test answers |"
    );
    println!("|---|---|---|---|---|---|");
    for r in &table {
        let ms = r
            .round_ms
            .map_or("-".to_string(), |(m, p)| format!("{m:.1} / {p:.1}"));
        let (wk, wf) = r
            .per_label
            .iter()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(b.1))
            .map_or((0, f64::NAN), |(k, f)| (k, *f));
        println!(
            "| {} | {:.3} | {:.3} | {} {wf:.3} | {ms} | {} |",
            r.name,
            r.f.micro,
            r.f.macro_,
            ontology.id(wk),
            r.n
        );
    }
    println!("\nper-label F1 (test split):\n");
    let mut head = "| label | positives |".to_string();
    for r in &table {
        head.push_str(&format!(" {} |", r.name.split(' ').next().unwrap_or("")));
    }
    println!("{head}");
    println!("|---|---|{}", "---|".repeat(table.len()));
    for (k, l) in ontology.labels().iter().enumerate() {
        let pos = test_y.iter().filter(|r| r[k]).count();
        let mut line = format!("| {} | {pos} |", l.id);
        for r in &table {
            line.push_str(&format!(" {:.3} |", r.per_label[k]));
        }
        println!("{line}");
    }
    println!("(macro-F1: a label with no true and no predicted positive scores F1 = 1)");
    if let Some(p) = arg_value(&args, "--json") {
        let v: Vec<serde_json::Value> = table
            .iter()
            .map(|r| {
                serde_json::json!({
                    "labeler": r.name, "micro_f1": r.f.micro, "macro_f1": r.f.macro_,
                    "round_ms_median": r.round_ms.map(|m| m.0), "round_ms_p95": r.round_ms.map(|m| m.1),
                    "round_answers": ROUND_ANSWERS, "answers": r.n,
                    "per_label": ontology.ids().zip(&r.per_label).map(|(id, f)| (id.to_string(), *f)).collect::<std::collections::BTreeMap<_, _>>(),
                })
            })
            .collect();
        std::fs::write(p, serde_json::to_string_pretty(&v).unwrap())?;
    }
    Ok(())
}
