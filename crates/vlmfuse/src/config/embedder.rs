//! `[embedder]`: the CLIP image tower that gives each clip its context vector.

use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use vlmfuse_models::WeightSource;

/// Which runtime runs the CLIP image tower.
#[derive(clap::ValueEnum, Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum EmbedderBackend {
    /// candle on `config.json` + `model.safetensors` (CPU or CUDA).
    #[default]
    Candle,
    /// ONNX Runtime on an ONNX export (a vision-tower or whole-CLIPModel graph) with its
    /// `preprocessor_config.json`; CPU. Faster than candle on CPU (see README).
    Onnx,
}

/// Absent from the config: /v1/infer answers 503 (a context is never invented).
#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EmbedderConfig {
    /// `{ path = "/models/clip" }` or `{ hub = "openai/clip-vit-base-patch32", revision = "main" }`
    /// (file only: a model's location is part of the deployment, not a per-run switch).
    #[arg(skip = WeightSource::local(""))]
    pub weights: WeightSource,
    /// "candle" (safetensors, CPU or CUDA) or "onnx" (an ONNX export on ONNX Runtime, CPU).
    /// No clap default: a default counts as "given" when the flags are layered over the file,
    /// and would switch a file's `backend = "onnx"` back to candle (the serde default applies).
    #[arg(
        long = "embedder-backend",
        env = "VLMFUSE_EMBEDDER_BACKEND",
        value_enum,
        required = false
    )]
    #[serde(default)]
    pub backend: EmbedderBackend,
    /// onnx: the ONNX file inside `weights` when it is not `model.onnx`, `vision_model.onnx` or
    /// `onnx/…` (for example "onnx/vision_model_fp16.onnx"). File only.
    #[arg(skip)]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_file: Option<String>,
    /// onnx: intra-op threads of the session (unset: one per core).
    #[arg(
        long = "embedder-threads",
        env = "VLMFUSE_EMBEDDER_THREADS",
        required = false
    )]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub threads: Option<usize>,
    /// onnx: `libonnxruntime.so` to load (unset: `ORT_DYLIB_PATH`, else the asset cache that
    /// scripts/fetch-assets.sh fills). File only.
    #[arg(skip)]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub onnx_library: Option<PathBuf>,
    /// The embedder's device, "cpu", "cuda" or "cuda:N" (CUDA needs the `cuda` build feature);
    /// applies when an [embedder] is configured.
    #[arg(
        long = "embedder-device",
        env = "VLMFUSE_EMBEDDER_DEVICE",
        required = false
    )]
    #[serde(default = "cpu")]
    pub device: String,
}

fn cpu() -> String {
    "cpu".into()
}
