//! VideoLLaMA2 (DAMO-NLP-SG/VideoLLaMA2, `Videollama2MistralForCausalLM`) in process: each
//! frame through the CLIP tower (the hidden state `mm_vision_select_layer`, CLS dropped), the
//! spatial-temporal connector over the clip ([`connector::StcConnector`]), and the Mistral LLM
//! over the prompt with the clip's tokens where `<video>` stood.
//!
//! Checkpoints load as the repository saves them: the LLM at `model.*` and `lm_head`, the tower
//! at `model.vision_tower.vision_tower.vision_model.*` (or, when the checkpoint lacks it, from
//! the tower named by `mm_vision_tower`), the connector at `model.mm_projector.*`. LoRA runs
//! as the repository's fine-tuning writes them (`adapter_config.json`, `adapter_model.*` and
//! `non_lora_trainables.bin` with the connector's trained weights) are merged at load.

pub mod config;
pub mod connector;
mod family;
pub mod processor;

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};

pub use config::VideoLlama2Config;
pub use family::VideoLlama2Family;
pub use processor::{VideoLlama2Processor, VISUAL_TOKEN};

use crate::models::common::{self, load_merged, splice_visual};
use crate::models::video_llava::bad_weights;
use crate::models::video_llava::processor::{EncodedBatch, VideoPixels};
use crate::models::video_llava::text::{KvCache, LlamaText};
use crate::models::video_llava::vision::ClipTower;
use crate::weights::{read_pth, var_builder, WeightSource};
use crate::ModelError;
use connector::StcConnector;

/// The tower's prefix in a VideoLLaMA2 checkpoint.
const TOWER: &str = "model.vision_tower.vision_tower.vision_model";

/// Model inputs: left-padded ids with [`VISUAL_TOKEN`] runs, and each row's clip.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInputs {
    pub ids: EncodedBatch,
    pub videos: Vec<VideoPixels>,
}

/// How to load a checkpoint.
pub use crate::models::common::LoadOptions;

/// Where the tower's config, processor and (if the checkpoint lacks them) weights come from.
pub struct Tower {
    pub config: serde_json::Value,
    pub preprocessor: serde_json::Value,
    pub source: Option<WeightSource>,
}

/// Resolves `mm_vision_tower`: a directory, else the hub repo of that name (through the same
/// cache, endpoint and offline setting as the checkpoint), else the built-in config of the
/// tower the released checkpoints name.
pub fn resolve_tower(name: &str, checkpoint: &WeightSource) -> Result<Tower, ModelError> {
    let dir = Path::new(name);
    let source = if dir.join("config.json").is_file() {
        WeightSource::local(dir)
    } else {
        match checkpoint {
            WeightSource::Hub {
                cache_dir,
                endpoint,
                offline,
                ..
            } => WeightSource::Hub {
                hub: name.to_string(),
                revision: "main".into(),
                cache_dir: cache_dir.clone(),
                endpoint: endpoint.clone(),
                offline: *offline,
            },
            WeightSource::Local { .. } => WeightSource::hub(name, "main"),
        }
    };
    let read = |s: &WeightSource| -> Result<(serde_json::Value, serde_json::Value), ModelError> {
        Ok((
            s.read_json("config.json")?,
            s.read_json("preprocessor_config.json")?,
        ))
    };
    match read(&source) {
        Ok((config, preprocessor)) => Ok(Tower {
            config,
            preprocessor,
            source: Some(source),
        }),
        Err(e) => match config::known_tower(name) {
            Some((config, preprocessor)) => {
                tracing::info!(tower = name, error = %e,
                    "vision tower config not found; using the built-in config of this tower");
                Ok(Tower {
                    config,
                    preprocessor,
                    source: None,
                })
            }
            None => Err(ModelError::BadConfig(format!(
                "mm_vision_tower `{name}`: neither a directory with config.json and \
                 preprocessor_config.json nor a readable hub repo ({e})"
            ))),
        },
    }
}

/// A loaded VideoLLaMA2.
pub struct VideoLlama2 {
    cfg: VideoLlama2Config,
    tower: ClipTower,
    connector: StcConnector,
    text: LlamaText,
    select: usize,
    device: Device,
    dtype: DType,
    merged_lora: Vec<String>,
}

/// A LoRA run's `non_lora_trainables.bin` keys (`base_model.model.model.mm_projector.*`) as
/// the repository's loader maps them (`base_model.` then a doubled `model.` dropped).
pub fn non_lora_name(k: &str) -> String {
    let k = k.strip_prefix("base_model.").unwrap_or(k);
    match k.strip_prefix("model.") {
        Some(rest) if rest.starts_with("model.") || rest.starts_with("lm_head") => rest.to_string(),
        _ => k.to_string(),
    }
}

