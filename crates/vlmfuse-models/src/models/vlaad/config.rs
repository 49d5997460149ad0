//! VLAAD's `config.json`. Video-LLaMA (the layout VLAAD is trained in) keeps its architecture
//! in code and its files in a YAML run config; this file names the same files and, where a
//! checkpoint differs from the released architecture, the sizes. Every size defaults to the
//! released model (EVA ViT-g/14 at 224 px without its last layer, BLIP-2's 32-query
//! Q-Former, a 2-layer video Q-Former over 32 frame positions, LLaMA-2-7B-chat).
//!
//! ```json
//! { "model_type": "vlaad",
//!   "llama_model": "llama-2-7b-chat-hf",
//!   "ckpt": "checkpoint_2.pth",
//!   "q_former_model": "blip2_pretrained_flant5xxl.pth",
//!   "vit_model": "eva_vit_g.pth" }
//! ```
//! Paths are relative to the directory holding `config.json` (or absolute).

use serde::Deserialize;

use crate::ModelError;

/// The `model_type`s this family answers to.
pub const MODEL_TYPES: [&str; 2] = ["vlaad", "video_llama"];

/// The demo's system turn for video (`demo_video.py`).
pub const DEFAULT_SYSTEM: &str = "You are able to understand the visual content that the user \
provides. Follow the instructions carefully and explain your answers in detail.";

/// EVA ViT-g as `create_eva_vit_g` builds it.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default)]
pub struct EvaConfig {
    pub embed_dim: usize,
    pub depth: usize,
    pub num_heads: usize,
    pub mlp_ratio: f64,
    pub patch_size: usize,
    pub layer_norm_eps: f64,
}

impl Default for EvaConfig {
    fn default() -> Self {
        Self {
            embed_dim: 1408,
            depth: 39,
            num_heads: 16,
            mlp_ratio: 4.3637,
            patch_size: 14,
            layer_norm_eps: 1e-6,
        }
    }
}

impl EvaConfig {
    /// `int(dim * mlp_ratio)`, as Python truncates it.
    pub fn mlp_hidden(&self) -> usize {
        (self.embed_dim as f64 * self.mlp_ratio) as usize
    }
}

/// The BERT of the Q-Formers (`bert-base-uncased`'s sizes).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default)]
pub struct QformerConfig {
    pub hidden_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub intermediate_size: usize,
    pub layer_norm_eps: f64,
    pub cross_attention_freq: usize,
}

impl Default for QformerConfig {
    fn default() -> Self {
        Self {
            hidden_size: 768,
            num_hidden_layers: 12,
            num_attention_heads: 12,
            intermediate_size: 3072,
            layer_norm_eps: 1e-12,
            cross_attention_freq: 2,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default)]
pub struct VlaadConfig {
    pub model_type: String,
    /// The LLaMA checkpoint directory (transformers layout).
    pub llama_model: String,
    /// The fine-tuned run (`{"model": state_dict}`: video Q-Former, frame positions,
    /// `llama_proj`).
    pub ckpt: String,
    /// BLIP-2's checkpoint (`{"model": …}`: `Qformer`, `query_tokens`, `ln_vision`, and the
    /// ViT if it carries one).
    pub q_former_model: String,
    /// EVA ViT-g's own weights (`eva_vit_g.pth`, flat); optional when `q_former_model`
    /// carries `visual_encoder.*`.
    pub vit_model: Option<String>,
    pub img_size: usize,
    pub n_frms: usize,
    pub num_query_token: usize,
    pub num_video_query_token: usize,
    pub max_frame_pos: usize,
    pub video_qformer_layers: usize,
    pub vit: EvaConfig,
    pub qformer: QformerConfig,
    /// The system turn of the LLaMA-2 conversation.
    pub system: String,
}

impl Default for VlaadConfig {
    fn default() -> Self {
        Self {
            model_type: "vlaad".into(),
            llama_model: String::new(),
            ckpt: String::new(),
            q_former_model: String::new(),
            vit_model: None,
            img_size: 224,
            n_frms: 8,
            num_query_token: 32,
            num_video_query_token: 32,
            max_frame_pos: 32,
            video_qformer_layers: 2,
            vit: EvaConfig::default(),
            qformer: QformerConfig::default(),
            system: DEFAULT_SYSTEM.into(),
        }
    }
}

impl VlaadConfig {
    pub fn from_json(v: &serde_json::Value) -> Result<Self, ModelError> {
        let c: VlaadConfig = serde_json::from_value(v.clone())
            .map_err(|e| ModelError::BadConfig(format!("config.json: {e}")))?;
        if !MODEL_TYPES.contains(&c.model_type.as_str()) {
            return Err(ModelError::BadConfig(format!(
                "config.json has model_type `{}`, not one of {MODEL_TYPES:?}",
                c.model_type
            )));
        }
        for (k, s) in [
            ("llama_model", &c.llama_model),
            ("ckpt", &c.ckpt),
            ("q_former_model", &c.q_former_model),
        ] {
            if s.is_empty() {
                return Err(ModelError::BadConfig(format!(
                    "config.json: `{k}` is required (a path relative to the checkpoint directory)"
                )));
            }
        }
        let e = &c.vit;
        if e.patch_size == 0 || !c.img_size.is_multiple_of(e.patch_size) {
            return Err(ModelError::BadConfig(format!(
                "img_size {} is not a multiple of the ViT's patch_size {}",
                c.img_size, e.patch_size
            )));
        }
        if e.num_heads == 0 || !e.embed_dim.is_multiple_of(e.num_heads) {
            return Err(ModelError::BadConfig(format!(
                "vit: embed_dim {} not divisible by num_heads {}",
                e.embed_dim, e.num_heads
            )));
        }
        let q = &c.qformer;
        if q.num_attention_heads == 0 || !q.hidden_size.is_multiple_of(q.num_attention_heads) {
            return Err(ModelError::BadConfig(format!(
                "qformer: hidden_size {} not divisible by num_attention_heads {}",
                q.hidden_size, q.num_attention_heads
            )));
        }
        if q.cross_attention_freq == 0 {
            return Err(ModelError::BadConfig(
                "qformer: cross_attention_freq is 0".into(),
            ));
        }
        if c.n_frms == 0 || c.n_frms > c.max_frame_pos {
            return Err(ModelError::BadConfig(format!(
                "n_frms {} (1 to max_frame_pos = {})",
                c.n_frms, c.max_frame_pos
            )));
        }
        Ok(c)
    }
}
