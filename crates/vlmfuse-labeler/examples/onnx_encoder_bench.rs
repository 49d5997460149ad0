//! The sentence encoder of the label stage on ONNX Runtime against candle: all clauses of three
//! typical VLM answers (the first three of the test split of `tests/data/labeler/answers.jsonl`)
//! in one batch, as the labeler encodes a round, on the real all-MiniLM-L6-v2.
//!
//! ```sh
//! RAYON_NUM_THREADS=2 cargo run --release \
//!     -p vlmfuse-labeler --example onnx_encoder_bench -- --threads 2 --reps 30
//! ```
//!
//! Prints the median per batch of each engine, the cores busy, the largest cosine distance
//! between the two engines' embeddings, and for reference today's label stage (the candle
//! `EmbeddingLabeler`, one answer after another).

use std::time::{Duration, Instant};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use candle_transformers::models::bert::{BertModel, Config as BertConfig};
use tokenizers::{PaddingParams, Tokenizer, TruncationParams};
use vlmfuse_labeler::{
    rules, text, BlockingLabeler, EmbeddingConfig, EmbeddingLabeler, OnnxEncoderConfig,
    OnnxSentenceEncoder, Ontology, SentenceEncoder,
};
use vlmfuse_ort::SessionOptions;
use vlmfuse_testkit_models::assets::require_assets;
use vlmfuse_testkit_models::labeler_eval::{default_dataset_path, load_dataset};

fn arg(name: &str, default: usize) -> usize {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(|v| {
            v.parse()
                .unwrap_or_else(|_| panic!("{name} takes a number"))
        })
        .unwrap_or(default)
}

/// Every item (list entry, clause part) of an answer, as the labeler reads it: the texts the
/// encoder would see if none of them were explained by a rule (the worst case).
fn clauses(answer: &str) -> Vec<String> {
    text::sentences(answer)
        .iter()
        .flat_map(|s| {
            rules::items(s)
                .into_iter()
                .map(|(a, b)| (a..b).map(|k| s.w(k)).collect::<Vec<_>>().join(" "))
                .collect::<Vec<_>>()
        })
        .collect()
}

fn cpu_time() -> Duration {
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage only writes into the struct we own.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| Duration::new(t.tv_sec as u64, t.tv_usec as u32 * 1000);
    tv(u.ru_utime) + tv(u.ru_stime)
}

