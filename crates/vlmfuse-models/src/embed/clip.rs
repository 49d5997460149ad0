//! CLIP image tower (candle-transformers' `clip::vision_model`) + `visual_projection`, loaded from
//! an HF-format directory (`config.json` + `model.safetensors`), e.g. openai/clip-vit-base-patch32.

use candle_core::{DType, Device, Tensor};
use candle_nn::Module;
use candle_transformers::models::clip::text_model::Activation;
use candle_transformers::models::clip::vision_model::{ClipVisionConfig, ClipVisionTransformer};
use serde::Deserialize;

use super::ContextEmbedder;
use crate::imaging::ImageProcessor;
use crate::weights::{var_builder, WeightSource};
use crate::{FrameRef, ModelError};

/// The subset of HF's `CLIPVisionConfig` candle needs. Defaults are transformers' defaults, so a
/// config that omits a field means what it means to transformers.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default)]
pub struct ClipVisionSettings {
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub num_channels: usize,
    pub image_size: usize,
    pub patch_size: usize,
    pub projection_dim: usize,
    pub hidden_act: String,
    pub layer_norm_eps: f64,
}

impl Default for ClipVisionSettings {
    fn default() -> Self {
        Self {
            hidden_size: 768,
            intermediate_size: 3072,
            num_hidden_layers: 12,
            num_attention_heads: 12,
            num_channels: 3,
            image_size: 224,
            patch_size: 32,
            projection_dim: 512,
            hidden_act: "quick_gelu".into(),
            layer_norm_eps: 1e-5,
        }
    }
}

impl ClipVisionSettings {
    /// Reads either a full `CLIPConfig` (`vision_config` inside) or a bare `CLIPVisionConfig`
    /// (`model_type = "clip_vision_model"`, fields at top level).
    ///
    /// In a full config the top-level `projection_dim` wins over `vision_config.projection_dim`,
    /// because that is the one `CLIPModel` sizes `visual_projection` with; transformers writes
    /// CLIPVisionConfig's default (512) inside `vision_config` whatever the model's projection
    /// is. The vision part's value counts only when the top level has none (older exports),
    /// and in a bare vision config (`CLIPVisionModelWithProjection`), where it is the real one.
    pub fn from_config_json(v: &serde_json::Value) -> Result<Self, ModelError> {
        let (mut part, top_proj) = match v.get("vision_config") {
            Some(vc) => (vc.clone(), v.get("projection_dim").cloned()),
            None => (v.clone(), None),
        };
        if let (Some(obj), Some(p)) = (part.as_object_mut(), top_proj) {
            obj.insert("projection_dim".into(), p);
        }
        let s: Self = serde_json::from_value(part)
            .map_err(|e| ModelError::BadConfig(format!("CLIP vision_config: {e}")))?;
        s.check()?;
        Ok(s)
    }

    fn check(&self) -> Result<(), ModelError> {
        if self.hidden_act != "quick_gelu" {
            // candle's CLIP implements QuickGELU only; running another activation silently would
            // give plausible-looking but wrong embeddings.
            return Err(ModelError::BadConfig(format!(
                "CLIP hidden_act `{}` is not supported (only quick_gelu)",
                self.hidden_act
            )));
        }
        if self.patch_size == 0 || !self.image_size.is_multiple_of(self.patch_size) {
            return Err(ModelError::BadConfig(format!(
                "CLIP image_size {} is not a multiple of patch_size {}",
                self.image_size, self.patch_size
            )));
        }
        if self.num_attention_heads == 0
            || !self.hidden_size.is_multiple_of(self.num_attention_heads)
        {
            return Err(ModelError::BadConfig(format!(
                "CLIP hidden_size {} not divisible by num_attention_heads {}",
                self.hidden_size, self.num_attention_heads
            )));
        }
        if self.num_channels != 3 {
            return Err(ModelError::BadConfig(format!(
                "CLIP num_channels {} (frames are RGB)",
                self.num_channels
            )));
        }
        if (self.layer_norm_eps - 1e-5).abs() > 1e-12 {
            tracing::warn!(
                eps = self.layer_norm_eps,
                "candle's CLIP hard-codes layer_norm_eps = 1e-5; embeddings may drift slightly"
            );
        }
        Ok(())
    }

    fn to_candle(&self) -> ClipVisionConfig {
        ClipVisionConfig {
            embed_dim: self.hidden_size,
            activation: Activation::QuickGelu,
            intermediate_size: self.intermediate_size,
            num_hidden_layers: self.num_hidden_layers,
            num_attention_heads: self.num_attention_heads,
            projection_dim: self.projection_dim,
            num_channels: self.num_channels,
            image_size: self.image_size,
            patch_size: self.patch_size,
        }
    }
}

/// CLIP context embedder: clip embedding = L2-normalised mean of the frames' projected image
/// embeddings, all frames in one batched forward pass.
pub struct ClipEmbedder {
    name: String,
    settings: ClipVisionSettings,
    vision: ClipVisionTransformer,
    projection: candle_nn::Linear,
    /// CLIPImageProcessor at the tower's input size (as the ONNX backend without a
    /// `preprocessor_config.json`), so both backends feed the same pixels.
    processor: ImageProcessor,
    device: Device,
}

