//! VideoLLaVA (`VideoLlavaForConditionalGeneration`, `LanguageBind/Video-LLaVA-7B-hf`) in
//! process: per-frame CLIP features from `vision_feature_layer`, the two-layer GELU projector,
//! and LLaMA over the prompt with the placeholders replaced by the projected frames.
//!
//! The model is loaded once and immutable; per-request state is a [`KvCache`] the caller owns
//! and resets, so one model serves concurrent requests from several threads. A batch of clips
//! runs as one left-padded batch: one vision pass over every frame, one causal prefill, then one
//! decoding step per token for all rows.
//!
//! Every checkpoint layout loads ([`PARTS`]): the hub's (`language_model.model.*`,
//! `video_tower.vision_model.*`, as `LanguageBind/Video-LLaVA-7B-hf` ships), transformers 5's
//! module paths (`model.language_model.*`, `model.video_tower.*`, `lm_head`) and what
//! transformers 5.23's `save_pretrained` writes (`video_tower.embeddings.*`). LoRA adapters
//! trained against any of them are merged at load.

pub mod config;
mod family;
pub mod processor;
pub mod text;
pub mod vision;

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

pub use config::{FeatureLayers, SelectStrategy, VideoLlavaConfig};
pub use family::VideoLlavaFamily;
pub use processor::{
    Arith, EncodedBatch, ImagePixels, ImageProcessor, Resample, VideoLlavaProcessor, VideoPixels,
};
pub use text::KvCache;

use crate::models::common::load_merged;
use crate::weights::WeightSource;
use crate::{FrameRef, ModelError};
use text::LlamaText;
use vision::{concat_features, ClipTower, Projector};

/// Where each part of the model lives in the layouts VideoLLaVA checkpoints come in: the hub
/// name this module reads, and the file prefixes that hold it, in the order they are tried.
/// - the hub's (`LanguageBind/Video-LLaVA-7B-hf`, transformers 4): `language_model.model.*`,
///   `language_model.lm_head.*`, `video_tower.vision_model.*`;
/// - transformers 5's module paths (in memory, and PEFT adapters trained on it):
///   `model.language_model.*`, `lm_head.*`, `model.video_tower.*`;
/// - transformers 5.23's `save_pretrained`: the towers without `vision_model`
///   (`video_tower.embeddings.*`, `video_tower.encoder.*`).
const PARTS: [(&str, &[&str], &str); 5] = [
    (
        "language_model.model.",
        &[
            "language_model.model.",
            "model.language_model.",
            "language_model.",
        ],
        "embed_tokens.weight",
    ),
    (
        "language_model.lm_head.",
        &["language_model.lm_head.", "lm_head."],
        "weight",
    ),
    (
        "video_tower.vision_model.",
        &[
            "video_tower.vision_model.",
            "model.video_tower.vision_model.",
            "model.video_tower.",
            "video_tower.",
        ],
        "embeddings.patch_embedding.weight",
    ),
    (
        "image_tower.vision_model.",
        &[
            "image_tower.vision_model.",
            "model.image_tower.vision_model.",
            "model.image_tower.",
            "image_tower.",
        ],
        "embeddings.patch_embedding.weight",
    ),
    (
        "multi_modal_projector.",
        &["multi_modal_projector.", "model.multi_modal_projector."],
        "linear_1.weight",
    ),
];

/// Any layout's name → the hub layout this module reads (names already in it pass through).
pub fn hub_name(name: &str) -> String {
    // The longest matching file prefix decides ("model.video_tower.vision_model." before
    // "model.video_tower."), and a name already under a hub prefix is left alone.
    if PARTS.iter().any(|(hub, _, _)| name.starts_with(hub)) {
        return name.to_string();
    }
    let mut best: Option<(&str, &str)> = None;
    for (hub, files, _) in PARTS {
        for f in files {
            if name.starts_with(f) && best.is_none_or(|(b, _)| f.len() > b.len()) {
                best = Some((f, hub));
            }
        }
    }
    match best {
        Some((f, hub)) => format!("{hub}{}", &name[f.len()..]),
        None => name.to_string(),
    }
}

/// For each part, the file prefix this checkpoint uses (probed by one tensor each), as a map
/// from hub names to file names. Parts it has in no known layout keep their hub names, so the
/// load error names the tensor the hub layout expects.
fn file_names(vb: &VarBuilder) -> impl Fn(&str) -> String + Sync + Send + 'static {
    let chosen: Vec<(&'static str, &'static str)> = PARTS
        .iter()
        .map(|(hub, files, probe)| {
            let f = files
                .iter()
                .find(|f| vb.contains_tensor(&format!("{f}{probe}")))
                .copied()
                .unwrap_or(hub);
            (*hub, f)
        })
        .collect();
    move |name: &str| {
        for (hub, f) in &chosen {
            if let Some(rest) = name.strip_prefix(hub) {
                return format!("{f}{rest}");
            }
        }
        name.to_string()
    }
}

