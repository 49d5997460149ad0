//! Loading a Qwen3-VL checkpoint: config (normalised from the HF layout), weights (with any
//! LoRA adapter merged), tokenizer, processor statistics and end-of-sequence ids.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use candle_transformers::models::qwen3_vl::{Config as QwenConfig, Qwen3VLModel};
use tokenizers::Tokenizer;

use super::config::{parse_dtype, CandleVlmConfig};
use super::video::{VideoProcessor, QWEN_DEFAULT_MEAN, QWEN_DEFAULT_STD};
use crate::lora::{load_adapter, merge_adapter};
use crate::{parse_device, ModelError};

/// Loaded weights, tokenizer and processor of one Qwen3-VL. Immutable after load; a model is
/// instantiated per generation (see the module docs).
pub struct QwenVlEngine {
    pub(super) tensors: HashMap<String, Tensor>,
    pub(super) config: QwenConfig,
    pub(super) tokenizer: Tokenizer,
    pub(super) device: Device,
    pub(super) dtype: DType,
    pub(super) video: VideoProcessor,
    pub(super) eos: Vec<u32>,
    pub(super) merged_lora: Vec<String>,
    pub(super) model_id: String,
}

/// Fills the fields candle's `TextConfig` requires but that HF configs put elsewhere or omit
/// (`tie_word_embeddings` at top level, `rope_theta` inside `rope_parameters` in newer
/// transformers), so real checkpoints load unmodified.
fn normalise_config(mut v: serde_json::Value) -> Result<QwenConfig, ModelError> {
    let top_tie = v.get("tie_word_embeddings").cloned();
    let tc = v
        .get_mut("text_config")
        .and_then(|t| t.as_object_mut())
        .ok_or_else(|| ModelError::BadConfig("config.json has no `text_config`".into()))?;
    if !tc.contains_key("tie_word_embeddings") {
        tc.insert(
            "tie_word_embeddings".into(),
            top_tie.unwrap_or(serde_json::Value::Bool(false)),
        );
    }
    if !tc.contains_key("rope_theta") {
        let theta = tc
            .get("rope_parameters")
            .and_then(|r| r.get("rope_theta"))
            .cloned()
            .unwrap_or(serde_json::json!(5_000_000.0));
        tc.insert("rope_theta".into(), theta);
    }
    if !tc.contains_key("head_dim") {
        let h = tc.get("hidden_size").and_then(|x| x.as_u64());
        let n = tc.get("num_attention_heads").and_then(|x| x.as_u64());
        if let Some(d) = h.zip(n).and_then(|(h, n)| h.checked_div(n)) {
            tc.insert("head_dim".into(), serde_json::json!(d));
        }
    }
    tc.entry("hidden_act").or_insert(serde_json::json!("silu"));
    tc.entry("rms_norm_eps").or_insert(serde_json::json!(1e-6));
    tc.entry("max_position_embeddings")
        .or_insert(serde_json::json!(262_144));
    serde_json::from_value(v).map_err(|e| ModelError::BadConfig(format!("Qwen3-VL config: {e}")))
}

/// `eos_token_id` may be a number or a list.
fn ids_of(v: Option<&serde_json::Value>) -> Vec<u32> {
    match v {
        Some(serde_json::Value::Number(n)) => {
            n.as_u64().map(|x| vec![x as u32]).unwrap_or_default()
        }
        Some(serde_json::Value::Array(a)) => a
            .iter()
            .filter_map(|x| x.as_u64().map(|x| x as u32))
            .collect(),
        _ => Vec::new(),
    }
}

fn load_tensors(files: &[std::path::PathBuf]) -> Result<HashMap<String, Tensor>, ModelError> {
    let mut all = HashMap::new();
    for f in files {
        let t = candle_core::safetensors::load(f, &Device::Cpu).map_err(|e| {
            ModelError::BadWeights {
                path: f.clone(),
                reason: e.to_string(),
            }
        })?;
        all.extend(t);
    }
    Ok(all)
}

