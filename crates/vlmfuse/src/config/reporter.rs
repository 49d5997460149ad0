//! `[[reporter]]`: the VLMs /v1/infer runs, each a backend (`kind`) plus its round timeout.

use serde::{Deserialize, Serialize};

/// One `[[reporter]]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReporterEntry {
    /// Seconds this reporter may take in a round (retries included) before it is left out.
    #[serde(default = "default_reporter_timeout")]
    pub round_timeout_s: f64,
    #[serde(flatten)]
    pub backend: ReporterBackend,
}

fn default_reporter_timeout() -> f64 {
    120.0
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum ReporterBackend {
    /// Any OpenAI-compatible chat-completions server (vLLM, SGLang, llama.cpp, ...).
    Openai(vlmfuse_models::OpenAiReporterConfig),
    /// In-process Qwen3-VL on candle.
    Candle(vlmfuse_models::CandleVlmConfig),
}

impl ReporterEntry {
    pub fn name(&self) -> String {
        match &self.backend {
            ReporterBackend::Openai(c) => c.name.clone().unwrap_or_else(|| c.model.clone()),
            ReporterBackend::Candle(c) => c.name.clone(),
        }
    }
}
