//! How far candle-transformers' own `qwen3_vl` is from transformers on the parity fixture: the
//! comparison behind "this crate owns the model" (see `models::qwen3_vl`), run by
//! `scripts/parity/qwen3_vl.py --candle-transformers` or by hand against the committed
//! references:
//!
//! ```sh
//! cargo run -p vlmfuse-models --example candle_transformers_qwen3_vl -- \
//!     [--fixture DIR] [--reference tests/data/parity/qwen3_vl/reference.json] [--case NAME]
//! ```
//!
//! It feeds candle-transformers the ids, pixels and grid this crate's processor builds for a
//! reference case (the parity tests check those against transformers) in two ways: the whole
//! prompt as one chunk, and the way the service ran it before it owned the model (text one
//! token at a time, the video span as one chunk). It prints one JSON line with the max abs
//! difference of each from transformers' first-token logits, the tolerance the parity tests
//! hold this crate's model to (1e-4) and whether each is within it. It is a measurement, not a
//! test: when upstream is fixed the numbers drop below the tolerance and the script says so.

use std::path::PathBuf;
use std::process::ExitCode;

use candle_core::{DType, Device, Tensor};
use serde_json::Value;
use vlmfuse_models::models::qwen3_vl::{LoadOptions, Qwen3Vl, Qwen3VlProcessor};
use vlmfuse_models::{FrameRef, WeightSource};
use vlmfuse_testkit_models::fixtures::qwen3_vl::parity_frame;
use vlmfuse_testkit_models::fixtures::TinyQwen3Vl;

