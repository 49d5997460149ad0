//! The in-process Qwen3-VL as a [`LocalReporter`]: a loaded engine plus this reporter's
//! generation settings. The service wraps it in a [`BackendPool`](vlmfuse_core::BackendPool),
//! which runs one generation at a time and queues the rest, so the engine needs no lock.

use std::sync::atomic::AtomicBool;
use std::time::Instant;

use candle_transformers::generation::LogitsProcessor;

use super::checkpoint::QwenVlEngine;
use super::config::CandleVlmConfig;
use super::generate::Generation;
use super::video;
use crate::reporter::{ClipInput, LocalReporter, ReporterOutput};
use crate::{Frame, FrameRef, ModelError};

/// [`LocalReporter`] over a [`QwenVlEngine`]. One generation at a time per model comes from its
/// pool (a second concurrent one would only contend for the same device and double its
/// activation memory), not from a lock here.
pub struct CandleVlmReporter {
    cfg: CandleVlmConfig,
    engine: QwenVlEngine,
}

impl CandleVlmReporter {
    /// Blocking (reads and converts every weight): call at startup, off the async threads.
    pub fn load(cfg: CandleVlmConfig) -> Result<Self, ModelError> {
        if cfg.frames == 0 {
            return Err(ModelError::BadConfig(format!(
                "reporter `{}`: frames must be at least 1",
                cfg.name
            )));
        }
        let t0 = Instant::now();
        let engine = QwenVlEngine::load(&cfg)?;
        tracing::info!(
            reporter = %cfg.name,
            weights = %cfg.weights.describe(),
            device = %cfg.device,
            ms = t0.elapsed().as_secs_f64() * 1e3,
            "loaded candle Qwen3-VL"
        );
        Ok(Self { cfg, engine })
    }

    pub fn config(&self) -> &CandleVlmConfig {
        &self.cfg
    }

    /// The loaded engine, for inspection (tests, `/readyz`).
    pub fn engine(&self) -> &QwenVlEngine {
        &self.engine
    }

    /// Blocking generation with this reporter's settings.
    pub fn generate_blocking(
        &self,
        frames: &[Frame],
        cancel: &AtomicBool,
    ) -> Result<Generation, ModelError> {
        let cfg = &self.cfg;
        let picked: Vec<FrameRef> = video::spread_indices(frames.len(), cfg.frames)
            .into_iter()
            .map(|i| frames[i].as_ref())
            .collect();
        for f in &picked {
            f.validate()?;
        }
        let mut sampler = LogitsProcessor::new(cfg.seed, cfg.temperature, cfg.top_p);
        self.engine.generate(
            &picked,
            &cfg.prompt,
            cfg.max_new_tokens,
            &mut sampler,
            cfg.causal_prefill,
            cancel,
        )
    }
}

impl LocalReporter for CandleVlmReporter {
    fn name(&self) -> &str {
        &self.cfg.name
    }

    fn generate(
        &self,
        clip: &ClipInput,
        cancel: &AtomicBool,
    ) -> Result<ReporterOutput, ModelError> {
        let t0 = Instant::now();
        let g = self.generate_blocking(&clip.frames, cancel)?;
        tracing::debug!(
            reporter = %self.cfg.name,
            prompt_tokens = g.prompt_tokens,
            visual_tokens = g.visual_tokens,
            new_tokens = g.tokens.len(),
            prefill_ms = g.prefill_ms,
            tokens_per_s = g.tokens_per_s(),
            "candle generation"
        );
        Ok(ReporterOutput {
            text: g.text,
            latency_ms: t0.elapsed().as_secs_f64() * 1e3,
            model: self.cfg.name.clone(),
        })
    }
}