pub(super) fn tok_err(e: impl std::fmt::Display) -> ModelError {
    ModelError::BadConfig(format!("tokenizer: {e}"))
}

impl QwenVlEngine {
    /// Reads config, weights (merging the adapter, if any), tokenizer and processor settings.
    /// Blocking and slow for real checkpoints: call it at startup or in `spawn_blocking`.
    pub fn load(cfg: &CandleVlmConfig) -> Result<Self, ModelError> {
        let device = parse_device(&cfg.device)?;
        let dtype = parse_dtype(cfg.dtype.as_deref(), &device)?;
        let raw: serde_json::Value = cfg.weights.read_json("config.json")?;
        let config = normalise_config(raw.clone())?;

        let files = cfg.weights.safetensors_files()?;
        let mut tensors = load_tensors(&files)?;
        let mut merged_lora = Vec::new();
        if let Some(adapter) = &cfg.adapter {
            let (lcfg, lt) = load_adapter(adapter)?;
            merged_lora = merge_adapter(&mut tensors, &lt, &lcfg).map_err(|e| match e {
                ModelError::BadWeights { reason, .. } => ModelError::BadWeights {
                    path: adapter
                        .resolve("adapter_model.safetensors")
                        .unwrap_or_default(),
                    reason,
                },
                other => other,
            })?;
            tracing::info!(
                reporter = %cfg.name,
                adapter = %adapter.describe(),
                modules = merged_lora.len(),
                "merged LoRA adapter"
            );
        }
        // candle builds an untied `lm_head` with a bias that Qwen checkpoints (8B and up,
        // untied) do not have; a zero bias is the same function.
        if !config.text_config.tie_word_embeddings && !tensors.contains_key("lm_head.bias") {
            if let Some(w) = tensors.get("lm_head.weight") {
                let bias = Tensor::zeros(w.dim(0)?, w.dtype(), w.device())?;
                tensors.insert("lm_head.bias".into(), bias);
            }
        }
        let tensors = tensors
            .into_iter()
            .map(|(k, t)| {
                // Integer tensors (none in Qwen3-VL today) must keep their dtype.
                let t = if t.dtype().is_float() {
                    t.to_dtype(dtype)?
                } else {
                    t
                };
                Ok((k, t.to_device(&device)?))
            })
            .collect::<Result<HashMap<_, _>, candle_core::Error>>()?;

        let tok_path = cfg.weights.resolve("tokenizer.json")?;
        let tokenizer = Tokenizer::from_file(&tok_path).map_err(|e| ModelError::BadWeights {
            path: tok_path.clone(),
            reason: e.to_string(),
        })?;

        // Statistics from the checkpoint's processor config (video first: Qwen3-VL ships both).
        let mut mean = QWEN_DEFAULT_MEAN;
        let mut std = QWEN_DEFAULT_STD;
        for f in ["video_preprocessor_config.json", "preprocessor_config.json"] {
            if cfg.weights.resolve_optional(f)?.is_some() {
                let p: serde_json::Value = cfg.weights.read_json(f)?;
                let triple = |k: &str| -> Option<[f32; 3]> {
                    let a = p.get(k)?.as_array()?;
                    if a.len() != 3 {
                        return None;
                    }
                    Some([
                        a[0].as_f64()? as f32,
                        a[1].as_f64()? as f32,
                        a[2].as_f64()? as f32,
                    ])
                };
                if let (Some(m), Some(s)) = (triple("image_mean"), triple("image_std")) {
                    mean = m;
                    std = s;
                    break;
                }
            }
        }
        let vc = &config.vision_config;
        let video = VideoProcessor {
            patch_size: vc.patch_size,
            temporal_patch_size: vc.temporal_patch_size,
            merge_size: vc.spatial_merge_size,
            mean,
            std,
            min_pixels: cfg.min_pixels,
            max_pixels: cfg.max_pixels,
        };
        if vc.temporal_patch_size != 2 {
            // candle's patch embedding splits the 3-D conv into exactly two 2-D convs.
            return Err(ModelError::BadConfig(format!(
                "temporal_patch_size {} is not supported by candle's qwen3_vl (needs 2)",
                vc.temporal_patch_size
            )));
        }

        let mut eos = Vec::new();
        if cfg
            .weights
            .resolve_optional("generation_config.json")?
            .is_some()
        {
            let g: serde_json::Value = cfg.weights.read_json("generation_config.json")?;
            eos.extend(ids_of(g.get("eos_token_id")));
        }
        if eos.is_empty() {
            eos.extend(ids_of(raw.get("eos_token_id")));
            eos.extend(ids_of(
                raw.get("text_config").and_then(|t| t.get("eos_token_id")),
            ));
        }
        // Chat models end their turn with <|im_end|> even where configs list only <|endoftext|>.
        if let Some(id) = tokenizer.token_to_id("<|im_end|>") {
            eos.push(id);
        }
        eos.sort_unstable();
        eos.dedup();
        for tok in ["<|im_start|>", "<|vision_start|>", "<|vision_end|>"] {
            if tokenizer.token_to_id(tok).is_none() {
                return Err(ModelError::BadConfig(format!(
                    "tokenizer at {} lacks `{tok}`",
                    tok_path.display()
                )));
            }
        }

        let engine = Self {
            tensors,
            config,
            tokenizer,
            device,
            dtype,
            video,
            eos,
            merged_lora,
            model_id: cfg.weights.describe(),
        };
        // Fail at startup, not on the first clip, if the weights do not fit the config.
        engine.build_model(16)?;
        Ok(engine)
    }

