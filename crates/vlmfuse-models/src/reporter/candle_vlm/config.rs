//! `[[reporter]] kind = "candle"`: the settings of one in-process VLM. The architecture is not a
//! setting: `config.json`'s `model_type` names it, and the checkpoint's processor config decides
//! the pixel budget, frame sampling and normalisation, as it does in transformers.

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
/// Qwen3-VL's frames per clip when `frames` is unset and its checkpoint's sampler cannot run
/// (frames given without a clip to decode them from, e.g. `trace` on frames in a test).
pub const DEFAULT_QWEN_FRAMES: usize = 8;

/// One in-process VLM reporter (Qwen3-VL or VideoLLaVA), as written in the service config.
///
/// Deserialised through [`RawCandleVlmConfig`] so that a config written for the old
/// candle-transformers path (`causal_prefill`, `max_pixels`, `min_pixels`) fails with a message
/// saying what replaced those fields, instead of being silently ignored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RawCandleVlmConfig")]
pub struct CandleVlmConfig {
    /// Reporter name in results and logs.
    pub name: String,
    /// Directory or HF-cache entry with `config.json`, `model.safetensors` (or shards),
    /// `tokenizer.json` and the processor configs.
    pub weights: WeightSource,
    /// PEFT LoRA adapter merged into the weights at load.
    pub adapter: Option<WeightSource>,
    /// `"cpu"`, `"cuda"` or `"cuda:N"`.
    pub device: String,
    /// `"f32"`, `"bf16"` or `"f16"`; unset means f32 on CPU (candle's CPU half-precision
    /// matmuls are slower than f32 and lose accuracy for nothing) and bf16 on CUDA.
    pub dtype: Option<String>,
    pub max_new_tokens: usize,
    /// Unset or 0: greedy, so a clip's report is reproducible.
    pub temperature: Option<f64>,
    pub top_p: Option<f64>,
    pub seed: u64,
    /// The user's question; the architecture's chat format is put around it.
    pub prompt: String,
    /// Qwen3-VL: unset (the default), the frames its checkpoint's video processor samples
    /// (`fps`, `min_frames`, `max_frames` or `num_frames`, as transformers picks frame indices),
    /// decoded from the clip at source resolution; set, at most this many of the clip's `[media]`
    /// frames, spread evenly. Each goes with its presentation time (the prompt states the
    /// times). Refused for VideoLLaVA, whose processor's `num_frames` (8) is what the model was
    /// trained with.
    pub frames: Option<usize>,
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
            frames: None,
        }
    }
}

/// The wire form of [`CandleVlmConfig`]: every current field plus the removed ones, so their
/// presence can be refused with an explanation.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
#[doc(hidden)]
pub struct RawCandleVlmConfig {
    name: String,
    weights: WeightSource,
    #[serde(default)]
    adapter: Option<WeightSource>,
    #[serde(default = "default_device")]
    device: String,
    #[serde(default)]
    dtype: Option<String>,
    #[serde(default = "default_max_new_tokens")]
    max_new_tokens: usize,
    #[serde(default)]
    temperature: Option<f64>,
    #[serde(default)]
    top_p: Option<f64>,
    #[serde(default)]
    seed: u64,
    #[serde(default = "default_prompt")]
    prompt: String,
    #[serde(default)]
    frames: Option<usize>,
    #[serde(default)]
    causal_prefill: Option<serde::de::IgnoredAny>,
    #[serde(default)]
    max_pixels: Option<serde::de::IgnoredAny>,
    #[serde(default)]
    min_pixels: Option<serde::de::IgnoredAny>,
}

impl TryFrom<RawCandleVlmConfig> for CandleVlmConfig {
    type Error = String;

    fn try_from(r: RawCandleVlmConfig) -> Result<Self, String> {
        let removed: Vec<&str> = [
            ("causal_prefill", r.causal_prefill.is_some()),
            ("max_pixels", r.max_pixels.is_some()),
            ("min_pixels", r.min_pixels.is_some()),
        ]
        .into_iter()
        .filter_map(|(k, set)| set.then_some(k))
        .collect();
        if !removed.is_empty() {
            return Err(format!(
                "reporter `{}`: {} no longer exist{}: the checkpoint's processor config \
                 (video_preprocessor_config.json / preprocessor_config.json) now decides the \
                 pixel budget and frame sampling, and the prompt is always prefilled in one \
                 causal pass; remove {}",
                r.name,
                removed
                    .iter()
                    .map(|k| format!("`{k}`"))
                    .collect::<Vec<_>>()
                    .join(", "),
                if removed.len() == 1 { "s" } else { "" },
                if removed.len() == 1 { "it" } else { "them" },
            ));
        }
        Ok(Self {
            name: r.name,
            weights: r.weights,
            adapter: r.adapter,
            device: r.device,
            dtype: r.dtype,
            max_new_tokens: r.max_new_tokens,
            temperature: r.temperature,
            top_p: r.top_p,
            seed: r.seed,
            prompt: r.prompt,
            frames: r.frames,
        })
    }
}

/// The dtype a reporter runs in: the configured one, else f32 on CPU and bf16 on CUDA.
pub fn parse_dtype(s: Option<&str>, device: &Device) -> Result<DType, ModelError> {
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
    fn config_defaults_from_json() {
        let c: CandleVlmConfig =
            serde_json::from_str(r#"{"name":"q","weights":{"path":"/m"}}"#).unwrap();
        assert_eq!(c, CandleVlmConfig::new("q", WeightSource::local("/m")));
        assert_eq!(c.prompt, DEFAULT_PROMPT);
        assert!(c.temperature.is_none());
        assert_eq!(c.frames, None);
    }

    #[test]
    fn removed_fields_are_refused_with_the_reason() {
        for (field, value) in [
            ("causal_prefill", "true"),
            ("max_pixels", "1024"),
            ("min_pixels", "16"),
        ] {
            let e = serde_json::from_str::<CandleVlmConfig>(&format!(
                r#"{{"name":"q","weights":{{"path":"/m"}},"{field}":{value}}}"#
            ))
            .unwrap_err()
            .to_string();
            assert!(e.contains(field), "{e}");
            assert!(e.contains("processor config"), "{e}");
        }
        let e = serde_json::from_str::<CandleVlmConfig>(
            r#"{"name":"q","weights":{"path":"/m"},"max_pixels":1,"min_pixels":1}"#,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("`max_pixels`, `min_pixels` no longer exist"),
            "{e}"
        );
    }

    #[test]
    fn dtype_defaults_per_device() {
        assert_eq!(parse_dtype(None, &Device::Cpu).unwrap(), DType::F32);
        assert_eq!(
            parse_dtype(Some("BF16"), &Device::Cpu).unwrap(),
            DType::BF16
        );
        assert_eq!(
            parse_dtype(Some("float16"), &Device::Cpu).unwrap(),
            DType::F16
        );
        assert!(parse_dtype(Some("f8"), &Device::Cpu).is_err());
    }
}