impl ClipEmbedder {
    /// Loads `config.json` + `model.safetensors` (or its shards) from `source`. Weights are held
    /// in f32: the tower is small and f32 keeps CPU and GPU embeddings comparable in one bank.
    pub fn load(source: &WeightSource, device: &Device) -> Result<Self, ModelError> {
        let cfg: serde_json::Value = source.read_json("config.json")?;
        let settings = ClipVisionSettings::from_config_json(&cfg)?;
        let files = source.safetensors_files()?;
        let vb = var_builder(&files, DType::F32, device)?;
        // candle silently substitutes a *random* class embedding when the tensor is absent,
        // which would make embeddings non-deterministic across restarts: refuse instead.
        let class_key = "vision_model.embeddings.class_embedding";
        if !vb.contains_tensor(class_key) {
            return Err(ModelError::BadWeights {
                path: files[0].clone(),
                reason: format!("no tensor `{class_key}` (not a CLIP checkpoint?)"),
            });
        }
        let bad = |e: candle_core::Error| ModelError::BadWeights {
            path: files[0].clone(),
            reason: e.to_string(),
        };
        let vision = ClipVisionTransformer::new(vb.pp("vision_model"), &settings.to_candle())
            .map_err(bad)?;
        let projection = candle_nn::linear_no_bias(
            settings.hidden_size,
            settings.projection_dim,
            vb.pp("visual_projection"),
        )
        .map_err(bad)?;
        tracing::info!(source = %source.describe(), dim = settings.projection_dim,
            image_size = settings.image_size, "loaded CLIP embedder");
        let processor = ImageProcessor::clip(settings.image_size as u32);
        Ok(Self {
            name: format!("clip:{}", source.describe()),
            settings,
            vision,
            projection,
            processor,
            device: device.clone(),
        })
    }

    /// Overrides the name reported to the fusion engine and metrics.
    pub fn with_name(mut self, name: impl Into<String>) -> Self {
        self.name = name.into();
        self
    }

    pub fn settings(&self) -> &ClipVisionSettings {
        &self.settings
    }

    /// Per-frame projected embeddings `[n_frames, projection_dim]`, unnormalised.
    pub fn frame_embeddings(&self, frames: &[FrameRef]) -> Result<Tensor, ModelError> {
        if frames.is_empty() {
            return Err(ModelError::InvalidInput("no frames to embed".into()));
        }
        let s = self.settings.image_size;
        let (buf, _) = self
            .processor
            .process_batch(frames, std::num::NonZeroUsize::MIN)?;
        let pixels = Tensor::from_vec(buf, (frames.len(), 3, s, s), &self.device)?;
        let feats = self.vision.forward(&pixels)?;
        Ok(self.projection.forward(&feats)?)
    }
}

impl ContextEmbedder for ClipEmbedder {
    fn name(&self) -> &str {
        &self.name
    }

    fn dim(&self) -> usize {
        self.settings.projection_dim
    }

    fn embed(&self, frames: &[FrameRef]) -> Result<Vec<f32>, ModelError> {
        let per_frame = self.frame_embeddings(frames)?;
        let mean = per_frame.mean(0)?;
        let n = mean.sqr()?.sum_all()?.sqrt()?.to_scalar::<f32>()?;
        if !n.is_finite() || n == 0.0 {
            return Err(ModelError::InvalidInput(format!(
                "clip embedding has norm {n}; cannot normalise"
            )));
        }
        Ok((mean / n as f64)?.to_vec1::<f32>()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn top_level_projection_dim_wins_in_a_full_config() {
        let full = json!({
            "model_type": "clip",
            "projection_dim": 768,
            "vision_config": {"hidden_size": 1024, "num_attention_heads": 16, "projection_dim": 512}
        });
        let s = ClipVisionSettings::from_config_json(&full).unwrap();
        assert_eq!((s.projection_dim, s.hidden_size), (768, 1024));

        // Older exports: only the vision part says it, or only the top level.
        let vision_only = json!({"vision_config": {"projection_dim": 256}});
        let s = ClipVisionSettings::from_config_json(&vision_only).unwrap();
        assert_eq!(s.projection_dim, 256);
        let top_only = json!({"projection_dim": 640, "vision_config": {}});
        let s = ClipVisionSettings::from_config_json(&top_only).unwrap();
        assert_eq!(s.projection_dim, 640);

        // A bare CLIPVisionConfig: its own value is the one.
        let bare = json!({"model_type": "clip_vision_model", "projection_dim": 1024});
        let s = ClipVisionSettings::from_config_json(&bare).unwrap();
        assert_eq!(s.projection_dim, 1024);
        // Neither: transformers' default.
        let s = ClipVisionSettings::from_config_json(&json!({"vision_config": {}})).unwrap();
        assert_eq!(s.projection_dim, 512);
    }
}
