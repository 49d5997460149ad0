//! VideoLLaMA2's `config.json`: a Mistral config at the top level (the repository's
//! `Videollama2MistralConfig`) plus the multimodal fields its training script writes
//! (`mm_vision_tower`, `mm_projector_type`, `mm_hidden_size`, `mm_vision_select_layer`,
//! `mm_vision_select_feature`, `num_frames`, `image_aspect_ratio`).

use crate::models::video_llava::config::{TextConfig, VisionConfig};
use crate::ModelError;

/// The `model_type`s VideoLLaMA2 writes for a Mistral LLM (`videollama2` is the 7B/8x7B
/// release's, `videollama2_mistral` the code's own name).
pub const MODEL_TYPES: [&str; 2] = ["videollama2", "videollama2_mistral"];

/// Frames per clip when the config does not say (`constants.NUM_FRAMES`).
pub const DEFAULT_NUM_FRAMES: usize = 8;
/// `constants.MAX_FRAMES`: the processor keeps at most this many frames.
pub const MAX_FRAMES: usize = 32;

/// Which vision-language connector sits between the tower and the LLM.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Connector {
    /// `stc_connector`: RegStage → Conv3d (kernel = stride = 2, padding 1) + SiLU → RegStage →
    /// two-layer GELU MLP (the released VideoLLaMA2 models).
    Stc,
    /// `stc_connector_v35`: the same with an unpadded Conv3d.
    StcV35,
}

impl Connector {
    /// The Conv3d's padding on every side.
    pub fn padding(&self) -> usize {
        match self {
            Connector::Stc => 1,
            Connector::StcV35 => 0,
        }
    }
}

/// `mm_vision_select_feature`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SelectFeature {
    /// Drop CLS (`patch`, the default).
    Patch,
    /// Keep it (`cls_patch`).
    ClsPatch,
}

/// How frames are brought to the tower's square input (`image_aspect_ratio`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AspectRatio {
    /// `pad`: `expand2square` with the processor's mean colour, then the CLIP processor.
    Pad,
    /// Anything else: the CLIP processor alone (shortest edge, centre crop).
    Crop,
}

#[derive(Debug, Clone, PartialEq)]
pub struct VideoLlama2Config {
    pub model_type: String,
    pub text: TextConfig,
    /// `sliding_window` of the Mistral LLM (`None`: full attention).
    pub sliding_window: Option<usize>,
    /// `mm_vision_tower`: a hub id or a directory holding the tower's `config.json` and
    /// `preprocessor_config.json`.
    pub vision_tower: String,
    /// Filled in by the loader from the tower's config.
    pub vision: VisionConfig,
    pub connector: Connector,
    pub mm_hidden_size: usize,
    /// Index into the tower's hidden states (negative from the end; `-2` by default).
    pub select_layer: i64,
    pub select_feature: SelectFeature,
    pub num_frames: usize,
    pub aspect_ratio: AspectRatio,
    pub tie_word_embeddings: bool,
}

fn field<'a>(v: &'a serde_json::Value, k: &str) -> Option<&'a serde_json::Value> {
    v.get(k).filter(|x| !x.is_null())
}

impl VideoLlama2Config {
    /// Parses `config.json`; the vision config is read separately (it lives with the tower)
    /// and set with [`with_vision`](Self::with_vision).
    pub fn from_json(v: &serde_json::Value) -> Result<Self, ModelError> {
        let mt = v.get("model_type").and_then(|m| m.as_str()).unwrap_or("");
        if !MODEL_TYPES.contains(&mt) {
            let hint = if mt.starts_with("videollama2_") {
                " (only VideoLLaMA2's Mistral LLM is supported in process)"
            } else {
                ""
            };
            return Err(ModelError::BadConfig(format!(
                "config.json has model_type `{mt}`, not one of {MODEL_TYPES:?}{hint}"
            )));
        }
        let (text, sliding_window) = TextConfig::mistral_json(v)?;
        let vision_tower = field(v, "mm_vision_tower")
            .or_else(|| field(v, "vision_tower"))
            .and_then(|x| x.as_str())
            .ok_or_else(|| {
                ModelError::BadConfig(
                    "config.json has no `mm_vision_tower` (not a VideoLLaMA2 checkpoint?)".into(),
                )
            })?
            .to_string();
        if !vision_tower.to_lowercase().contains("clip") {
            return Err(ModelError::BadConfig(format!(
                "mm_vision_tower `{vision_tower}`: only CLIP towers are supported in process \
                 (the SigLIP tower of VideoLLaMA2.1 is not)"
            )));
        }
        let connector = match field(v, "mm_projector_type").and_then(|x| x.as_str()) {
            Some("stc_connector") => Connector::Stc,
            Some("stc_connector_v35") => Connector::StcV35,
            Some(o) => {
                return Err(ModelError::BadConfig(format!(
                    "mm_projector_type `{o}` is not supported in process (stc_connector, \
                     stc_connector_v35)"
                )))
            }
            None => {
                return Err(ModelError::BadConfig(
                    "config.json has no `mm_projector_type`".into(),
                ))
            }
        };
        let mm_hidden_size = field(v, "mm_hidden_size")
            .and_then(|x| x.as_u64())
            .ok_or_else(|| ModelError::BadConfig("config.json has no `mm_hidden_size`".into()))?
            as usize;
        let select_layer = match field(v, "mm_vision_select_layer") {
            None => -1,
            Some(x) => x.as_i64().ok_or_else(|| {
                ModelError::BadConfig("mm_vision_select_layer is not an integer".into())
            })?,
        };
        let select_feature = match field(v, "mm_vision_select_feature")
            .and_then(|x| x.as_str())
            .unwrap_or("patch")
        {
            "patch" => SelectFeature::Patch,
            "cls_patch" => SelectFeature::ClsPatch,
            o => {
                return Err(ModelError::BadConfig(format!(
                    "mm_vision_select_feature `{o}` (patch or cls_patch)"
                )))
            }
        };
        let num_frames = field(v, "num_frames")
            .and_then(|x| x.as_u64())
            .map(|x| x as usize)
            .unwrap_or(DEFAULT_NUM_FRAMES);
        if num_frames == 0 || num_frames > MAX_FRAMES {
            return Err(ModelError::BadConfig(format!(
                "num_frames {num_frames} (1 to {MAX_FRAMES})"
            )));
        }
        let aspect_ratio = match field(v, "image_aspect_ratio").and_then(|x| x.as_str()) {
            Some("pad") => AspectRatio::Pad,
            _ => AspectRatio::Crop,
        };
        let tie_word_embeddings = field(v, "tie_word_embeddings")
            .and_then(|x| x.as_bool())
            .unwrap_or(false);
        Ok(Self {
            model_type: mt.to_string(),
            text,
            sliding_window,
            vision_tower,
            vision: VisionConfig::default(),
            connector,
            mm_hidden_size,
            select_layer,
            select_feature,
            num_frames,
            aspect_ratio,
            tie_word_embeddings,
        })
    }

