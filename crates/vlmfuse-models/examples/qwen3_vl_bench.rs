//! Time to first token and decode throughput of the in-process Qwen3-VL, for
//! `scripts/bench/qwen3_vl.py` (which runs transformers on the same weights and frames in the
//! same run and prints the ratios). Build it in release:
//!
//! ```sh
//! cargo build --release -p vlmfuse-models --example qwen3_vl_bench
//! ${CARGO_TARGET_DIR:-target}/release/examples/qwen3_vl_bench MODEL_DIR --frames 8 --size 64x64 --new 32
//! ```
//!
//! Frames are the parity tests' synthetic clip. Prints one JSON object: medians over `--runs`
//! timed runs after one warm-up, and the greedy ids (so the caller can check both engines
//! decoded the same tokens).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use candle_core::{DType, Device};
use vlmfuse_models::generate::{generate_with, GenerateOptions};
use vlmfuse_models::models::qwen3_vl::{Cache, LoadOptions, Qwen3Vl, Qwen3VlProcessor};
use vlmfuse_models::{FrameRef, WeightSource};
use vlmfuse_testkit_models::fixtures::qwen3_vl::parity_frame;

struct Args {
    model: PathBuf,
    frames: usize,
    width: usize,
    height: usize,
    new: usize,
    runs: usize,
    prompt: String,
    dtype: DType,
}

fn parse() -> Result<Args, String> {
    let mut a = Args {
        model: PathBuf::new(),
        frames: 8,
        width: 64,
        height: 64,
        new: 32,
        runs: 5,
        prompt: "describe the dashcam clip".into(),
        dtype: DType::F32,
    };
    let mut it = std::env::args().skip(1);
    let mut model = None;
    while let Some(k) = it.next() {
        let mut val = || it.next().ok_or(format!("{k} needs a value"));
        match k.as_str() {
            "--frames" => a.frames = val()?.parse().map_err(|e| format!("--frames: {e}"))?,
            "--size" => {
                let v = val()?;
                let (w, h) = v.split_once('x').ok_or("--size WxH")?;
                a.width = w.parse().map_err(|e| format!("--size: {e}"))?;
                a.height = h.parse().map_err(|e| format!("--size: {e}"))?;
            }
            "--new" => a.new = val()?.parse().map_err(|e| format!("--new: {e}"))?,
            "--runs" => a.runs = val()?.parse().map_err(|e| format!("--runs: {e}"))?,
            "--prompt" => a.prompt = val()?,
            "--dtype" => {
                a.dtype = match val()?.as_str() {
                    "f32" => DType::F32,
                    "f16" => DType::F16,
                    "bf16" => DType::BF16,
                    o => return Err(format!("--dtype {o}: f32, f16 or bf16")),
                }
            }
            _ if model.is_none() && !k.starts_with('-') => model = Some(PathBuf::from(k)),
            _ => return Err(format!("unknown argument {k}")),
        }
    }
    a.model = model.ok_or("usage: qwen3_vl_bench MODEL_DIR [--frames N] [--size WxH] [--new N] [--runs N] [--prompt S] [--dtype f32]")?;
    if a.runs == 0 || a.new == 0 {
        return Err("--runs and --new must be positive".into());
    }
    Ok(a)
}

/// The parity tests' synthetic clip.
fn frames(n: usize, w: usize, h: usize) -> Vec<Vec<u8>> {
    (0..n).map(|k| parity_frame(w, h, k)).collect()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn main() -> ExitCode {
    let a = match parse() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::from(2);
        }
    };
    match run(&a) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("qwen3_vl_bench: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(a: &Args) -> Result<(), vlmfuse_models::ModelError> {
    let src = WeightSource::local(&a.model);
    let t = Instant::now();
    let model = Qwen3Vl::load(
        &src,
        &LoadOptions {
            dtype: a.dtype,
            device: Device::Cpu,
            adapter: None,
        },
    )?;
    let proc = Qwen3VlProcessor::load(&src, model.config())?;
    let load_ms = t.elapsed().as_secs_f64() * 1e3;
    let clip = frames(a.frames, a.width, a.height);
    let refs: Vec<FrameRef> = clip
        .iter()
        .map(|rgb| FrameRef {
            width: a.width as u32,
            height: a.height as u32,
            rgb,
        })
        .collect();
    // Frames 0.5 s apart, as the media layer would hand over a 2 fps sampling.
    let times: Vec<f64> = (0..a.frames).map(|i| i as f64 * 0.5).collect();
    let (mut pre, mut prefill, mut decode) = (Vec::new(), Vec::new(), Vec::new());
    let mut ids = Vec::new();
    let mut prompt_tokens = 0;
    for run in 0..=a.runs {
        let t0 = Instant::now();
        let seq = if a.frames == 0 {
            proc.prepare(&a.prompt, None)?
        } else {
            proc.prepare_frames(&a.prompt, &refs, &times)?
        };
        let t1 = Instant::now();
        prompt_tokens = seq.ids.len();
        let mut cache = Cache::new(seq.ids.len() + a.new + 1);
        let g = generate_with(
            &model,
            &vec![seq],
            &mut cache,
            &GenerateOptions::greedy(a.new, &[]),
            None,
        )?;
        let out = g.tokens[0].clone();
        if run > 0 {
            pre.push((t1 - t0).as_secs_f64() * 1e3);
            prefill.push(g.prefill.as_secs_f64() * 1e3);
            // The first token comes from the prefill; the rest from `new - 1` steps.
            decode.push((a.new - 1) as f64 / g.decode.as_secs_f64().max(1e-9));
        }
        ids = out;
    }
    let (pre, prefill) = (median(pre), median(prefill));
    let j = serde_json::json!({
        "engine": "vlmfuse",
        // candle's CPU pool is rayon's global one: RAYON_NUM_THREADS or one per core.
        "threads": std::env::var("RAYON_NUM_THREADS")
            .ok()
            .and_then(|s| s.parse::<usize>().ok())
            .unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)),
        "load_ms": load_ms,
        "prompt_tokens": prompt_tokens,
        "preprocess_ms": pre,
        "prefill_ms": prefill,
        "ttft_ms": pre + prefill,
        "decode_tokens_per_s": median(decode),
        "runs": a.runs,
        "ids": ids,
    });
    println!("{j}");
    Ok(())
}