/// The inverse of [`hub_name`].
pub fn transformers5_name(name: &str) -> String {
    const MAP: [(&str, &str); 5] = [
        ("language_model.model.", "model.language_model."),
        ("language_model.lm_head.", "lm_head."),
        ("video_tower.vision_model.", "model.video_tower."),
        ("image_tower.vision_model.", "model.image_tower."),
        ("multi_modal_projector.", "model.multi_modal_projector."),
    ];
    for (from, to) in MAP {
        if let Some(rest) = name.strip_prefix(from) {
            return format!("{to}{rest}");
        }
    }
    name.to_string()
}

/// How to load a checkpoint.
#[derive(Debug, Clone)]
pub struct LoadOptions {
    pub dtype: DType,
    pub device: Device,
    /// A PEFT LoRA adapter merged into the weights at load.
    pub adapter: Option<WeightSource>,
    /// Also load the image tower (only needed for `<image>` prompts; clips use the video tower).
    pub image_tower: bool,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            dtype: DType::F32,
            device: Device::Cpu,
            adapter: None,
            image_tower: false,
        }
    }
}

/// Everything one prefill needs: the left-padded token ids and the pixels of every clip and
/// image, in the order their placeholders appear (row by row).
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInputs {
    pub ids: EncodedBatch,
    pub videos: Vec<VideoPixels>,
    pub images: Vec<ImagePixels>,
}

impl VideoLlavaProcessor {
    /// One prompt per clip (each holding one `<video>`, e.g. from
    /// [`video_prompt`](Self::video_prompt)), preprocessed, expanded, tokenized and left-padded.
    pub fn prepare_videos(&self, items: &[(&str, &[FrameRef])]) -> Result<ModelInputs, ModelError> {
        if items.is_empty() {
            return Err(ModelError::InvalidInput("an empty batch".into()));
        }
        let mut rows = Vec::with_capacity(items.len());
        let mut videos = Vec::with_capacity(items.len());
        for (prompt, frames) in items {
            let v = self.preprocess_video(frames)?;
            let text = self.expand(prompt, &[self.video_token_count(&v)], &[])?;
            rows.push(self.encode(&text)?);
            videos.push(v);
        }
        Ok(ModelInputs {
            ids: self.pad_left(rows),
            videos,
            images: Vec::new(),
        })
    }

    /// Text-only prompts (no placeholders), left-padded.
    pub fn prepare_text(&self, prompts: &[&str]) -> Result<ModelInputs, ModelError> {
        let rows = prompts
            .iter()
            .map(|p| {
                let t = self.expand(p, &[], &[])?;
                self.encode(&t)
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(ModelInputs {
            ids: self.pad_left(rows),
            videos: Vec::new(),
            images: Vec::new(),
        })
    }

    /// One prompt with one `<image>`.
    pub fn prepare_image(&self, prompt: &str, image: FrameRef) -> Result<ModelInputs, ModelError> {
        let px = self.preprocess_image(image)?;
        let text = self.expand(prompt, &[], &[self.image_token_count(&px)])?;
        Ok(ModelInputs {
            ids: self.pad_left(vec![self.encode(&text)?]),
            videos: Vec::new(),
            images: vec![px],
        })
    }
}

/// A loaded VideoLLaVA.
pub struct VideoLlava {
    cfg: VideoLlavaConfig,
    video_tower: ClipTower,
    image_tower: Option<ClipTower>,
    projector: Projector,
    text: LlamaText,
    feature_idx: Vec<usize>,
    device: Device,
    dtype: DType,
    merged_lora: Vec<String>,
}

/// A candle error on the file `path` as [`ModelError::BadWeights`].
pub(crate) fn bad_weights(
    path: &std::path::Path,
) -> impl Fn(candle_core::Error) -> ModelError + '_ {
    move |e| ModelError::BadWeights {
        path: path.to_path_buf(),
        reason: e.to_string(),
    }
}

impl VideoLlava {
    /// Reads `config.json` and the weights (merging the adapter, if any) onto `opts.device` in
    /// `opts.dtype`. Blocking and slow for real checkpoints: call it at startup.
    pub fn load(source: &WeightSource, opts: &LoadOptions) -> Result<Self, ModelError> {
        let raw: serde_json::Value = source.read_json("config.json")?;
        let cfg = VideoLlavaConfig::from_json(&raw)?;
        let files = source.safetensors_files()?;
        let first = files.first().cloned().unwrap_or_default();
        // With an adapter the weights are renamed to the hub layout first, so an adapter of
        // either naming finds them; without one each part is read where the file keeps it.
        let (vb, merged_lora) = load_merged(
            &files,
            opts.adapter.as_ref(),
            HashMap::new(),
            hub_name,
            opts.dtype,
            &opts.device,
        )?;
        let vb = if opts.adapter.is_none() {
            let names = file_names(&vb);
            vb.rename_f(names)
        } else {
            vb
        };
        Self::from_var_builder(vb, cfg, opts, merged_lora, &first)
    }