/// Median wall time in ms and cores busy over `reps` runs after two warm-ups.
fn time<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, f64, T) {
    let _ = f();
    let mut out = f();
    let mut walls = Vec::with_capacity(reps);
    let (c0, w0) = (cpu_time(), Instant::now());
    for _ in 0..reps {
        let t = Instant::now();
        out = f();
        walls.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let cores = (cpu_time() - c0).as_secs_f64() / w0.elapsed().as_secs_f64();
    walls.sort_by(f64::total_cmp);
    (walls[walls.len() / 2], cores, out)
}

struct CandleEncoder {
    model: BertModel,
    tokenizer: Tokenizer,
}

impl CandleEncoder {
    fn load(dir: &std::path::Path) -> Self {
        let cfg: BertConfig =
            serde_json::from_str(&std::fs::read_to_string(dir.join("config.json")).unwrap())
                .unwrap();
        // SAFETY: the asset cache is not modified while the benchmark runs.
        let vb = unsafe {
            VarBuilder::from_mmaped_safetensors(
                &[dir.join("model.safetensors")],
                DType::F32,
                &Device::Cpu,
            )
            .unwrap()
        };
        let mut tokenizer = Tokenizer::from_file(dir.join("tokenizer.json")).unwrap();
        tokenizer.with_padding(Some(PaddingParams::default()));
        tokenizer
            .with_truncation(Some(TruncationParams {
                max_length: 128,
                ..Default::default()
            }))
            .unwrap();
        Self {
            model: BertModel::load(vb, &cfg).unwrap(),
            tokenizer,
        }
    }

    fn encode(&self, texts: &[&str]) -> Vec<Vec<f32>> {
        let enc = self.tokenizer.encode_batch(texts.to_vec(), true).unwrap();
        let stack = |f: &dyn Fn(&tokenizers::Encoding) -> &[u32]| {
            let rows: Vec<Tensor> = enc
                .iter()
                .map(|e| Tensor::new(f(e), &Device::Cpu).unwrap())
                .collect();
            Tensor::stack(&rows, 0).unwrap()
        };
        let ids = stack(&|e| e.get_ids());
        let mask = stack(&|e| e.get_attention_mask());
        let hidden = self
            .model
            .forward(&ids, &ids.zeros_like().unwrap(), Some(&mask))
            .unwrap();
        let m = mask.to_dtype(DType::F32).unwrap().unsqueeze(2).unwrap();
        let mean = hidden
            .broadcast_mul(&m)
            .unwrap()
            .sum(1)
            .unwrap()
            .broadcast_div(&m.sum(1).unwrap())
            .unwrap();
        let norm = mean.sqr().unwrap().sum_keepdim(1).unwrap().sqrt().unwrap();
        mean.broadcast_div(&norm).unwrap().to_vec2().unwrap()
    }
}

fn main() {
    let threads = arg("--threads", 2);
    let reps = arg("--reps", 30);
    let assets = require_assets();
    let data = load_dataset(&default_dataset_path()).expect("labeler dataset");
    let answers: Vec<String> = data
        .iter()
        .filter(|a| a.split == "test")
        .take(3)
        .map(|a| a.text.clone())
        .collect();
    let clauses: Vec<String> = answers.iter().flat_map(|a| clauses(a)).collect();
    let texts: Vec<&str> = clauses.iter().map(String::as_str).collect();
    println!(
        "3 answers ({} characters) → {} clauses in one batch, {threads} threads, {reps} runs",
        answers.iter().map(String::len).sum::<usize>(),
        texts.len()
    );

    let ort = OnnxSentenceEncoder::load(&OnnxEncoderConfig {
        session: SessionOptions::with_threads(threads),
        ..OnnxEncoderConfig::new(&assets.minilm_onnx_dir)
    })
    .expect("load the ONNX encoder");
    let lens: Vec<usize> = ort
        .token_ids(&texts)
        .unwrap()
        .iter()
        .map(Vec::len)
        .collect();
    let longest = lens.iter().copied().max().unwrap_or(0);
    println!(
        "tokens: {} in all, longest clause {longest}, {} once padded to it",
        lens.iter().sum::<usize>(),
        longest * lens.len()
    );
    let (ort_ms, ort_cores, a) = time(reps, || ort.encode(&texts).unwrap());
    println!("encoder, onnx   : median {ort_ms:6.1} ms, {ort_cores:.2} cores busy");

    let candle = CandleEncoder::load(&assets.minilm_dir);
    let (candle_ms, candle_cores, b) = time(reps, || candle.encode(&texts));
    println!("encoder, candle : median {candle_ms:6.1} ms, {candle_cores:.2} cores busy");
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| {
            x.iter()
                .zip(y)
                .map(|(p, q)| *p as f64 * *q as f64)
                .sum::<f64>()
        })
        .fold(1.0, f64::min);
    println!(
        "candle / onnx   : {:.2}x; lowest cosine between engines {worst:.8}",
        candle_ms / ort_ms
    );

    let labeler = EmbeddingLabeler::load(
        Ontology::default_driving(),
        EmbeddingConfig::new(&assets.minilm_dir),
    )
    .expect("load the embedding labeler");
    let refs: Vec<&str> = answers.iter().map(String::as_str).collect();
    let (stage_ms, stage_cores, _) = time(reps.min(10), || {
        labeler.label_batch_blocking(&refs).unwrap();
    });
    println!(
        "label stage today (candle EmbeddingLabeler, the three answers as one round): median \
         {stage_ms:6.1} ms, {stage_cores:.2} cores busy"
    );
    println!(
        "target: label stage for three answers <= 30 ms: encoder part on onnx {}",
        if ort_ms <= 30.0 { "met" } else { "MISSED" }
    );
}
