//! The in-process VLM as a [`LocalReporter`]: a model loaded once plus this reporter's
//! generation settings. The service wraps it in a [`BackendPool`](vlmfuse_core::BackendPool),
//! which runs one generation at a time and queues the rest, so the model needs no lock; every
//! generation gets a fresh cache.

use std::sync::atomic::AtomicBool;
use std::time::Instant;

use candle_core::Tensor;

use super::config::{parse_dtype, CandleVlmConfig};
use crate::generate::GenerateOptions;
use crate::models::family::{load_family, AnyFamily, FamilyOptions, Prepared};
use crate::reporter::{ClipInput, LocalReporter, ReporterOutput};
use crate::{parse_device, Frame, ModelError};

/// What one generation produced, with the numbers needed to report throughput.
#[derive(Debug, Clone, PartialEq)]
pub struct Generation {
    pub text: String,
    /// Generated ids, the end-of-sequence id excluded.
    pub tokens: Vec<u32>,
    /// Prompt length of this row (placeholders included, padding excluded).
    pub prompt_tokens: usize,
    pub visual_tokens: usize,
    /// Preprocessing, vision tower and prefill of the whole batch.
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

/// The model's inputs and first output for one clip: what `vlmfuse describe --dump` writes, so
/// a checkpoint can be checked against its reference implementation from outside.
#[derive(Debug, Clone)]
pub struct Trace {
    /// `qwen3_vl` or `video_llava`.
    pub model_type: &'static str,
    pub input_ids: Vec<u32>,
    /// The vision tower's input (f32, on the CPU): Qwen3-VL `[patches, patch_dim]`, VideoLLaVA
    /// `[frames, 3, height, width]`.
    pub pixel_values: Option<Tensor>,
    /// Qwen3-VL: `t`, `h`, `w` in patches; VideoLLaVA: `frames`, `height`, `width`.
    pub grid: serde_json::Value,
    /// Next-token logits after the prompt (f32).
    pub first_token_logits: Vec<f32>,
    /// The logits each generated token (and the stop token, if one ended the answer) was
    /// chosen from: `[tokens, vocab]`.
    pub step_logits: Vec<Vec<f32>>,
    /// The stop token that ended the answer (`None`: it ran to `max_new_tokens`).
    pub stop: Option<u32>,
    pub generation: Generation,
}

/// What [`CandleVlmReporter::run`] hands back: the answers, and the logits kept for a trace.
struct Run {
    gens: Vec<Generation>,
    first: Vec<Vec<f32>>,
    steps: Vec<Vec<Vec<f32>>>,
    stops: Vec<Option<u32>>,
}

/// [`LocalReporter`] over an in-process Qwen3-VL or VideoLLaVA. One generation at a time per
/// model comes from its pool (a second concurrent one would only contend for the same device
/// and double its activation memory), not from a lock here.
pub struct CandleVlmReporter {
    cfg: CandleVlmConfig,
    family: Box<dyn AnyFamily>,
}

impl CandleVlmReporter {
    /// Blocking (reads every weight, merges the adapter): call at startup, off the async
    /// threads. Fails for an unsupported `model_type`, a device this build lacks, a bad dtype.
    pub fn load(cfg: CandleVlmConfig) -> Result<Self, ModelError> {
        if cfg.frames == Some(0) {
            return Err(ModelError::BadConfig(format!(
                "reporter `{}`: frames must be at least 1",
                cfg.name
            )));
        }
        if cfg.max_new_tokens == 0 {
            return Err(ModelError::BadConfig(format!(
                "reporter `{}`: max_new_tokens must be at least 1",
                cfg.name
            )));
        }
        let t0 = Instant::now();
        let device = parse_device(&cfg.device)?;
        let dtype = parse_dtype(cfg.dtype.as_deref(), &device)?;
        let family = load_family(
            &cfg.weights,
            &FamilyOptions {
                dtype,
                device: device.clone(),
                adapter: cfg.adapter.clone(),
                frames: cfg.frames,
                prompt: cfg.prompt.clone(),
            },
        )
        .map_err(|e| match e {
            ModelError::BadConfig(m) => {
                ModelError::BadConfig(format!("reporter `{}`: {m}", cfg.name))
            }
            e => e,
        })?;
        if family.eos_ids().is_empty() {
            tracing::warn!(
                reporter = %cfg.name,
                "the checkpoint names no eos_token_id: answers run to max_new_tokens"
            );
        }
        tracing::info!(
            reporter = %cfg.name,
            model_type = family.model_type(),
            weights = %cfg.weights.describe(),
            device = %cfg.device,
            dtype = ?dtype,
            lora_modules = family.merged_lora_keys().len(),
            ms = t0.elapsed().as_secs_f64() * 1e3,
            "loaded in-process VLM"
        );
        Ok(Self { cfg, family })
    }

