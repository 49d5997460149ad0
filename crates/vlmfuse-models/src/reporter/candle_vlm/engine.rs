//! The architectures a `kind = "candle"` reporter can run, behind one small interface: turn a
//! batch of clips into model inputs, prefill them, feed one token per row. The model code lives
//! in [`crate::models`] (parity-tested against transformers); this file only adapts it.

use candle_core::{DType, Device, Tensor};

use crate::models::qwen3_vl::{self, Qwen3Vl, Qwen3VlProcessor, Sequence};
use crate::models::video_llava::{self, ModelInputs, VideoLlava, VideoLlavaProcessor};
use crate::weights::WeightSource;
use crate::{Frame, FrameRef, ModelError};

/// The `model_type`s of `config.json` this reporter loads.
pub const SUPPORTED_MODEL_TYPES: [&str; 2] = ["qwen3_vl", "video_llava"];

/// A loaded checkpoint with its processor. Immutable: request state lives in [`ArchCache`].
pub enum Arch {
    Qwen3Vl {
        model: Box<Qwen3Vl>,
        processor: Box<Qwen3VlProcessor>,
    },
    VideoLlava {
        model: Box<VideoLlava>,
        processor: Box<VideoLlavaProcessor>,
    },
}

/// Per-request state of one generation (the KV cache of a batch).
pub enum ArchCache {
    Qwen3Vl(qwen3_vl::Cache),
    VideoLlava(video_llava::KvCache),
}

/// The model inputs of a batch of clips, as the architecture's processor builds them.
pub enum Prepared {
    Qwen3Vl(Vec<Sequence>),
    VideoLlava(ModelInputs),
}

/// What a prepared input looks like, for `vlmfuse describe --dump` and logs.
#[derive(Debug, Clone)]
pub struct InputView {
    /// Token ids of each row (VideoLLaVA's left padding included).
    pub input_ids: Vec<Vec<u32>>,
    /// Visual placeholder tokens per row.
    pub visual_tokens: Vec<usize>,
}

/// `np.linspace(0, n - 1, k).round()` without repeats: `k` of `n` frames spread evenly, first
/// and last included; every frame when `k >= n`.
pub fn spread_indices(n: usize, k: usize) -> Vec<usize> {
    if k == 0 || n == 0 {
        return Vec::new();
    }
    if k >= n {
        return (0..n).collect();
    }
    if k == 1 {
        return vec![n / 2];
    }
    (0..k)
        .map(|i| ((i * (n - 1)) as f64 / (k - 1) as f64).round() as usize)
        .collect()
}

impl Arch {
    /// Reads `config.json`'s `model_type` and loads that architecture with its processor.
    pub fn load(
        weights: &WeightSource,
        adapter: Option<&WeightSource>,
        dtype: DType,
        device: &Device,
    ) -> Result<Self, ModelError> {
        let raw: serde_json::Value = weights.read_json("config.json")?;
        let model_type = raw.get("model_type").and_then(|v| v.as_str());
        match model_type {
            Some("qwen3_vl") => {
                let model = Qwen3Vl::load(
                    weights,
                    &qwen3_vl::LoadOptions {
                        dtype,
                        device: device.clone(),
                        adapter: adapter.cloned(),
                    },
                )?;
                let processor = Qwen3VlProcessor::load(weights, model.config())?;
                Ok(Arch::Qwen3Vl {
                    model: Box::new(model),
                    processor: Box::new(processor),
                })
            }
            Some("video_llava") => {
                let model = VideoLlava::load(
                    weights,
                    &video_llava::LoadOptions {
                        dtype,
                        device: device.clone(),
                        adapter: adapter.cloned(),
                        image_tower: false,
                    },
                )?;
                let processor = VideoLlavaProcessor::load(weights, model.config())?;
                Ok(Arch::VideoLlava {
                    model: Box::new(model),
                    processor: Box::new(processor),
                })
            }
            other => {
                let file = weights
                    .resolve("config.json")
                    .map(|p| p.display().to_string())
                    .unwrap_or_else(|_| format!("{}/config.json", weights.describe()));
                Err(ModelError::BadConfig(format!(
                    "{file}: model_type {} is not supported by kind = \"candle\"; supported: {} \
                     (other models can be served by an OpenAI-compatible server, kind = \"openai\")",
                    match other {
                        Some(t) => format!("`{t}`"),
                        None => "is missing".into(),
                    },
                    SUPPORTED_MODEL_TYPES.join(", ")
                )))
            }
        }
    }

