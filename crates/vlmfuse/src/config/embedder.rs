//! `[embedder]`: the CLIP image tower that gives each clip its context vector.

use serde::{Deserialize, Serialize};
use vlmfuse_models::WeightSource;

/// Absent from the config: /v1/infer answers 503 (a context is never invented).
#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EmbedderConfig {
    /// `{ path = "/models/clip" }` or `{ hub = "openai/clip-vit-base-patch32", revision = "main" }`
    /// (file only: a model's location is part of the deployment, not a per-run switch).
    #[arg(skip = WeightSource::local(""))]
    pub weights: WeightSource,
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