    fn from_var_builder(
        vb: VarBuilder,
        cfg: VideoLlavaConfig,
        opts: &LoadOptions,
        merged_lora: Vec<String>,
        path: &std::path::Path,
    ) -> Result<Self, ModelError> {
        let feature_idx = cfg.feature_layers.resolve(cfg.vision.num_hidden_layers)?;
        let depth = feature_idx.iter().copied().max().unwrap_or(0);
        let err = bad_weights(path);
        let video_tower =
            ClipTower::load(vb.pp("video_tower.vision_model"), &cfg.vision, depth).map_err(&err)?;
        let image_tower = if opts.image_tower {
            Some(
                ClipTower::load(vb.pp("image_tower.vision_model"), &cfg.vision, depth)
                    .map_err(&err)?,
            )
        } else {
            None
        };
        let projector = Projector::load(vb.pp("multi_modal_projector"), &cfg).map_err(&err)?;
        let head_key = "language_model.lm_head.weight";
        let head = if cfg.tie_word_embeddings {
            None
        } else if vb.contains_tensor(head_key) {
            Some(vb.pp("language_model.lm_head"))
        } else {
            return Err(ModelError::BadWeights {
                path: path.to_path_buf(),
                reason: format!(
                    "no `{head_key}` (or `lm_head.weight`) and tie_word_embeddings is false"
                ),
            });
        };
        let text = LlamaText::load(vb.pp("language_model.model"), head, &cfg.text).map_err(&err)?;
        Ok(Self {
            cfg,
            video_tower,
            image_tower,
            projector,
            text,
            feature_idx,
            device: opts.device.clone(),
            dtype: opts.dtype,
            merged_lora,
        })
    }

