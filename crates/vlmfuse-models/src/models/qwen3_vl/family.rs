//! Qwen3-VL as a [`Family`] of the in-process reporter: the checkpoint's own frame sampler (its
//! video processor's `fps`, `min_frames`, `max_frames` or `num_frames`, as transformers picks
//! frame indices) unless `[[reporter]] frames` fixes a count, the frames' presentation times,
//! the model's own chat template, M-RoPE positions.

use candle_core::{DType, Device, Tensor};

use super::{Cache, Qwen3Vl, Qwen3VlProcessor, Sequence};
use crate::generate::Decoder;
use crate::models::family::{spread_indices, Family, FamilyOptions, InputView, Pixels};
use crate::reporter::candle_vlm::DEFAULT_QWEN_FRAMES;
use crate::weights::WeightSource;
use crate::{Frame, FrameRef, ModelError};

impl Decoder for Qwen3Vl {
    type Inputs = Vec<Sequence>;
    type Cache = Cache;

    fn rows(inputs: &Vec<Sequence>) -> usize {
        inputs.len()
    }
    fn max_len(inputs: &Vec<Sequence>) -> usize {
        inputs.iter().map(|s| s.ids.len()).max().unwrap_or(0)
    }
    fn new_cache(&self, capacity: usize) -> Cache {
        Cache::new(capacity)
    }
    fn prefill(&self, inputs: &Vec<Sequence>, cache: &mut Cache) -> Result<Tensor, ModelError> {
        Qwen3Vl::prefill(self, inputs, cache)
    }
    fn step(&self, tokens: &[u32], cache: &mut Cache) -> Result<Tensor, ModelError> {
        Qwen3Vl::step(self, tokens, cache)
    }
}

/// A Qwen3-VL checkpoint with its processor and the reporter's frame count and prompt.
pub struct Qwen3VlFamily {
    pub model: Qwen3Vl,
    pub processor: Qwen3VlProcessor,
    frames: usize,
    /// No `[[reporter]] frames`: the checkpoint's sampler picks the frames
    /// ([`Family::frame_times`]) and every frame given is taken.
    own_sampler: bool,
    prompt: String,
}

impl Family for Qwen3VlFamily {
    type Model = Qwen3Vl;
    const MODEL_TYPE: &'static str = "qwen3_vl";

    fn model(&self) -> &Qwen3Vl {
        &self.model
    }

    fn load(weights: &WeightSource, opts: &FamilyOptions) -> Result<Self, ModelError> {
        let model = Qwen3Vl::load(
            weights,
            &super::LoadOptions {
                dtype: opts.dtype,
                device: opts.device.clone(),
                adapter: opts.adapter.clone(),
            },
        )?;
        let processor = Qwen3VlProcessor::load(weights, model.config())?;
        Ok(Self {
            model,
            processor,
            frames: opts.frames.unwrap_or(DEFAULT_QWEN_FRAMES).max(1),
            own_sampler: opts.frames.is_none(),
            prompt: opts.prompt.clone(),
        })
    }

    fn prepare(&self, clips: &[&[Frame]]) -> Result<Vec<Sequence>, ModelError> {
        clips
            .iter()
            .map(|frames| {
                // The sampler's frames are all taken (they number at most its `max_frames`);
                // frames from elsewhere are spread to that many.
                let n = if self.own_sampler {
                    self.processor.video.config.max_frames.max(1)
                } else {
                    self.frames
                };
                let idx = spread_indices(frames.len(), n);
                let refs: Vec<FrameRef> = idx.iter().map(|&i| frames[i].as_ref()).collect();
                let times: Vec<f64> = idx.iter().map(|&i| frames[i].pts_s).collect();
                self.processor.prepare_frames(&self.prompt, &refs, &times)
            })
            .collect()
    }

    fn view(&self, inputs: &Vec<Sequence>) -> InputView {
        let vid = self.model.config().video_token_id;
        InputView {
            input_ids: inputs.iter().map(|s| s.ids.clone()).collect(),
            visual_tokens: inputs
                .iter()
                .map(|s| s.ids.iter().filter(|&&t| t == vid).count())
                .collect(),
            prompt_tokens: inputs.iter().map(|s| s.ids.len()).collect(),
        }
    }

    fn pixels(&self, inputs: &Vec<Sequence>, r: usize) -> Result<Option<Pixels>, ModelError> {
        let Some(v) = inputs.get(r).and_then(|s| s.video.as_ref()) else {
            return Ok(None);
        };
        let d = self.model.config().vision.patch_dim();
        let t = Tensor::from_slice(&v.pixel_values, (v.pixel_values.len() / d, d), &Device::Cpu)?;
        let [gt, gh, gw] = v.grid_thw;
        let grid = serde_json::json!({
            "model_type": "qwen3_vl", "t": gt, "h": gh, "w": gw,
            "video_grid_thw": [gt, gh, gw],
            "merge_size": self.model.config().vision.spatial_merge_size,
        });
        Ok(Some((t, grid)))
    }

    fn eos_ids(&self) -> &[u32] {
        self.processor.eos_ids()
    }
    fn decode(&self, ids: &[u32]) -> Result<String, ModelError> {
        self.processor.decode(ids)
    }
    fn dtype(&self) -> DType {
        self.model.dtype()
    }
    fn device(&self) -> &Device {
        self.model.device()
    }
    fn merged_lora_keys(&self) -> &[String] {
        self.model.merged_lora_keys()
    }
    fn vocab_size(&self) -> usize {
        self.model.config().text.vocab_size
    }
    fn frames(&self) -> usize {
        self.frames
    }

    /// The frames transformers' Qwen3-VL video processor samples: indices
    /// `linspace(0, total - 1, n).round()` of the clip's `total = round(duration * fps)` frames
    /// ([`super::VideoProcessor::sample_indices`], checked against transformers 5.23), each
    /// asked for half a frame before its nominal time `i / fps` so that the first frame at or
    /// after it is frame `i` itself whatever the rounding of its timestamp.
    fn frame_times(&self, duration_s: f64, fps: f64) -> Option<Vec<f64>> {
        let usable = |v: f64| v.is_finite() && v > 0.0;
        if !(self.own_sampler && usable(duration_s) && usable(fps)) {
            return None;
        }
        let total = ((duration_s * fps).round() as usize).max(1);
        let idx = self.processor.video.sample_indices(total, fps);
        Some(
            idx.iter()
                .map(|&i| ((i as f64 - 0.5) / fps).max(0.0))
                .collect(),
        )
    }
}