    pub fn config(&self) -> &CandleVlmConfig {
        &self.cfg
    }

    /// The loaded family (model and processor), for inspection and tests;
    /// `family().as_any().downcast_ref::<Qwen3VlFamily>()` reaches the concrete one.
    pub fn family(&self) -> &dyn AnyFamily {
        self.family.as_ref()
    }

    /// The inputs this reporter builds for `clips` (one row each).
    pub fn prepare(&self, clips: &[&[Frame]]) -> Result<Prepared, ModelError> {
        self.family.prepare(clips)
    }

    /// One clip, blocking, with this reporter's settings.
    pub fn generate_blocking(
        &self,
        frames: &[Frame],
        cancel: &AtomicBool,
    ) -> Result<Generation, ModelError> {
        Ok(self
            .generate_batch_blocking(&[frames], cancel)?
            .pop()
            .expect("one row"))
    }

    /// Several clips as one batch (left padding and an attention mask): one vision pass, one
    /// prefill, one decoding step per token for all rows. Each row gets what it gets alone.
    pub fn generate_batch_blocking(
        &self,
        clips: &[&[Frame]],
        cancel: &AtomicBool,
    ) -> Result<Vec<Generation>, ModelError> {
        let t0 = Instant::now();
        let prepared = self.prepare(clips)?;
        Ok(self.run(&prepared, cancel, t0, false)?.gens)
    }

    /// One clip with everything `describe --dump` writes.
    pub fn trace(&self, frames: &[Frame], cancel: &AtomicBool) -> Result<Trace, ModelError> {
        let t0 = Instant::now();
        let prepared = self.prepare(&[frames])?;
        let view = self.family.view(&prepared)?;
        let (pixel_values, grid) = match self.family.pixels(&prepared, 0)? {
            Some((t, g)) => (Some(t), g),
            None => (None, serde_json::Value::Null),
        };
        let Run {
            mut gens,
            first,
            mut steps,
            stops,
        } = self.run(&prepared, cancel, t0, true)?;
        Ok(Trace {
            model_type: self.family.model_type(),
            input_ids: view.input_ids.into_iter().next().unwrap_or_default(),
            pixel_values,
            grid,
            first_token_logits: first.into_iter().next().unwrap_or_default(),
            step_logits: if steps.is_empty() {
                Vec::new()
            } else {
                steps.swap_remove(0)
            },
            stop: stops.first().copied().flatten(),
            generation: gens.pop().expect("one row"),
        })
    }