    /// Sets the tower's config (its `config.json`: a `CLIPVisionConfig`, or a `CLIPConfig`
    /// whose `vision_config` is used) and checks it against `mm_hidden_size`.
    pub fn with_vision(mut self, tower_json: &serde_json::Value) -> Result<Self, ModelError> {
        let v = field(tower_json, "vision_config").unwrap_or(tower_json);
        let vision: VisionConfig = serde_json::from_value(v.clone()).map_err(|e| {
            ModelError::BadConfig(format!("vision tower config ({}): {e}", self.vision_tower))
        })?;
        vision.check()?;
        if vision.hidden_size != self.mm_hidden_size {
            return Err(ModelError::BadConfig(format!(
                "mm_hidden_size {} but the vision tower `{}` has hidden_size {}",
                self.mm_hidden_size, self.vision_tower, vision.hidden_size
            )));
        }
        self.vision = vision;
        self.select_index()?;
        Ok(self)
    }

    /// The hidden state the connector reads, as an index into `[embeddings, layer 1, …]`.
    pub fn select_index(&self) -> Result<usize, ModelError> {
        let n = self.vision.num_hidden_layers as i64 + 1;
        let l = self.select_layer;
        let i = if l < 0 { n + l } else { l };
        if (0..n).contains(&i) {
            Ok(i as usize)
        } else {
            Err(ModelError::BadConfig(format!(
                "mm_vision_select_layer {l} is outside the {n} hidden states of a {}-layer tower",
                self.vision.num_hidden_layers
            )))
        }
    }

    /// Patches per side of one frame.
    pub fn grid(&self) -> usize {
        self.vision.grid()
    }

    /// Visual tokens one clip of `frames` frames becomes: the Conv3d's output volume
    /// `T'·H'·W'` (`⌊(n + 2p − 2) / 2⌋ + 1` per axis). Without CLS the spatial side is the
    /// patch grid; `cls_patch` is refused by the connector (not a square).
    pub fn tokens_per_clip(&self, frames: usize) -> usize {
        let p = self.connector.padding();
        let out = |n: usize| (n + 2 * p).saturating_sub(2) / 2 + 1;
        let g = self.grid();
        out(frames) * out(g) * out(g)
    }
}

/// The built-in configs of the towers the released checkpoints name, for when neither a
/// directory nor the hub cache has them (an offline machine with only the VideoLLaMA2
/// checkpoint): `openai/clip-vit-large-patch14-336`'s vision config and processor.
pub fn known_tower(name: &str) -> Option<(serde_json::Value, serde_json::Value)> {
    if name.trim_end_matches('/') != "openai/clip-vit-large-patch14-336" {
        return None;
    }
    Some((
        serde_json::json!({
            "hidden_size": 1024, "intermediate_size": 4096, "num_hidden_layers": 24,
            "num_attention_heads": 16, "num_channels": 3, "image_size": 336, "patch_size": 14,
            "hidden_act": "quick_gelu", "layer_norm_eps": 1e-5,
        }),
        serde_json::json!({
            "crop_size": 336, "do_center_crop": true, "do_normalize": true, "do_resize": true,
            "image_mean": [0.48145466, 0.4578275, 0.40821073],
            "image_std": [0.26862954, 0.26130258, 0.27577711],
            "resample": 3, "size": 336,
        }),
    ))
}