    /// `qwen3_vl` or `video_llava`.
    pub fn model_type(&self) -> &'static str {
        match self {
            Arch::Qwen3Vl { .. } => "qwen3_vl",
            Arch::VideoLlava { .. } => "video_llava",
        }
    }

    pub fn dtype(&self) -> DType {
        match self {
            Arch::Qwen3Vl { model, .. } => model.dtype(),
            Arch::VideoLlava { model, .. } => model.dtype(),
        }
    }

    pub fn device(&self) -> &Device {
        match self {
            Arch::Qwen3Vl { model, .. } => model.device(),
            Arch::VideoLlava { model, .. } => model.device(),
        }
    }

    pub fn merged_lora_keys(&self) -> &[String] {
        match self {
            Arch::Qwen3Vl { model, .. } => model.merged_lora_keys(),
            Arch::VideoLlava { model, .. } => model.merged_lora_keys(),
        }
    }

    /// Ids that end an answer: `generation_config.json`'s, plus the chat turn end.
    pub fn eos_ids(&self) -> &[u32] {
        match self {
            Arch::Qwen3Vl { processor, .. } => processor.eos_ids(),
            Arch::VideoLlava { processor, .. } => &processor.eos_token_ids,
        }
    }

    pub fn vocab_size(&self) -> usize {
        match self {
            Arch::Qwen3Vl { model, .. } => model.config().text.vocab_size,
            Arch::VideoLlava { model, .. } => model.config().text.vocab_size,
        }
    }

    /// Builds the inputs of a batch: one row per clip, each with `prompt` in the model's chat
    /// format. Qwen3-VL takes up to `qwen_frames` frames of each clip with their presentation
    /// times; VideoLLaVA's processor picks its own `num_frames`.
    pub fn prepare(
        &self,
        clips: &[&[Frame]],
        prompt: &str,
        qwen_frames: usize,
    ) -> Result<Prepared, ModelError> {
        if clips.is_empty() {
            return Err(ModelError::InvalidInput("an empty batch".into()));
        }
        for (i, c) in clips.iter().enumerate() {
            if c.is_empty() {
                return Err(ModelError::InvalidInput(format!("clip {i} has no frames")));
            }
            for f in c.iter() {
                f.as_ref().validate()?;
            }
        }
        match self {
            Arch::Qwen3Vl { processor, .. } => {
                let seqs = clips
                    .iter()
                    .map(|frames| {
                        let idx = spread_indices(frames.len(), qwen_frames.max(1));
                        let refs: Vec<FrameRef> = idx.iter().map(|&i| frames[i].as_ref()).collect();
                        let times: Vec<f64> = idx.iter().map(|&i| frames[i].pts_s).collect();
                        processor.prepare_frames(prompt, &refs, &times)
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                Ok(Prepared::Qwen3Vl(seqs))
            }
            Arch::VideoLlava { processor, .. } => {
                let text = processor.video_prompt(prompt);
                let refs: Vec<Vec<FrameRef>> = clips
                    .iter()
                    .map(|c| c.iter().map(Frame::as_ref).collect())
                    .collect();
                let items: Vec<(&str, &[FrameRef])> =
                    refs.iter().map(|r| (text.as_str(), r.as_slice())).collect();
                Ok(Prepared::VideoLlava(processor.prepare_videos(&items)?))
            }
        }
    }

    pub fn new_cache(&self, capacity: usize) -> ArchCache {
        match self {
            Arch::Qwen3Vl { .. } => ArchCache::Qwen3Vl(qwen3_vl::Cache::new(capacity)),
            Arch::VideoLlava { model, .. } => ArchCache::VideoLlava(model.new_cache(capacity)),
        }
    }

    /// The whole prompt of every row in one causal pass: next-token logits `[batch, vocab]` f32.
    pub fn prefill(&self, p: &Prepared, cache: &mut ArchCache) -> Result<Tensor, ModelError> {
        let logits = match (self, p, cache) {
            (Arch::Qwen3Vl { model, .. }, Prepared::Qwen3Vl(s), ArchCache::Qwen3Vl(c)) => {
                model.prefill(s, c)?
            }
            (Arch::VideoLlava { model, .. }, Prepared::VideoLlava(i), ArchCache::VideoLlava(c)) => {
                model.prefill(i, c)?
            }
            _ => {
                return Err(ModelError::InvalidInput(
                    "inputs or cache of another architecture".into(),
                ))
            }
        };
        Ok(logits.to_dtype(DType::F32)?)
    }

    /// One token per row after [`prefill`](Self::prefill): the next logits `[batch, vocab]` f32.
    pub fn step(&self, tokens: &[u32], cache: &mut ArchCache) -> Result<Tensor, ModelError> {
        let logits = match (self, cache) {
            (Arch::Qwen3Vl { model, .. }, ArchCache::Qwen3Vl(c)) => model.step(tokens, c)?,
            (Arch::VideoLlava { model, .. }, ArchCache::VideoLlava(c)) => model.step(tokens, c)?,
            _ => {
                return Err(ModelError::InvalidInput(
                    "a cache of another architecture".into(),
                ))
            }
        };
        Ok(logits.to_dtype(DType::F32)?)
    }

    /// Text of generated ids, special tokens dropped.
    pub fn decode(&self, ids: &[u32]) -> Result<String, ModelError> {
        match self {
            Arch::Qwen3Vl { processor, .. } => processor.decode(ids),
            Arch::VideoLlava { processor, .. } => processor
                .tokenizer()
                .decode(ids, true)
                .map_err(|e| ModelError::BadConfig(format!("tokenizer: {e}"))),
        }
    }
}

impl Prepared {
    pub fn rows(&self) -> usize {
        match self {
            Prepared::Qwen3Vl(s) => s.len(),
            Prepared::VideoLlava(i) => i.ids.batch(),
        }
    }

    /// The longest row, in tokens.
    pub fn max_len(&self) -> usize {
        match self {
            Prepared::Qwen3Vl(s) => s.iter().map(|s| s.ids.len()).max().unwrap_or(0),
            Prepared::VideoLlava(i) => i.ids.seq_len(),
        }
    }

    /// Token ids and visual token counts per row.
    pub fn view(&self, arch: &Arch) -> InputView {
        match (self, arch) {
            (Prepared::Qwen3Vl(s), Arch::Qwen3Vl { model, .. }) => {
                let vid = model.config().video_token_id;
                InputView {
                    input_ids: s.iter().map(|s| s.ids.clone()).collect(),
                    visual_tokens: s
                        .iter()
                        .map(|s| s.ids.iter().filter(|&&t| t == vid).count())
                        .collect(),
                }
            }
            (Prepared::VideoLlava(i), Arch::VideoLlava { model, .. }) => {
                let vid = model.config().video_token_id;
                InputView {
                    input_ids: i.ids.input_ids.clone(),
                    visual_tokens: i
                        .ids
                        .input_ids
                        .iter()
                        .map(|r| r.iter().filter(|&&t| t == vid).count())
                        .collect(),
                }
            }
            _ => InputView {
                input_ids: Vec::new(),
                visual_tokens: Vec::new(),
            },
        }
    }

    /// Row `r`'s pixel values as the vision tower takes them (Qwen3-VL: `[patches, patch_dim]`;
    /// VideoLLaVA: `[frames, 3, height, width]`) and its grid as JSON (Qwen3-VL: `t`/`h`/`w` in
    /// patches; VideoLLaVA: frame count and size).
    pub fn pixels(
        &self,
        arch: &Arch,
        r: usize,
    ) -> Result<Option<(Tensor, serde_json::Value)>, ModelError> {
        match (self, arch) {
            (Prepared::Qwen3Vl(s), Arch::Qwen3Vl { model, .. }) => {
                let Some(v) = s.get(r).and_then(|s| s.video.as_ref()) else {
                    return Ok(None);
                };
                let d = model.config().vision.patch_dim();
                let t = Tensor::from_slice(
                    &v.pixel_values,
                    (v.pixel_values.len() / d, d),
                    &Device::Cpu,
                )?;
                let [gt, gh, gw] = v.grid_thw;
                let grid = serde_json::json!({
                    "model_type": "qwen3_vl", "t": gt, "h": gh, "w": gw,
                    "video_grid_thw": [gt, gh, gw],
                    "merge_size": model.config().vision.spatial_merge_size,
                });
                Ok(Some((t, grid)))
            }
            (Prepared::VideoLlava(i), Arch::VideoLlava { .. }) => {
                let Some(v) = i.videos.get(r) else {
                    return Ok(None);
                };
                let t =
                    Tensor::from_slice(&v.data, (v.frames, 3, v.height, v.width), &Device::Cpu)?;
                let grid = serde_json::json!({
                    "model_type": "video_llava", "frames": v.frames,
                    "height": v.height, "width": v.width,
                });
                Ok(Some((t, grid)))
            }
            _ => Ok(None),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_indices_cover_the_clip() {
        assert_eq!(spread_indices(10, 4), vec![0, 3, 6, 9]);
        assert_eq!(spread_indices(3, 8), vec![0, 1, 2]);
        assert_eq!(spread_indices(5, 1), vec![2]);
        assert!(spread_indices(0, 3).is_empty());
    }
}
