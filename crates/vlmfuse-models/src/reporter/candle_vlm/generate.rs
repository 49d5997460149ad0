//! Prompt layout, prefill and token-by-token generation on a loaded [`QwenVlEngine`].

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use candle_core::{DType, Tensor};
use candle_transformers::generation::LogitsProcessor;
use candle_transformers::models::qwen3_vl::Qwen3VLModel;

use super::checkpoint::{tok_err, QwenVlEngine};
use super::video::VideoPatches;
use crate::{FrameRef, ModelError};

/// What one generation produced, with the numbers needed to report throughput.
#[derive(Debug, Clone, PartialEq)]
pub struct Generation {
    pub text: String,
    pub tokens: Vec<u32>,
    pub prompt_tokens: usize,
    pub visual_tokens: usize,
    pub prefill_ms: f64,
    pub decode_ms: f64,
}

impl Generation {
    /// Decode throughput (excludes prefill, which is dominated by the vision tower).
    pub fn tokens_per_s(&self) -> f64 {
        if self.decode_ms <= 0.0 {
            0.0
        } else {
            self.tokens.len() as f64 / (self.decode_ms / 1e3)
        }
    }
}

impl QwenVlEngine {
    /// `[start, end)` span of the `<|video_pad|>` placeholders.
    pub fn prompt_ids(
        &self,
        visual_tokens: usize,
        prompt: &str,
    ) -> Result<(Vec<u32>, (usize, usize)), ModelError> {
        let enc = |s: &str| -> Result<Vec<u32>, ModelError> {
            Ok(self
                .tokenizer
                .encode(s, false)
                .map_err(tok_err)?
                .get_ids()
                .to_vec())
        };
        let mut ids = enc("<|im_start|>user\n")?;
        ids.push(self.config.vision_start_token_id);
        let start = ids.len();
        ids.extend(std::iter::repeat_n(
            self.config.video_token_id,
            visual_tokens,
        ));
        let end = ids.len();
        ids.push(self.config.vision_end_token_id);
        ids.extend(enc(&format!(
            "{prompt}<|im_end|>\n<|im_start|>assistant\n"
        ))?);
        Ok((ids, (start, end)))
    }

    fn patches(&self, frames: &[FrameRef]) -> Result<(Tensor, Tensor, VideoPatches), ModelError> {
        let vp = self.video.process(frames)?;
        let n = vp.grid_thw.iter().product::<usize>();
        let pixels = Tensor::from_slice(&vp.data, (n, vp.row_len), &self.device)?;
        let thw: Vec<u32> = vp.grid_thw.iter().map(|&x| x as u32).collect();
        let grid = Tensor::from_vec(thw, (1, 3), &self.device)?;
        Ok((pixels, grid, vp))
    }

    /// Runs the prompt through `model` and returns the next-token logits (f32, `[vocab]`).
    fn prefill(
        &self,
        model: &Qwen3VLModel,
        ids: &[u32],
        span: (usize, usize),
        pixels: Tensor,
        grid: Tensor,
        causal: bool,
    ) -> Result<Tensor, ModelError> {
        let fwd = |chunk: &[u32], offset: usize, video: Option<(Tensor, Tensor, usize, usize)>| {
            let input = Tensor::new(chunk, &self.device)?.unsqueeze(0)?;
            let (pv, gv, spans) = match video {
                Some((p, g, s, e)) => (Some(p), Some(g), vec![vec![(s, e)]]),
                None => (None, None, vec![vec![]]),
            };
            model.forward(
                &input,
                None,
                pv,
                None,
                gv,
                vec![chunk.len()],
                vec![vec![]],
                spans,
                &[offset],
            )
        };
        let logits = if !causal {
            fwd(ids, 0, Some((pixels, grid, span.0, span.1)))?
        } else {
            // Video chunk = <|vision_start|> pads <|vision_end|>: everything around it goes one
            // token at a time, where candle's mask is right.
            let (cs, ce) = (span.0 - 1, span.1 + 1);
            for (i, &t) in ids[..cs].iter().enumerate() {
                fwd(&[t], i, None)?;
            }
            let mut last = fwd(
                &ids[cs..ce],
                cs,
                Some((pixels, grid, span.0 - cs, span.1 - cs)),
            )?;
            for (i, &t) in ids[ce..].iter().enumerate() {
                last = fwd(&[t], ce + i, None)?;
            }
            last
        };
        Ok(logits.squeeze(0)?.to_dtype(DType::F32)?)
    }

    /// Logits for the first generated token; lets tests compare base and adapted models.
    pub fn first_token_logits(
        &self,
        frames: &[FrameRef],
        prompt: &str,
        causal: bool,
    ) -> Result<Vec<f32>, ModelError> {
        let (pixels, grid, vp) = self.patches(frames)?;
        let (ids, span) = self.prompt_ids(vp.merged_tokens(self.video.merge_size), prompt)?;
        let model = self.build_model(ids.len() + 1)?;
        Ok(self
            .prefill(&model, &ids, span, pixels, grid, causal)?
            .to_vec1::<f32>()?)
    }

    /// Describes `frames` in answer to `prompt`. Stops at an EOS id, after `max_new_tokens`,
    /// or (with an error) as soon as `cancel` is set.
    #[allow(clippy::too_many_arguments)]
    pub fn generate(
        &self,
        frames: &[FrameRef],
        prompt: &str,
        max_new_tokens: usize,
        sampler: &mut LogitsProcessor,
        causal: bool,
        cancel: &AtomicBool,
    ) -> Result<Generation, ModelError> {
        let t0 = Instant::now();
        let (pixels, grid, vp) = self.patches(frames)?;
        let visual = vp.merged_tokens(self.video.merge_size);
        let (ids, span) = self.prompt_ids(visual, prompt)?;
        let model = self.build_model(ids.len() + max_new_tokens + 1)?;
        let mut logits = self.prefill(&model, &ids, span, pixels, grid, causal)?;
        let prefill_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = Instant::now();
        let mut out = Vec::new();
        let mut pos = ids.len();
        while out.len() < max_new_tokens {
            if cancel.load(Ordering::Relaxed) {
                return Err(ModelError::Timeout {
                    what: "generation (cancelled)".into(),
                    after: t0.elapsed(),
                });
            }
            let next = sampler.sample(&logits)?;
            if self.eos.contains(&next) {
                break;
            }
            out.push(next);
            if out.len() == max_new_tokens {
                break;
            }
            let input = Tensor::new(&[next], &self.device)?.unsqueeze(0)?;
            logits = model
                .forward(
                    &input,
                    None,
                    None,
                    None,
                    None,
                    vec![1],
                    vec![vec![]],
                    vec![vec![]],
                    &[pos],
                )?
                .squeeze(0)?
                .to_dtype(DType::F32)?;
            pos += 1;
        }
        let decode_ms = t1.elapsed().as_secs_f64() * 1e3;
        let text = self.tokenizer.decode(&out, true).map_err(tok_err)?;
        Ok(Generation {
            text: text.trim().to_string(),
            tokens: out,
            prompt_tokens: ids.len(),
            visual_tokens: visual,
            prefill_ms,
            decode_ms,
        })
    }
}