impl VideoLlama2 {
    /// Reads `config.json`, the tower's config and the weights (merging the adapter, if any).
    /// Blocking; call it at start-up.
    pub fn load(source: &WeightSource, opts: &LoadOptions) -> Result<(Self, Tower), ModelError> {
        let raw: serde_json::Value = source.read_json("config.json")?;
        let cfg = VideoLlama2Config::from_json(&raw)?;
        let tower_src = resolve_tower(&cfg.vision_tower, source)?;
        let cfg = cfg.with_vision(&tower_src.config)?;
        let files = source.safetensors_files()?;
        let first = files.first().cloned().unwrap_or_default();
        // The connector (and anything else trained in full) comes with a LoRA run.
        let mut extra = HashMap::new();
        if let Some(adapter) = &opts.adapter {
            if let Some(p) = adapter.resolve_optional("non_lora_trainables.bin")? {
                let t = read_pth(&p, None)?;
                tracing::info!(tensors = t.len(), "loaded non_lora_trainables.bin");
                extra.extend(t.into_iter().map(|(k, v)| (non_lora_name(&k), v)));
            }
        }
        let (vb, merged_lora) = load_merged(
            &files,
            opts.adapter.as_ref(),
            extra,
            |k| k.to_string(),
            opts.dtype,
            &opts.device,
        )?;
        let err = bad_weights(&first);
        let select = cfg.select_index()?;
        let probe = format!("{TOWER}.embeddings.patch_embedding.weight");
        let tower = if vb.contains_tensor(&probe) {
            ClipTower::load(vb.pp(TOWER), &cfg.vision, select).map_err(&err)?
        } else {
            let ts = tower_src
                .source
                .as_ref()
                .ok_or_else(|| ModelError::BadWeights {
                    path: first.clone(),
                    reason: format!(
                        "no `{probe}` in the checkpoint and no weights for the tower `{}`",
                        cfg.vision_tower
                    ),
                })?;
            let tf = ts.safetensors_files()?;
            let tvb = var_builder(&tf, opts.dtype, &opts.device)?;
            tracing::info!(tower = %ts.describe(), "vision tower weights from the tower's own checkpoint");
            ClipTower::load(tvb.pp("vision_model"), &cfg.vision, select).map_err(bad_weights(
                tf.first().map(|p| p.as_path()).unwrap_or(&first),
            ))?
        };
        let connector = StcConnector::load(vb.pp("model.mm_projector"), &cfg).map_err(&err)?;
        let head = if cfg.tie_word_embeddings {
            None
        } else if vb.contains_tensor("lm_head.weight") {
            Some(vb.pp("lm_head"))
        } else {
            return Err(ModelError::BadWeights {
                path: first.clone(),
                reason: "no `lm_head.weight` and tie_word_embeddings is false".into(),
            });
        };
        let text = LlamaText::load(vb.pp("model"), head, &cfg.text).map_err(&err)?;
        Ok((
            Self {
                cfg,
                tower,
                connector,
                text,
                select,
                device: opts.device.clone(),
                dtype: opts.dtype,
                merged_lora,
            },
            tower_src,
        ))
    }

    pub fn config(&self) -> &VideoLlama2Config {
        &self.cfg
    }
    pub fn device(&self) -> &Device {
        &self.device
    }
    pub fn dtype(&self) -> DType {
        self.dtype
    }
    pub fn merged_lora_keys(&self) -> &[String] {
        &self.merged_lora
    }
    pub fn new_cache(&self, capacity: usize) -> KvCache {
        self.text.new_cache(capacity)
    }

    /// Visual tokens of each clip, `[Σ tokens, hidden]`: every frame in one tower pass, then
    /// the connector per clip.
    pub fn video_features(&self, videos: &[VideoPixels]) -> Result<Tensor, ModelError> {
        let s = self.cfg.vision.image_size;
        let g = self.cfg.grid();
        let mut out = Vec::with_capacity(videos.len());
        for v in videos {
            if v.height != s || v.width != s {
                return Err(ModelError::InvalidInput(format!(
                    "a clip preprocessed to {}x{}, but the tower takes {s}x{s} (processor crop \
                     size and the tower's image_size disagree)",
                    v.width, v.height
                )));
            }
            let px = Tensor::from_slice(&v.data, (v.frames, 3, s, s), &self.device)?;
            let hs = self
                .tower
                .hidden_states(&px, &[self.select])?
                .pop()
                .expect("one hidden state");
            let hs = match self.cfg.select_feature {
                config::SelectFeature::Patch => hs.narrow(1, 1, g * g)?,
                config::SelectFeature::ClsPatch => {
                    return Err(ModelError::BadConfig(
                        "mm_vision_select_feature = cls_patch leaves no square grid for the \
                         STC connector"
                            .into(),
                    ))
                }
            };
            let x = hs.reshape((1, v.frames, g, g, self.cfg.mm_hidden_size))?;
            let f = self.connector.forward(&x)?;
            out.push(f.squeeze(0)?);
        }
        Ok(Tensor::cat(&out, 0)?)
    }

    /// Input embeddings with the [`VISUAL_TOKEN`] positions replaced, in order, by the clips'
    /// tokens.
    pub fn input_embeddings(&self, inputs: &ModelInputs) -> Result<Tensor, ModelError> {
        splice_visual(&self.text, &inputs.ids, || {
            self.video_features(&inputs.videos)
        })
    }

    fn check_window(&self, len: usize) -> Result<(), ModelError> {
        match self.cfg.sliding_window {
            Some(w) if len > w => Err(ModelError::InvalidInput(format!(
                "{len} positions exceed the LLM's sliding_window {w} (sliding-window attention \
                 is not implemented in process)"
            ))),
            _ => Ok(()),
        }
    }

    /// The whole prompt of every row in one causal pass; logits of each row's last token.
    pub fn prefill(&self, inputs: &ModelInputs, cache: &mut KvCache) -> Result<Tensor, ModelError> {
        cache.reset();
        self.check_window(inputs.ids.seq_len())?;
        let emb = self.input_embeddings(inputs)?;
        Ok(self.text.forward(&emb, &inputs.ids.attention_mask, cache)?)
    }

    /// One token per row; the next logits.
    pub fn step(&self, tokens: &[u32], cache: &mut KvCache) -> Result<Tensor, ModelError> {
        self.check_window(cache.len() + 1)?;
        common::step(&self.text, tokens, cache)
    }
}