    /// [`crate::generate::generate`] with this reporter's settings: greedy (lowest id on ties,
    /// as `torch.argmax`) unless a temperature is set; a row stops at an end-of-sequence id or
    /// `max_new_tokens`; `cancel` is checked between steps.
    fn run(
        &self,
        prepared: &Prepared,
        cancel: &AtomicBool,
        t0: Instant,
        keep_first: bool,
    ) -> Result<Run, ModelError> {
        let cfg = &self.cfg;
        let view = self.family.view(prepared)?;
        let opts = GenerateOptions {
            max_new_tokens: cfg.max_new_tokens,
            stop: self.family.eos_ids().to_vec(),
            temperature: cfg.temperature,
            top_p: cfg.top_p,
            seed: cfg.seed,
            keep_first_logits: keep_first,
            keep_step_logits: keep_first,
        };
        let g = self.family.generate(prepared, &opts, Some(cancel))?;
        // The prefill time includes preprocessing, which happened before `generate` started.
        let prefill_ms = (t0.elapsed() - g.decode).as_secs_f64() * 1e3;
        let decode_ms = g.decode.as_secs_f64() * 1e3;
        let gens = g
            .tokens
            .into_iter()
            .enumerate()
            .map(|(r, tokens)| {
                Ok(Generation {
                    text: self.family.decode(&tokens)?.trim().to_string(),
                    prompt_tokens: view.prompt_tokens[r],
                    visual_tokens: view.visual_tokens[r],
                    tokens,
                    prefill_ms,
                    decode_ms,
                })
            })
            .collect::<Result<Vec<_>, ModelError>>()?;
        Ok(Run {
            gens,
            first: g.first_logits,
            steps: g.step_logits,
            stops: g.stop,
        })
    }

    fn output(&self, g: &Generation, t0: Instant) -> ReporterOutput {
        tracing::debug!(
            reporter = %self.cfg.name,
            prompt_tokens = g.prompt_tokens,
            visual_tokens = g.visual_tokens,
            new_tokens = g.tokens.len(),
            prefill_ms = g.prefill_ms,
            tokens_per_s = g.tokens_per_s(),
            "candle generation"
        );
        ReporterOutput {
            text: g.text.clone(),
            latency_ms: t0.elapsed().as_secs_f64() * 1e3,
            model: self.cfg.name.clone(),
        }
    }
}

impl LocalReporter for CandleVlmReporter {
    fn name(&self) -> &str {
        &self.cfg.name
    }

    fn frame_times(&self, duration_s: f64, fps: f64) -> Option<Vec<f64>> {
        self.family.frame_times(duration_s, fps)
    }

    fn frame_size(&self) -> Option<(u32, u32)> {
        self.family.frame_size()
    }

    fn generate(
        &self,
        clip: &ClipInput,
        cancel: &AtomicBool,
    ) -> Result<ReporterOutput, ModelError> {
        let t0 = Instant::now();
        let g = self.generate_blocking(clip.frames_for(&self.cfg.name), cancel)?;
        Ok(self.output(&g, t0))
    }

    /// One batch for all clips. A clip the processor refuses (no frames, mixed sizes) fails
    /// alone: the batch then runs clip by clip, so the others still get their answer.
    fn generate_batch(
        &self,
        clips: &[ClipInput],
        cancel: &AtomicBool,
    ) -> Vec<Result<ReporterOutput, ModelError>> {
        if clips.len() <= 1 {
            return clips.iter().map(|c| self.generate(c, cancel)).collect();
        }
        let t0 = Instant::now();
        let frames: Vec<&[Frame]> = clips.iter().map(|c| c.frames_for(&self.cfg.name)).collect();
        let prepared = match self.prepare(&frames) {
            Ok(p) => p,
            Err(e) => {
                tracing::debug!(reporter = %self.cfg.name, error = %e, "batch refused; clip by clip");
                return clips.iter().map(|c| self.generate(c, cancel)).collect();
            }
        };
        match self.run(&prepared, cancel, t0, false) {
            Ok(Run { gens, .. }) => gens.iter().map(|g| Ok(self.output(g, t0))).collect(),
            Err(ModelError::Timeout { .. }) => clips
                .iter()
                .map(|_| {
                    Err(ModelError::Timeout {
                        what: "generation (cancelled)".into(),
                        after: t0.elapsed(),
                    })
                })
                .collect(),
            // Each clip then gets its own error (or its answer, if another one broke the batch).
            Err(e) => {
                tracing::warn!(reporter = %self.cfg.name, error = %e, "batch failed; clip by clip");
                clips.iter().map(|c| self.generate(c, cancel)).collect()
            }
        }
    }
}
