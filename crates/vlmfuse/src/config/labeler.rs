//! `[labeler]`: which backend maps reporter text to ontology labels. A tagged enum like
//! `[[reporter]]`: each kind has only the fields that mean something for it, so a field of
//! another kind is a typo the parser reports, not a setting silently ignored.

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum LabelerConfig {
    /// The offline default: the annotation guidelines' rules plus all-MiniLM-L6-v2 paraphrase
    /// matching for what the rules do not list.
    Embedding(EmbeddingLabelerConfig),
    /// Any OpenAI-compatible LLM asked for JSON restricted to the ontology.
    Openai(OpenAiLabelerConfig),
    /// An in-process instruct LLM (GGUF: Llama 3.x, Qwen2/3, Gemma 3) whose decoding is
    /// constrained to a valid list of ontology ids.
    Gguf(GgufLabelerConfig),
}

impl Default for LabelerConfig {
    fn default() -> Self {
        LabelerConfig::Embedding(EmbeddingLabelerConfig::default())
    }
}

/// The engine that runs the embedding labeler's sentence encoder. The matcher is the same; on
/// the test split both give the same labels, and ONNX Runtime is about 3x faster per round on
/// CPU (README, "Labelers").
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum EncoderEngine {
    /// ONNX Runtime (the library fetched by scripts/fetch-assets.sh, or `$ORT_DYLIB_PATH`).
    #[default]
    Onnx,
    /// candle, from `model.safetensors`: no native library needed.
    Candle,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EmbeddingLabelerConfig {
    /// Which engine runs the encoder.
    #[serde(default)]
    pub encoder: EncoderEngine,
    /// The MiniLM directory (`model.onnx` for onnx, `model.safetensors` for candle, and
    /// `tokenizer.json`); unset: `minilm-onnx` or `minilm` under the asset cache
    /// (scripts/fetch-assets.sh).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_dir: Option<PathBuf>,
    /// onnx: intra-op threads of the encoder; unset: the core count.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub threads: Option<usize>,
    /// Cosine threshold for labels without a tuned one (labels the paper's ontology does not
    /// have); unset: the default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub threshold: Option<f32>,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GgufLabelerConfig {
    /// The model file; unset: the fetched gemma-3-270m under the asset cache.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_path: Option<PathBuf>,
    /// A Jinja chat template that replaces the file's (for files with a broken or missing one);
    /// unset: the file's, else the family's turn format. There is no threshold: the model writes
    /// the label list itself.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chat_template: Option<String>,
    /// Tokens of an answer the model reads; longer answers keep their first ones. Unset: 512.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_answer_tokens: Option<usize>,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OpenAiLabelerConfig {
    /// Server base URL; unset: the labeler's default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base_url: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    /// Name of the environment variable holding the API key (never the key itself).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub api_key_env: Option<String>,
    /// Ask for `response_format: json_object`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub json_mode: Option<bool>,
    /// Seconds per request.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub timeout_s: Option<f64>,
}

impl LabelerConfig {
    /// `embedding`, `openai` or `gguf`, as the config spells it.
    pub fn kind(&self) -> &'static str {
        match self {
            LabelerConfig::Embedding(_) => "embedding",
            LabelerConfig::Openai(_) => "openai",
            LabelerConfig::Gguf(_) => "gguf",
        }
    }
}