    /// A weight as the model sees it (after any LoRA merge, in the model's dtype and device).
    pub fn tensor(&self, key: &str) -> Option<&Tensor> {
        self.tensors.get(key)
    }

    /// Base weight keys the adapter changed.
    pub fn merged_lora_keys(&self) -> &[String] {
        &self.merged_lora
    }

    pub fn eos_ids(&self) -> &[u32] {
        &self.eos
    }

    pub fn video_processor(&self) -> &VideoProcessor {
        &self.video
    }

    pub fn tokenizer(&self) -> &Tokenizer {
        &self.tokenizer
    }

    pub(super) fn build_model(&self, max_positions: usize) -> Result<Qwen3VLModel, ModelError> {
        let mut cfg = self.config.clone();
        cfg.text_config.max_position_embeddings = max_positions.max(1);
        let vb = VarBuilder::from_tensors(self.tensors.clone(), self.dtype, &self.device);
        Qwen3VLModel::new(&cfg, vb).map_err(|e| ModelError::BadWeights {
            path: self.model_id.clone().into(),
            reason: e.to_string(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eos_ids_accept_number_or_list() {
        assert_eq!(ids_of(Some(&serde_json::json!(5))), vec![5]);
        assert_eq!(ids_of(Some(&serde_json::json!([1, 2]))), vec![1, 2]);
        assert!(ids_of(None).is_empty());
    }

    #[test]
    fn config_fields_are_filled_from_hf_layout() {
        let v = serde_json::json!({
            "tie_word_embeddings": true,
            "image_token_id": 1, "video_token_id": 2,
            "vision_start_token_id": 3, "vision_end_token_id": 4,
            "vision_config": {},
            "text_config": {
                "vocab_size": 10, "hidden_size": 8, "intermediate_size": 16,
                "num_hidden_layers": 1, "num_attention_heads": 2, "num_key_value_heads": 1,
                "rope_parameters": {"rope_theta": 1000.0}
            }
        });
        let c = normalise_config(v).unwrap();
        assert!(c.text_config.tie_word_embeddings);
        assert_eq!(c.text_config.rope_theta, 1000.0);
        assert_eq!(c.text_config.head_dim, 4);
        assert!(normalise_config(serde_json::json!({})).is_err());
    }
}