/// What the parity tests allow between this crate's model and transformers.
const LOGIT_TOL: f32 = 1e-4;
const SEED: u64 = 7;

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn main() -> ExitCode {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut fixture: Option<PathBuf> = None;
    let mut reference = root.join("tests/data/parity/qwen3_vl/reference.json");
    let mut case_name = "video8_describe".to_string();
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        let mut val = || it.next().unwrap_or_default();
        match a.as_str() {
            "--fixture" => fixture = Some(val().into()),
            "--reference" => reference = val().into(),
            "--case" => case_name = val(),
            _ => {
                eprintln!(
                    "usage: candle_transformers_qwen3_vl [--fixture DIR] [--reference FILE] \
                     [--case NAME]"
                );
                return ExitCode::from(2);
            }
        }
    }
    match run(fixture, &reference, &case_name) {
        Ok(line) => {
            println!("{line}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("candle_transformers_qwen3_vl: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(
    fixture: Option<PathBuf>,
    reference: &std::path::Path,
    case_name: &str,
) -> anyhow::Result<Value> {
    use candle_transformers::models::qwen3_vl::{Config as CtConfig, Qwen3VLModel};
    let tmp = tempfile::tempdir()?;
    let dir = match fixture {
        Some(d) => d,
        None => {
            TinyQwen3Vl::default().write(tmp.path(), SEED)?;
            tmp.path().to_path_buf()
        }
    };
    let reference: Value = serde_json::from_str(&std::fs::read_to_string(reference)?)?;
    let case = reference["cases"]
        .as_array()
        .and_then(|c| c.iter().find(|c| c["name"] == case_name))
        .ok_or_else(|| anyhow::anyhow!("no case `{case_name}` in the reference"))?;
    let want: Vec<f32> = case["first_logits"]
        .as_array()
        .ok_or_else(|| anyhow::anyhow!("case without first_logits"))?
        .iter()
        .map(|x| x.as_f64().unwrap_or(f64::NAN) as f32)
        .collect();
    let num = |k: &str| case[k].as_u64().unwrap_or(0) as usize;

    // The inputs as this crate builds them (checked against transformers by the parity tests).
    let src = WeightSource::local(&dir);
    let ours = Qwen3Vl::load(&src, &LoadOptions::default())?;
    let proc = Qwen3VlProcessor::load(&src, ours.config())?;
    let (w, h, n, k0) = (num("width"), num("height"), num("frames"), num("k0"));
    anyhow::ensure!(n > 0, "case `{case_name}` has no video");
    let clip: Vec<Vec<u8>> = (k0..k0 + n).map(|k| parity_frame(w, h, k)).collect();
    let refs: Vec<FrameRef> = clip
        .iter()
        .map(|rgb| FrameRef {
            width: w as u32,
            height: h as u32,
            rgb,
        })
        .collect();
    let fps = case["video_fps"].as_f64().unwrap_or(1.0);
    let times: Vec<f64> = case["indices"]
        .as_array()
        .map(|a| a.iter().map(|i| i.as_f64().unwrap_or(0.0) / fps).collect())
        .unwrap_or_default();
    let seq = proc.prepare_frames(case["prompt"].as_str().unwrap_or(""), &refs, &times)?;
    let v = seq.video.as_ref().expect("a video case");

    // candle-transformers' model on the same weights (it wants an lm_head bias and an untied head).
    let mut raw: Value = src.read_json("config.json")?;
    raw["text_config"]["tie_word_embeddings"] = Value::Bool(false);
    raw["text_config"]["max_position_embeddings"] = serde_json::json!(1024);
    let cfg: CtConfig = serde_json::from_value(raw)?;
    let mut t = candle_core::safetensors::load(src.resolve("model.safetensors")?, &Device::Cpu)?;
    let vocab = t["lm_head.weight"].dim(0)?;
    t.insert(
        "lm_head.bias".into(),
        Tensor::zeros(vocab, DType::F32, &Device::Cpu)?,
    );
    let vid = cfg.video_token_id;
    let mut spans = Vec::new();
    let mut i = 0;
    while i < seq.ids.len() {
        if seq.ids[i] == vid {
            let s = i;
            while i < seq.ids.len() && seq.ids[i] == vid {
                i += 1;
            }
            spans.push((s, i));
        } else {
            i += 1;
        }
    }
    let d = ours.config().vision.patch_dim();
    let px = Tensor::from_slice(&v.pixel_values, (v.pixel_values.len() / d, d), &Device::Cpu)?;
    let g: Vec<u32> = v.grid_thw.iter().map(|&x| x as u32).collect();
    let grid = Tensor::from_vec(g, (1, 3), &Device::Cpu)?;

    // 1. The whole prompt as one chunk.
    let model = Qwen3VLModel::new(
        &cfg,
        candle_nn::VarBuilder::from_tensors(t.clone(), DType::F32, &Device::Cpu),
    )?;
    let input = Tensor::new(seq.ids.as_slice(), &Device::Cpu)?.unsqueeze(0)?;
    let one_chunk = model
        .forward(
            &input,
            None,
            Some(px.clone()),
            None,
            Some(grid.clone()),
            vec![seq.ids.len()],
            vec![vec![]],
            vec![spans.clone()],
            &[0],
        )?
        .squeeze(0)?
        .to_vec1::<f32>()?;

    // 2. How the service ran it before it owned the model (its removed `causal_prefill` mode):
    // text one token at a time, the video span (first <|vision_start|> to last <|vision_end|>)
    // as one chunk.
    let model = Qwen3VLModel::new(
        &cfg,
        candle_nn::VarBuilder::from_tensors(t, DType::F32, &Device::Cpu),
    )?;
    let (cs, ce) = (spans[0].0 - 1, spans.last().expect("a span").1 + 1);
    let fwd = |chunk: &[u32],
               off: usize,
               video: Option<Vec<(usize, usize)>>|
     -> candle_core::Result<Tensor> {
        let input = Tensor::new(chunk, &Device::Cpu)?.unsqueeze(0)?;
        let (p, g, s) = match video {
            Some(s) => (Some(px.clone()), Some(grid.clone()), vec![s]),
            None => (None, None, vec![vec![]]),
        };
        model.forward(
            &input,
            None,
            p,
            None,
            g,
            vec![chunk.len()],
            vec![vec![]],
            s,
            &[off],
        )
    };
    for (i, &t) in seq.ids[..cs].iter().enumerate() {
        fwd(&[t], i, None)?;
    }
    let local: Vec<(usize, usize)> = spans.iter().map(|&(a, b)| (a - cs, b - cs)).collect();
    let mut last = fwd(&seq.ids[cs..ce], cs, Some(local))?;
    for (i, &t) in seq.ids[ce..].iter().enumerate() {
        last = fwd(&[t], ce + i, None)?;
    }
    let causal = last.squeeze(0)?.to_vec1::<f32>()?;

    let (d1, d2) = (
        max_abs_diff(&one_chunk, &want),
        max_abs_diff(&causal, &want),
    );
    Ok(serde_json::json!({
        "case": case_name,
        "logit_range": case["logit_range"],
        "tolerance": 1e-4,
        "one_chunk_max_abs_diff": d1,
        "causal_text_video_chunk_max_abs_diff": d2,
        "one_chunk_within_tolerance": d1 <= LOGIT_TOL,
        "causal_within_tolerance": d2 <= LOGIT_TOL,
    }))
}
