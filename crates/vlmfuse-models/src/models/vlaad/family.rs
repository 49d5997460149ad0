//! VLAAD as a [`Family`] of the in-process reporter: `n_frms` frames of each clip, decoded by
//! the service at the model's input size when it can seek (as decord does), the LLaMA-2
//! conversation, one batch for all clips.

use candle_core::{DType, Device, Tensor};
use tokenizers::Tokenizer;

use super::{KvCache, LoadOptions, ModelInputs, Vlaad, VlaadProcessor, VISUAL_TOKEN};
use crate::generate::Decoder;
use crate::models::family::{Family, FamilyOptions, InputView, Pixels};
use crate::models::video_llava::processor::token_str;
use crate::weights::WeightSource;
use crate::{Frame, FrameRef, ModelError};

impl Decoder for Vlaad {
    type Inputs = ModelInputs;
    type Cache = KvCache;

    fn rows(inputs: &ModelInputs) -> usize {
        inputs.ids.batch()
    }
    fn max_len(inputs: &ModelInputs) -> usize {
        inputs.ids.seq_len()
    }
    fn new_cache(&self, capacity: usize) -> KvCache {
        Vlaad::new_cache(self, capacity)
    }
    fn prefill(&self, inputs: &ModelInputs, cache: &mut KvCache) -> Result<Tensor, ModelError> {
        Vlaad::prefill(self, inputs, cache)
    }
    fn step(&self, tokens: &[u32], cache: &mut KvCache) -> Result<Tensor, ModelError> {
        Vlaad::step(self, tokens, cache)
    }
}

/// The LLaMA directory's tokenizer as transformers 4.28 reads `tokenizer.json` (as written),
/// with the BOS template `LlamaTokenizerFast` adds when the file has no post-processor.
pub fn load_tokenizer(source: &WeightSource) -> Result<(Tokenizer, Vec<u32>, u32), ModelError> {
    use tokenizers::processors::template::TemplateProcessing;
    let path = source.resolve("tokenizer.json")?;
    let badw = |e: String| ModelError::BadWeights {
        path: path.clone(),
        reason: e,
    };
    let mut tok = Tokenizer::from_file(&path).map_err(|e| badw(e.to_string()))?;
    let tc: serde_json::Value = match source.resolve_optional("tokenizer_config.json")? {
        Some(_) => source.read_json("tokenizer_config.json")?,
        None => serde_json::json!({}),
    };
    let bos = token_str(tc.get("bos_token")).unwrap_or_else(|| "<s>".into());
    let eos = token_str(tc.get("eos_token")).unwrap_or_else(|| "</s>".into());
    let unk = token_str(tc.get("unk_token")).unwrap_or_else(|| "<unk>".into());
    let add_bos = tc
        .get("add_bos_token")
        .and_then(|x| x.as_bool())
        .unwrap_or(true);
    if tok.get_post_processor().is_none() && add_bos {
        let id = tok
            .token_to_id(&bos)
            .ok_or_else(|| badw(format!("BOS `{bos}` is not in the vocabulary")))?;
        let post = TemplateProcessing::builder()
            .try_single(vec![format!("{bos}:0"), "$A:0".into()])
            .map_err(badw)?
            .try_pair(vec![format!("{bos}:0"), "$A:0".into(), "$B:1".into()])
            .map_err(badw)?
            .special_tokens(vec![(bos.clone(), id)])
            .build()
            .map_err(|e| badw(e.to_string()))?;
        tok.with_post_processor(Some(post));
    }
    // Chat.answer stops on id 2 (LLaMA's EOS); the tokenizer's EOS is that id.
    let eos_ids = tok.token_to_id(&eos).into_iter().collect();
    // `pad_token = unk_token` when the tokenizer has none.
    let pad = tok.token_to_id(&unk).unwrap_or(0);
    Ok((tok, eos_ids, pad))
}

/// A VLAAD release with its processor and the reporter's prompt.
pub struct VlaadFamily {
    pub model: Vlaad,
    pub processor: VlaadProcessor,
    prompt: String,
}

impl VlaadFamily {
    /// One row per clip; `times` are each clip's frame times (for the prompt).
    pub fn prepare_clips(
        &self,
        clips: &[(&[FrameRef], &[f64])],
        user: &str,
    ) -> Result<ModelInputs, ModelError> {
        let n = self.model.config().num_video_query_token;
        let mut rows = Vec::with_capacity(clips.len());
        let mut videos = Vec::with_capacity(clips.len());
        for (frames, times) in clips {
            let v = self.processor.preprocess(frames, times)?;
            let text = self.processor.prompt(user, &v.times);
            rows.push(self.processor.encode(&text, n)?);
            videos.push(v);
        }
        Ok(ModelInputs {
            ids: self.processor.pad_left(rows),
            videos,
        })
    }
}

impl Family for VlaadFamily {
    type Model = Vlaad;
    const MODEL_TYPE: &'static str = "vlaad";

    fn model(&self) -> &Vlaad {
        &self.model
    }

    fn load(weights: &WeightSource, opts: &FamilyOptions) -> Result<Self, ModelError> {
        let model = Vlaad::load(
            weights,
            &LoadOptions {
                dtype: opts.dtype,
                device: opts.device.clone(),
                adapter: opts.adapter.clone(),
            },
        )?;
        if let Some(n) = opts.frames {
            return Err(ModelError::BadConfig(format!(
                "frames = {n} applies to Qwen3-VL only; this checkpoint is VLAAD, whose config \
                 takes n_frms = {} of each clip; remove frames",
                model.config().n_frms
            )));
        }
        let (tok, eos, pad) = load_tokenizer(model.llama_source())?;
        let processor = VlaadProcessor::new(tok, model.config(), eos, pad);
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
        let times: Vec<Vec<f64>> = clips
            .iter()
            .map(|c| c.iter().map(|f| f.pts_s).collect())
            .collect();
        let items: Vec<(&[FrameRef], &[f64])> = refs
            .iter()
            .zip(&times)
            .map(|(r, t)| (r.as_slice(), t.as_slice()))
            .collect();
        self.prepare_clips(&items, &self.prompt)
    }

    fn view(&self, inputs: &ModelInputs) -> InputView {
        crate::models::common::view(&inputs.ids, VISUAL_TOKEN)
    }

    fn pixels(&self, inputs: &ModelInputs, r: usize) -> Result<Option<Pixels>, ModelError> {
        let Some(v) = inputs.videos.get(r) else {
            return Ok(None);
        };
        let t = Tensor::from_slice(&v.data, (v.frames, 3, v.size, v.size), &Device::Cpu)?;
        let grid = serde_json::json!({
            "model_type": "vlaad", "frames": v.frames, "height": v.size, "width": v.size,
            "times_s": v.times,
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
        self.model.text_config().vocab_size
    }
    fn frames(&self) -> usize {
        self.processor.n_frms
    }
    fn frame_times(&self, duration_s: f64, fps: f64) -> Option<Vec<f64>> {
        self.processor.frame_times(duration_s, fps)
    }
    fn frame_size(&self) -> Option<(u32, u32)> {
        let s = self.processor.img_size as u32;
        Some((s, s))
    }
}
