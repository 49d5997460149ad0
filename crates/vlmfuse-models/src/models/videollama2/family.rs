//! VideoLLaMA2 as a [`Family`] of the in-process reporter: `num_frames` frames of each clip
//! (the repository's uniform sampler, decoded by the service when it can seek), the
//! repository's chat prompt, one batch for all clips.

use candle_core::{DType, Device, Tensor};

use super::{KvCache, LoadOptions, ModelInputs, VideoLlama2, VideoLlama2Processor, VISUAL_TOKEN};
use crate::generate::Decoder;
use crate::models::family::{Family, FamilyOptions, InputView, Pixels};
use crate::weights::WeightSource;
use crate::{Frame, FrameRef, ModelError};

impl Decoder for VideoLlama2 {
    type Inputs = ModelInputs;
    type Cache = KvCache;

    fn rows(inputs: &ModelInputs) -> usize {
        inputs.ids.batch()
    }
    fn max_len(inputs: &ModelInputs) -> usize {
        inputs.ids.seq_len()
    }
    fn new_cache(&self, capacity: usize) -> KvCache {
        VideoLlama2::new_cache(self, capacity)
    }
    fn prefill(&self, inputs: &ModelInputs, cache: &mut KvCache) -> Result<Tensor, ModelError> {
        VideoLlama2::prefill(self, inputs, cache)
    }
    fn step(&self, tokens: &[u32], cache: &mut KvCache) -> Result<Tensor, ModelError> {
        VideoLlama2::step(self, tokens, cache)
    }
}

/// A VideoLLaMA2 checkpoint with its processor and the reporter's prompt.
pub struct VideoLlama2Family {
    pub model: VideoLlama2,
    pub processor: VideoLlama2Processor,
    prompt: String,
}

impl VideoLlama2Family {
    /// One row per clip.
    pub fn prepare_clips(
        &self,
        clips: &[&[FrameRef]],
        user: &str,
    ) -> Result<ModelInputs, ModelError> {
        let text = self.processor.prompt(user)?;
        let mut rows = Vec::with_capacity(clips.len());
        let mut videos = Vec::with_capacity(clips.len());
        for c in clips {
            let v = self.processor.preprocess_video(c)?;
            let n = self.model.config().tokens_per_clip(v.frames);
            rows.push(self.processor.encode(&text, n)?);
            videos.push(v);
        }
        Ok(ModelInputs {
            ids: self.processor.pad_left(rows),
            videos,
        })
    }
}

impl Family for VideoLlama2Family {
    type Model = VideoLlama2;
    const MODEL_TYPE: &'static str = "videollama2";

    fn model(&self) -> &VideoLlama2 {
        &self.model
    }

    fn load(weights: &WeightSource, opts: &FamilyOptions) -> Result<Self, ModelError> {
        let (model, tower) = VideoLlama2::load(
            weights,
            &LoadOptions {
                dtype: opts.dtype,
                device: opts.device.clone(),
                adapter: opts.adapter.clone(),
            },
        )?;
        if let Some(n) = opts.frames {
            return Err(ModelError::BadConfig(format!(
                "frames = {n} applies to Qwen3-VL only; this checkpoint is VideoLLaMA2, whose \
                 config takes num_frames = {} of each clip; remove frames",
                model.config().num_frames
            )));
        }
        let processor = VideoLlama2Processor::load(weights, model.config(), &tower.preprocessor)?;
        if !processor.own_template {
            tracing::info!("tokenizer_config.json has no chat_template; using transformers 4.40's LLaMA-2 default");
        }
        Ok(Self {
            model,
            processor,
            prompt: opts.prompt.clone(),
        })
    }

    fn prepare(&self, clips: &[&[Frame]]) -> Result<ModelInputs, ModelError> {
        let refs: Vec<Vec<FrameRef>> = clips
            .iter()
            .map(|c| c.iter().map(Frame::as_ref).collect())
            .collect();
        let slices: Vec<&[FrameRef]> = refs.iter().map(|r| r.as_slice()).collect();
        self.prepare_clips(&slices, &self.prompt)
    }

    fn view(&self, inputs: &ModelInputs) -> InputView {
        crate::models::common::view(&inputs.ids, VISUAL_TOKEN)
    }

    fn pixels(&self, inputs: &ModelInputs, r: usize) -> Result<Option<Pixels>, ModelError> {
        let Some(v) = inputs.videos.get(r) else {
            return Ok(None);
        };
        let t = Tensor::from_slice(&v.data, (v.frames, 3, v.height, v.width), &Device::Cpu)?;
        let grid = serde_json::json!({
            "model_type": "videollama2", "frames": v.frames,
            "height": v.height, "width": v.width,
            "visual_tokens": self.model.config().tokens_per_clip(v.frames),
        });
        Ok(Some((t, grid)))
    }

    fn eos_ids(&self) -> &[u32] {
        &self.processor.eos_token_ids
    }
    fn decode(&self, ids: &[u32]) -> Result<String, ModelError> {
        self.processor.decode(ids, true)
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
        self.processor.num_frames
    }
    fn frame_times(&self, duration_s: f64, fps: f64) -> Option<Vec<f64>> {
        self.processor.frame_times(duration_s, fps)
    }
}