    pub fn config(&self) -> &VideoLlavaConfig {
        &self.cfg
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// Hub-layout keys of the base weights the adapter changed.
    pub fn merged_lora_keys(&self) -> &[String] {
        &self.merged_lora
    }

    /// A fresh per-request cache; `capacity` is a hint (prompt + new tokens).
    pub fn new_cache(&self, capacity: usize) -> KvCache {
        self.text.new_cache(capacity)
    }

    fn check_pixels(&self, h: usize, w: usize, what: &str) -> Result<(), ModelError> {
        let s = self.cfg.vision.image_size;
        if h != s || w != s {
            return Err(ModelError::InvalidInput(format!(
                "{what} preprocessed to {w}x{h}, but the tower takes {s}x{s} (processor crop \
                 size and vision_config.image_size disagree)"
            )));
        }
        Ok(())
    }

    /// Projected features of every frame of every clip, `[Σ frames · tokens_per_frame, hidden]`
    /// (CLS kept: transformers' `get_video_features` ignores the select strategy), all frames
    /// in one tower pass.
    pub fn video_features(&self, videos: &[VideoPixels]) -> Result<Tensor, ModelError> {
        let mut data = Vec::new();
        let mut n = 0;
        for v in videos {
            self.check_pixels(v.height, v.width, "a clip")?;
            data.extend_from_slice(&v.data);
            n += v.frames;
        }
        let s = self.cfg.vision.image_size;
        let px = Tensor::from_vec(data, (n, 3, s, s), &self.device)?;
        let hs = self.video_tower.hidden_states(&px, &self.feature_idx)?;
        let f = self.projector.forward(&concat_features(&hs)?)?;
        let (a, b, c) = f.dims3()?;
        Ok(f.reshape((a * b, c))?)
    }

    /// Projected image features `[Σ tokens, hidden]`, CLS dropped under `default`.
    pub fn image_features(&self, images: &[ImagePixels]) -> Result<Tensor, ModelError> {
        let tower = self.image_tower.as_ref().ok_or_else(|| {
            ModelError::InvalidInput(
                "an <image> prompt, but the model was loaded without its image tower".into(),
            )
        })?;
        let mut data = Vec::new();
        for i in images {
            self.check_pixels(i.height, i.width, "an image")?;
            data.extend_from_slice(&i.data);
        }
        let s = self.cfg.vision.image_size;
        let px = Tensor::from_vec(data, (images.len(), 3, s, s), &self.device)?;
        let mut hs = tower.hidden_states(&px, &self.feature_idx)?;
        if self.cfg.select_strategy == SelectStrategy::Default {
            for h in hs.iter_mut() {
                let t = h.dim(1)?;
                *h = h.narrow(1, 1, t - 1)?;
            }
        }
        let f = self.projector.forward(&concat_features(&hs)?)?;
        let (a, b, c) = f.dims3()?;
        Ok(f.reshape((a * b, c))?)
    }

    /// Input embeddings with placeholder rows replaced, in order, by the visual features
    /// (transformers' `masked_scatter`); a count mismatch is an error, as there.
    pub fn input_embeddings(&self, inputs: &ModelInputs) -> Result<Tensor, ModelError> {
        let (b, t) = (inputs.ids.batch(), inputs.ids.seq_len());
        if b == 0 || t == 0 {
            return Err(ModelError::InvalidInput("an empty prompt".into()));
        }
        let vocab = self.cfg.text.vocab_size as u32;
        let flat: Vec<u32> = inputs.ids.input_ids.iter().flatten().copied().collect();
        if let Some(bad) = flat.iter().find(|&&i| i >= vocab) {
            return Err(ModelError::InvalidInput(format!(
                "token id {bad} is outside the vocabulary ({vocab})"
            )));
        }
        let ids = Tensor::from_vec(flat.clone(), (b, t), &self.device)?;
        let emb = self
            .text
            .embed(&ids)?
            .reshape((b * t, self.cfg.text.hidden_size))?;
        let (vid, img) = (self.cfg.video_token_id, self.cfg.image_token_id);
        let nv = flat.iter().filter(|&&i| i == vid).count();
        let ni = flat.iter().filter(|&&i| i == img).count();
        if nv == 0 && ni == 0 {
            if !inputs.videos.is_empty() || !inputs.images.is_empty() {
                return Err(ModelError::InvalidInput(
                    "pixels given but the prompt has no placeholders".into(),
                ));
            }
            return Ok(emb.reshape((b, t, self.cfg.text.hidden_size))?);
        }
        let mut table = vec![emb];
        let mut video_base = 0;
        if nv > 0 || !inputs.videos.is_empty() {
            let f = self.video_features(&inputs.videos)?.to_dtype(self.dtype)?;
            if f.dim(0)? != nv {
                return Err(ModelError::InvalidInput(format!(
                    "video features and video tokens do not match: {nv} tokens, {} features",
                    f.dim(0)?
                )));
            }
            video_base = b * t;
            table.push(f);
        }
        let mut image_base = 0;
        if ni > 0 || !inputs.images.is_empty() {
            let f = self.image_features(&inputs.images)?.to_dtype(self.dtype)?;
            if f.dim(0)? != ni {
                return Err(ModelError::InvalidInput(format!(
                    "image features and image tokens do not match: {ni} tokens, {} features",
                    f.dim(0)?
                )));
            }
            image_base = b * t + nv;
            table.push(f);
        }
        let (mut kv, mut ki) = (0usize, 0usize);
        let src: Vec<u32> = flat
            .iter()
            .enumerate()
            .map(|(p, &id)| {
                if id == vid {
                    kv += 1;
                    (video_base + kv - 1) as u32
                } else if id == img {
                    ki += 1;
                    (image_base + ki - 1) as u32
                } else {
                    p as u32
                }
            })
            .collect();
        let table = Tensor::cat(&table, 0)?;
        let src = Tensor::from_vec(src, b * t, &self.device)?;
        Ok(table
            .index_select(&src, 0)?
            .reshape((b, t, self.cfg.text.hidden_size))?)
    }

    /// Runs the whole prompt of every row in one causal pass after a reset cache and returns
    /// the logits of each row's last token, `[batch, vocab]` in f32.
    pub fn prefill(&self, inputs: &ModelInputs, cache: &mut KvCache) -> Result<Tensor, ModelError> {
        cache.reset();
        let emb = self.input_embeddings(inputs)?;
        Ok(self.text.forward(&emb, &inputs.ids.attention_mask, cache)?)
    }

    /// Feeds one token per row and returns the next logits, `[batch, vocab]`.
    pub fn step(&self, tokens: &[u32], cache: &mut KvCache) -> Result<Tensor, ModelError> {
        crate::models::common::step(&self.text, tokens, cache)
    }

    /// Logits after every prompt position fed one token at a time, `[batch, seq, vocab]`: the
    /// slow reference the one-pass prefill is checked against.
    pub fn logits_token_by_token(
        &self,
        inputs: &ModelInputs,
        cache: &mut KvCache,
    ) -> Result<Tensor, ModelError> {
        cache.reset();
        let emb = self.input_embeddings(inputs)?;
        Ok(self
            .text
            .forward_stepwise(&emb, &inputs.ids.attention_mask, cache)?)
    }
}
