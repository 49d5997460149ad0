//! `[[reporter]] kind = "candle"`: the settings of one in-process Qwen3-VL.

use candle_core::{DType, Device};
use serde::{Deserialize, Serialize};

use crate::reporter::DEFAULT_PROMPT;
use crate::weights::WeightSource;
use crate::ModelError;

fn default_device() -> String {
    "cpu".into()
}
fn default_max_new_tokens() -> usize {
    512
}
fn default_prompt() -> String {
    DEFAULT_PROMPT.into()
}
fn default_frames() -> usize {
    8
}
fn default_max_pixels() -> usize {
    640 * 360
}
fn default_min_pixels() -> usize {
    64 * 64
}
fn default_true() -> bool {
    true
}

/// One in-process Qwen3-VL reporter, as written in the service config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CandleVlmConfig {
    /// Reporter name in results and logs.
    pub name: String,
    /// Directory or HF-cache entry with `config.json`, `model.safetensors` (or shards) and
    /// `tokenizer.json`.
    pub weights: WeightSource,
    /// PEFT LoRA adapter merged into the weights at load.
    #[serde(default)]
    pub adapter: Option<WeightSource>,
    /// `"cpu"`, `"cuda"` or `"cuda:N"`.
    #[serde(default = "default_device")]
    pub device: String,
    /// `"f32"`, `"bf16"` or `"f16"`; unset means f32 on CPU (candle's CPU bf16 matmuls are
    /// slow) and bf16 on CUDA.
    #[serde(default)]
    pub dtype: Option<String>,
    #[serde(default = "default_max_new_tokens")]
    pub max_new_tokens: usize,
    /// Unset or 0: greedy, so a clip's report is reproducible.
    #[serde(default)]
    pub temperature: Option<f64>,
    #[serde(default)]
    pub top_p: Option<f64>,
    #[serde(default)]
    pub seed: u64,
    #[serde(default = "default_prompt")]
    pub prompt: String,
    /// At most this many of the clip's sampled frames go to the model (spread evenly).
    #[serde(default = "default_frames")]
    pub frames: usize,
    /// Per-frame pixel budget after resizing; bounds the visual token count.
    #[serde(default = "default_max_pixels")]
    pub max_pixels: usize,
    #[serde(default = "default_min_pixels")]
    pub min_pixels: usize,
    /// Feed prompt text one token at a time so attention is causal as in training. candle's
    /// multi-token forward attends bidirectionally; `false` trades that fidelity for a faster
    /// prefill (the video span is always one chunk, since its embeddings go in together).
    #[serde(default = "default_true")]
    pub causal_prefill: bool,
}

impl CandleVlmConfig {
    pub fn new(name: impl Into<String>, weights: WeightSource) -> Self {
        Self {
            name: name.into(),
            weights,
            adapter: None,
            device: default_device(),
            dtype: None,
            max_new_tokens: default_max_new_tokens(),
            temperature: None,
            top_p: None,
            seed: 0,
            prompt: default_prompt(),
            frames: default_frames(),
            max_pixels: default_max_pixels(),
            min_pixels: default_min_pixels(),
            causal_prefill: true,
        }
    }
}

pub(super) fn parse_dtype(s: Option<&str>, device: &Device) -> Result<DType, ModelError> {
    match s.map(|s| s.trim().to_ascii_lowercase()) {
        None => Ok(if device.is_cpu() {
            DType::F32
        } else {
            DType::BF16
        }),
        Some(s) => match s.as_str() {
            "f32" | "float32" => Ok(DType::F32),
            "bf16" | "bfloat16" => Ok(DType::BF16),
            "f16" | "float16" => Ok(DType::F16),
            other => Err(ModelError::BadConfig(format!(
                "dtype `{other}`; expected f32, bf16 or f16"
            ))),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_defaults_from_toml_like_json() {
        let c: CandleVlmConfig =
            serde_json::from_str(r#"{"name":"q","weights":{"path":"/m"}}"#).unwrap();
        assert_eq!(c, CandleVlmConfig::new("q", WeightSource::local("/m")));
        assert_eq!(c.prompt, DEFAULT_PROMPT);
        assert!(c.causal_prefill && c.temperature.is_none());
    }

    #[test]
    fn dtype_defaults_per_device() {
        assert_eq!(parse_dtype(None, &Device::Cpu).unwrap(), DType::F32);
        assert_eq!(
            parse_dtype(Some("BF16"), &Device::Cpu).unwrap(),
            DType::BF16
        );
        assert!(parse_dtype(Some("f8"), &Device::Cpu).is_err());
    }
}
