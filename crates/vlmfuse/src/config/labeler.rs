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

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EmbeddingLabelerConfig {
    /// The MiniLM directory; unset: `minilm` under the asset cache (scripts/fetch-assets.sh).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_dir: Option<PathBuf>,
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
