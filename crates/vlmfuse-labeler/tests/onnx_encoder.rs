//! The ONNX Runtime sentence encoder against torch (expected outputs committed by
//! `scripts/onnx/make_fixtures.py`) and against candle on the same weights: on the tiny BERT
//! exports under `tests/data/onnx/tiny-bert` always, and on the real all-MiniLM-L6-v2 when the
//! assets can be fetched.

mod common;

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use candle_transformers::models::bert::{BertModel, Config as BertConfig};
use tokenizers::{PaddingParams, Tokenizer, TruncationParams};
use vlmfuse_labeler::{
    LabelerError, LabelerErrorKind, OnnxEncoderConfig, OnnxSentenceEncoder, SentenceEncoder,
};
use vlmfuse_ort::SessionOptions;

fn data(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data/onnx")
        .join(rel)
}

struct Expected {
    texts: Vec<String>,
    ids: Option<Vec<Vec<u32>>>,
    embeddings: Vec<Vec<f32>>,
}

fn expected(dir: &str) -> Expected {
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(data(dir).join("expected.json")).unwrap())
            .unwrap();
    let strs = |v: &serde_json::Value| -> Vec<String> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|s| s.as_str().unwrap().to_string())
            .collect()
    };
    Expected {
        texts: strs(&v["texts"]),
        ids: v.get("ids").map(|ids| {
            ids.as_array()
                .unwrap()
                .iter()
                .map(|r| {
                    r.as_array()
                        .unwrap()
                        .iter()
                        .map(|i| i.as_u64().unwrap() as u32)
                        .collect()
                })
                .collect()
        }),
        embeddings: v["embeddings"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| {
                r.as_array()
                    .unwrap()
                    .iter()
                    .map(|x| x.as_f64().unwrap() as f32)
                    .collect()
            })
            .collect(),
    }
}

fn cosine(a: &[f32], b: &[f32]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum();
    let na: f64 = a.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    let nb: f64 = b.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    dot / (na * nb)
}

fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// candle-transformers' BERT on the same safetensors, pooled the same way (the reference the
/// candle backend of the labeler computes).
fn candle_embed(dir: &Path, texts: &[&str]) -> Vec<Vec<f32>> {
    let cfg: BertConfig =
        serde_json::from_str(&std::fs::read_to_string(dir.join("config.json")).unwrap()).unwrap();
    let vb = unsafe {
        VarBuilder::from_mmaped_safetensors(
            &[dir.join("model.safetensors")],
            DType::F32,
            &Device::Cpu,
        )
        .unwrap()
    };
    let model = BertModel::load(vb, &cfg).unwrap();
    let mut tok = Tokenizer::from_file(dir.join("tokenizer.json")).unwrap();
    tok.with_padding(Some(PaddingParams::default()));
    tok.with_truncation(Some(TruncationParams {
        max_length: 128,
        ..Default::default()
    }))
    .unwrap();
    let enc = tok.encode_batch(texts.to_vec(), true).unwrap();
    let stack = |f: &dyn Fn(&tokenizers::Encoding) -> &[u32]| {
        let rows: Vec<Tensor> = enc
            .iter()
            .map(|e| Tensor::new(f(e), &Device::Cpu).unwrap())
            .collect();
        Tensor::stack(&rows, 0).unwrap()
    };
    let ids = stack(&|e| e.get_ids());
    let mask = stack(&|e| e.get_attention_mask());
    let hidden = model
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

fn runtime() -> vlmfuse_labeler::assets::AssetPaths {
    common::assets()
}

fn check_against(enc: &OnnxSentenceEncoder, exp: &Expected, what: &str) {
    let texts: Vec<&str> = exp.texts.iter().map(String::as_str).collect();
    let got = enc.encode(&texts).unwrap();
    assert_eq!(got.len(), texts.len());
    for (k, (g, w)) in got.iter().zip(&exp.embeddings).enumerate() {
        let c = cosine(g, w);
        assert!(c >= 0.99999, "{what}, text {k} {:?}: cosine {c}", texts[k]);
        assert!(max_abs(g, w) < 1e-4, "{what}, text {k}: {}", max_abs(g, w));
        let n: f32 = g.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((n - 1.0).abs() < 1e-5, "{what}: norm {n}");
    }
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn tiny_bert_export_matches_torch_and_candle() {
    runtime();
    let exp = expected("tiny-bert");
    let dir = data("tiny-bert");
    let enc = OnnxSentenceEncoder::load(&OnnxEncoderConfig::new(&dir)).unwrap();
    assert_eq!(enc.engine(), "onnx");
    assert_eq!(enc.dim(), 32);
    assert!(enc.model_path().ends_with("model.onnx"));
    let texts: Vec<&str> = exp.texts.iter().map(String::as_str).collect();
    // The Rust tokenizer gives the Python tokenizer's ids (an unknown word included).
    assert_eq!(&enc.token_ids(&texts).unwrap(), exp.ids.as_ref().unwrap());
    check_against(&enc, &exp, "torch export");

    let theirs = candle_embed(&dir, &texts);
    for (k, (a, b)) in enc.encode(&texts).unwrap().iter().zip(&theirs).enumerate() {
        let c = cosine(a, b);
        assert!(c >= 0.99999, "ort vs candle, text {k}: {c}");
    }
    assert!(enc.encode(&[]).unwrap().is_empty());
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn the_safetensors_graph_matches_torch() {
    // scripts/onnx/bert_graph.py's graph (the one the real MiniLM runs through) on the tiny
    // weights: external data read straight from model.safetensors.
    runtime();
    let exp = expected("tiny-bert");
    let cfg = OnnxEncoderConfig {
        model_file: Some("graph.onnx".into()),
        ..OnnxEncoderConfig::new(data("tiny-bert"))
    };
    let enc = OnnxSentenceEncoder::load(&cfg).unwrap();
    check_against(&enc, &exp, "safetensors graph");
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn batching_does_not_leak_padding_and_threads_change_nothing() {
    runtime();
    let exp = expected("tiny-bert");
    let texts: Vec<&str> = exp.texts.iter().map(String::as_str).collect();
    let enc = OnnxSentenceEncoder::load(&OnnxEncoderConfig {
        session: SessionOptions::with_threads(1),
        ..OnnxEncoderConfig::new(data("tiny-bert"))
    })
    .unwrap();
    assert_eq!(enc.threads(), 1);
    let batch = enc.encode(&texts).unwrap();
    for (t, b) in texts.iter().zip(&batch) {
        let alone = enc.encode(&[t]).unwrap();
        assert!(
            max_abs(&alone[0], b) < 1e-5,
            "{t}: {}",
            max_abs(&alone[0], b)
        );
    }
    let two = OnnxSentenceEncoder::load(&OnnxEncoderConfig {
        session: SessionOptions::with_threads(2),
        ..OnnxEncoderConfig::new(data("tiny-bert"))
    })
    .unwrap();
    for (a, b) in two.encode(&texts).unwrap().iter().zip(&batch) {
        assert!(max_abs(a, b) < 1e-6);
    }
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn real_minilm_matches_torch_and_candle() {
    let assets = runtime();
    let exp = expected("all-minilm-l6-v2");
    let enc = OnnxSentenceEncoder::load(&OnnxEncoderConfig::new(&assets.minilm_onnx_dir)).unwrap();
    assert_eq!(enc.dim(), 384);
    check_against(&enc, &exp, "all-MiniLM-L6-v2");
    let texts: Vec<&str> = exp.texts.iter().map(String::as_str).collect();
    let theirs = candle_embed(&assets.minilm_dir, &texts);
    for (k, (a, b)) in enc.encode(&texts).unwrap().iter().zip(&theirs).enumerate() {
        let c = cosine(a, b);
        assert!(c >= 0.99999, "ort vs candle, text {k}: {c}");
    }
}

#[test]
#[ignore = "needs assets: scripts/fetch-assets.sh"]
fn wrong_models_are_clear_errors() {
    runtime();
    // An image encoder where a sentence encoder belongs.
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(
        data("tiny-clip/onnx/vision_model.onnx"),
        dir.path().join("model.onnx"),
    )
    .unwrap();
    std::fs::copy(
        data("tiny-bert/tokenizer.json"),
        dir.path().join("tokenizer.json"),
    )
    .unwrap();
    let e = LabelerError::from(
        OnnxSentenceEncoder::load(&OnnxEncoderConfig::new(dir.path())).unwrap_err(),
    );
    assert_eq!(e.kind(), LabelerErrorKind::Model, "{e}");
    assert!(e.to_string().contains("pixel_values"), "{e}");

    // A graph whose external weights are missing.
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(data("tiny-bert/graph.onnx"), dir.path().join("model.onnx")).unwrap();
    std::fs::copy(
        data("tiny-bert/tokenizer.json"),
        dir.path().join("tokenizer.json"),
    )
    .unwrap();
    let e = LabelerError::from(
        OnnxSentenceEncoder::load(&OnnxEncoderConfig::new(dir.path())).unwrap_err(),
    );
    assert_eq!(e.kind(), LabelerErrorKind::Model, "{e}");
    assert!(e.to_string().contains("model.safetensors"), "{e}");

    // ... or symlinked from elsewhere: ONNX Runtime refuses, and the message says what to do.
    #[cfg(unix)]
    {
        std::os::unix::fs::symlink(
            data("tiny-bert/model.safetensors"),
            dir.path().join("model.safetensors"),
        )
        .unwrap();
        let e = LabelerError::from(
            OnnxSentenceEncoder::load(&OnnxEncoderConfig::new(dir.path())).unwrap_err(),
        );
        assert!(e.to_string().contains("hard link"), "{e}");
    }

    // A corrupt tokenizer.
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(data("tiny-bert/model.onnx"), dir.path().join("model.onnx")).unwrap();
    std::fs::write(dir.path().join("tokenizer.json"), "{").unwrap();
    let e = LabelerError::from(
        OnnxSentenceEncoder::load(&OnnxEncoderConfig::new(dir.path())).unwrap_err(),
    );
    assert_eq!(e.kind(), LabelerErrorKind::Tokenizer, "{e}");
}
