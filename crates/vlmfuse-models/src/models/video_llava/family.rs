//! VideoLLaVA as a [`Family`] of the in-process reporter: the processor's own `num_frames` of
//! each clip, the `USER: <video>\n… ASSISTANT:` prompt, left padding for batches.

use candle_core::{DType, Device, Tensor};

use super::{KvCache, ModelInputs, VideoLlava, VideoLlavaProcessor};
use crate::generate::Decoder;
use crate::models::family::{Family, FamilyOptions, InputView, Pixels};
use crate::weights::WeightSource;
use crate::{Frame, FrameRef, ModelError};

impl Decoder for VideoLlava {
    type Inputs = ModelInputs;
    type Cache = KvCache;

    fn rows(inputs: &ModelInputs) -> usize {
        inputs.ids.batch()
    }
    fn max_len(inputs: &ModelInputs) -> usize {
        inputs.ids.seq_len()
    }
    fn new_cache(&self, capacity: usize) -> KvCache {
        VideoLlava::new_cache(self, capacity)
    }
    fn prefill(&self, inputs: &ModelInputs, cache: &mut KvCache) -> Result<Tensor, ModelError> {
        VideoLlava::prefill(self, inputs, cache)
    }
    fn step(&self, tokens: &[u32], cache: &mut KvCache) -> Result<Tensor, ModelError> {
        VideoLlava::step(self, tokens, cache)
    }
}

/// A VideoLLaVA checkpoint with its processor and the reporter's prompt.
pub struct VideoLlavaFamily {
    pub model: VideoLlava,
    pub processor: VideoLlavaProcessor,
    prompt: String,
}

impl Family for VideoLlavaFamily {
    type Model = VideoLlava;
    const MODEL_TYPE: &'static str = "video_llava";

    fn model(&self) -> &VideoLlava {
        &self.model
    }

    fn load(weights: &WeightSource, opts: &FamilyOptions) -> Result<Self, ModelError> {
        let model = VideoLlava::load(
            weights,
            &super::LoadOptions {
                dtype: opts.dtype,
                device: opts.device.clone(),
                adapter: opts.adapter.clone(),
                image_tower: false,
            },
        )?;
        let processor = VideoLlavaProcessor::load(weights, model.config())?;
        if let Some(n) = opts.frames {
            return Err(ModelError::BadConfig(format!(
                "frames = {n} applies to Qwen3-VL only; this checkpoint is video_llava, whose \
                 processor takes num_frames = {} of each clip; remove frames",
                processor.num_frames
            )));
        }
        Ok(Self {
            model,
            processor,
            prompt: opts.prompt.clone(),
        })
    }

    fn prepare(&self, clips: &[&[Frame]]) -> Result<ModelInputs, ModelError> {
        let text = self.processor.video_prompt(&self.prompt);
        let refs: Vec<Vec<FrameRef>> = clips
            .iter()
            .map(|c| c.iter().map(Frame::as_ref).collect())
            .collect();
        let items: Vec<(&str, &[FrameRef])> =
            refs.iter().map(|r| (text.as_str(), r.as_slice())).collect();
        self.processor.prepare_videos(&items)
    }

    fn view(&self, inputs: &ModelInputs) -> InputView {
        crate::models::common::view(&inputs.ids, self.model.config().video_token_id)
    }

    fn pixels(&self, inputs: &ModelInputs, r: usize) -> Result<Option<Pixels>, ModelError> {
        let Some(v) = inputs.videos.get(r) else {
            return Ok(None);
        };
        let t = Tensor::from_slice(&v.data, (v.frames, 3, v.height, v.width), &Device::Cpu)?;
        let grid = serde_json::json!({
            "model_type": "video_llava", "frames": v.frames,
            "height": v.height, "width": v.width,
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
}
