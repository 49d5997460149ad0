//! In-process VLM reporter on candle-transformers' `qwen3_vl`: for deployments that want a
//! (possibly LoRA fine-tuned) model on their own GPU without running a separate server.
//!
//! Two upstream quirks shape this module:
//! - candle's Qwen3-VL keeps its KV cache in private fields with no reset, so every generation
//!   builds a fresh model from weights held in memory (cheap: tensors are reference-counted).
//!   That rebuild also sizes the KV cache and RoPE table to the request instead of the
//!   checkpoint's 256k `max_position_embeddings`, which candle would allocate up front.
//! - an untied `lm_head` is built with a bias that the checkpoints lack; a zero one is added.
//! - its forward pass applies no causal mask when more than one token is fed at once, so by
//!   default the prompt text is prefilled one token at a time (see
//!   [`CandleVlmConfig::causal_prefill`]).

pub mod video;

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use candle_transformers::generation::LogitsProcessor;
use candle_transformers::models::qwen3_vl::{Config as QwenConfig, Qwen3VLModel};
use futures::future::BoxFuture;
use serde::{Deserialize, Serialize};
use tokenizers::Tokenizer;

use crate::lora::{load_adapter, merge_adapter};
use crate::reporter::{ClipInput, Reporter, ReporterOutput, DEFAULT_PROMPT};
use crate::weights::WeightSource;
use crate::{parse_device, Frame, FrameRef, ModelError};

pub use video::{smart_resize, VideoPatches, VideoProcessor, QWEN_DEFAULT_MEAN, QWEN_DEFAULT_STD};

fn default_device() -> String {
    "cpu".into()
}
fn default_max_new_tokens() -> usize {
    512
}
fn default_prompt() -> String {
    DEFAULT_PROMPT.into()
}
fn default_frames() -> usize {
    8
}
fn default_max_pixels() -> usize {
    640 * 360
}
fn default_min_pixels() -> usize {
    64 * 64
}
fn default_true() -> bool {
    true
}

/// One in-process Qwen3-VL reporter, as written in the service config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CandleVlmConfig {
    /// Reporter name in results and logs.
    pub name: String,
    /// Directory or HF-cache entry with `config.json`, `model.safetensors` (or shards) and
    /// `tokenizer.json`.
    pub weights: WeightSource,
    /// PEFT LoRA adapter merged into the weights at load.
    #[serde(default)]
    pub adapter: Option<WeightSource>,
    /// `"cpu"`, `"cuda"` or `"cuda:N"`.
    #[serde(default = "default_device")]
    pub device: String,
    /// `"f32"`, `"bf16"` or `"f16"`; unset means f32 on CPU (candle's CPU bf16 matmuls are
    /// slow) and bf16 on CUDA.
    #[serde(default)]
    pub dtype: Option<String>,
    #[serde(default = "default_max_new_tokens")]
    pub max_new_tokens: usize,
    /// Unset or 0: greedy, so a clip's report is reproducible.
    #[serde(default)]
    pub temperature: Option<f64>,
    #[serde(default)]
    pub top_p: Option<f64>,
    #[serde(default)]
    pub seed: u64,
    #[serde(default = "default_prompt")]
    pub prompt: String,
    /// At most this many of the clip's sampled frames go to the model (spread evenly).
    #[serde(default = "default_frames")]
    pub frames: usize,
    /// Per-frame pixel budget after resizing; bounds the visual token count.
    #[serde(default = "default_max_pixels")]
    pub max_pixels: usize,
    #[serde(default = "default_min_pixels")]
    pub min_pixels: usize,
    /// Feed prompt text one token at a time so attention is causal as in training. candle's
    /// multi-token forward attends bidirectionally; `false` trades that fidelity for a faster
    /// prefill (the video span is always one chunk, since its embeddings go in together).
    #[serde(default = "default_true")]
    pub causal_prefill: bool,
}

impl CandleVlmConfig {
    pub fn new(name: impl Into<String>, weights: WeightSource) -> Self {
        Self {
            name: name.into(),
            weights,
            adapter: None,
            device: default_device(),
            dtype: None,
            max_new_tokens: default_max_new_tokens(),
            temperature: None,
            top_p: None,
            seed: 0,
            prompt: default_prompt(),
            frames: default_frames(),
            max_pixels: default_max_pixels(),
            min_pixels: default_min_pixels(),
            causal_prefill: true,
        }
    }
}

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

/// Loaded weights, tokenizer and processor of one Qwen3-VL. Immutable after load; a model is
/// instantiated per generation (see the module docs).
pub struct QwenVlEngine {
    tensors: HashMap<String, Tensor>,
    config: QwenConfig,
    tokenizer: Tokenizer,
    device: Device,
    dtype: DType,
    video: VideoProcessor,
    eos: Vec<u32>,
    merged_lora: Vec<String>,
    model_id: String,
}

fn parse_dtype(s: Option<&str>, device: &Device) -> Result<DType, ModelError> {
    match s.map(|s| s.trim().to_ascii_lowercase()) {
        None => Ok(if device.is_cpu() {
            DType::F32
        } else {
            DType::BF16
        }),
        Some(s) => match s.as_str() {
            "f32" | "float32" => Ok(DType::F32),
            "bf16" | "bfloat16" => Ok(DType::BF16),
            "f16" | "float16" => Ok(DType::F16),
            other => Err(ModelError::BadConfig(format!(
                "dtype `{other}`; expected f32, bf16 or f16"
            ))),
        },
    }
}

/// Fills the fields candle's `TextConfig` requires but that HF configs put elsewhere or omit
/// (`tie_word_embeddings` at top level, `rope_theta` inside `rope_parameters` in newer
/// transformers), so real checkpoints load unmodified.
fn normalise_config(mut v: serde_json::Value) -> Result<QwenConfig, ModelError> {
    let top_tie = v.get("tie_word_embeddings").cloned();
    let tc = v
        .get_mut("text_config")
        .and_then(|t| t.as_object_mut())
        .ok_or_else(|| ModelError::BadConfig("config.json has no `text_config`".into()))?;
    if !tc.contains_key("tie_word_embeddings") {
        tc.insert(
            "tie_word_embeddings".into(),
            top_tie.unwrap_or(serde_json::Value::Bool(false)),
        );
    }
    if !tc.contains_key("rope_theta") {
        let theta = tc
            .get("rope_parameters")
            .and_then(|r| r.get("rope_theta"))
            .cloned()
            .unwrap_or(serde_json::json!(5_000_000.0));
        tc.insert("rope_theta".into(), theta);
    }
    if !tc.contains_key("head_dim") {
        let h = tc.get("hidden_size").and_then(|x| x.as_u64());
        let n = tc.get("num_attention_heads").and_then(|x| x.as_u64());
        if let Some(d) = h.zip(n).and_then(|(h, n)| h.checked_div(n)) {
            tc.insert("head_dim".into(), serde_json::json!(d));
        }
    }
    tc.entry("hidden_act").or_insert(serde_json::json!("silu"));
    tc.entry("rms_norm_eps").or_insert(serde_json::json!(1e-6));
    tc.entry("max_position_embeddings")
        .or_insert(serde_json::json!(262_144));
    serde_json::from_value(v).map_err(|e| ModelError::BadConfig(format!("Qwen3-VL config: {e}")))
}

/// `eos_token_id` may be a number or a list.
fn ids_of(v: Option<&serde_json::Value>) -> Vec<u32> {
    match v {
        Some(serde_json::Value::Number(n)) => {
            n.as_u64().map(|x| vec![x as u32]).unwrap_or_default()
        }
        Some(serde_json::Value::Array(a)) => a
            .iter()
            .filter_map(|x| x.as_u64().map(|x| x as u32))
            .collect(),
        _ => Vec::new(),
    }
}

fn load_tensors(files: &[std::path::PathBuf]) -> Result<HashMap<String, Tensor>, ModelError> {
    let mut all = HashMap::new();
    for f in files {
        let t = candle_core::safetensors::load(f, &Device::Cpu).map_err(|e| {
            ModelError::BadWeights {
                path: f.clone(),
                reason: e.to_string(),
            }
        })?;
        all.extend(t);
    }
    Ok(all)
}

fn tok_err(e: impl std::fmt::Display) -> ModelError {
    ModelError::BadConfig(format!("tokenizer: {e}"))
}

/// Sets the flag when the reporter's future is dropped (a `run_all` timeout), so the blocking
/// generation stops at the next token instead of holding the model for the full budget.
struct CancelOnDrop(Arc<AtomicBool>);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

impl QwenVlEngine {
    /// Reads config, weights (merging the adapter, if any), tokenizer and processor settings.
    /// Blocking and slow for real checkpoints: call it at startup or in `spawn_blocking`.
    pub fn load(cfg: &CandleVlmConfig) -> Result<Self, ModelError> {
        let device = parse_device(&cfg.device)?;
        let dtype = parse_dtype(cfg.dtype.as_deref(), &device)?;
        let raw: serde_json::Value = cfg.weights.read_json("config.json")?;
        let config = normalise_config(raw.clone())?;

        let files = cfg.weights.safetensors_files()?;
        let mut tensors = load_tensors(&files)?;
        let mut merged_lora = Vec::new();
        if let Some(adapter) = &cfg.adapter {
            let (lcfg, lt) = load_adapter(adapter)?;
            merged_lora = merge_adapter(&mut tensors, &lt, &lcfg).map_err(|e| match e {
                ModelError::BadWeights { reason, .. } => ModelError::BadWeights {
                    path: adapter
                        .resolve("adapter_model.safetensors")
                        .unwrap_or_default(),
                    reason,
                },
                other => other,
            })?;
            tracing::info!(
                reporter = %cfg.name,
                adapter = %adapter.describe(),
                modules = merged_lora.len(),
                "merged LoRA adapter"
            );
        }
        // candle builds an untied `lm_head` with a bias that Qwen checkpoints (8B and up,
        // untied) do not have; a zero bias is the same function.
        if !config.text_config.tie_word_embeddings && !tensors.contains_key("lm_head.bias") {
            if let Some(w) = tensors.get("lm_head.weight") {
                let bias = Tensor::zeros(w.dim(0)?, w.dtype(), w.device())?;
                tensors.insert("lm_head.bias".into(), bias);
            }
        }
        let tensors = tensors
            .into_iter()
            .map(|(k, t)| {
                // Integer tensors (none in Qwen3-VL today) must keep their dtype.
                let t = if t.dtype().is_float() {
                    t.to_dtype(dtype)?
                } else {
                    t
                };
                Ok((k, t.to_device(&device)?))
            })
            .collect::<Result<HashMap<_, _>, candle_core::Error>>()?;

        let tok_path = cfg.weights.resolve("tokenizer.json")?;
        let tokenizer = Tokenizer::from_file(&tok_path).map_err(|e| ModelError::BadWeights {
            path: tok_path.clone(),
            reason: e.to_string(),
        })?;

        // Statistics from the checkpoint's processor config (video first: Qwen3-VL ships both).
        let mut mean = QWEN_DEFAULT_MEAN;
        let mut std = QWEN_DEFAULT_STD;
        for f in ["video_preprocessor_config.json", "preprocessor_config.json"] {
            if cfg.weights.resolve_optional(f)?.is_some() {
                let p: serde_json::Value = cfg.weights.read_json(f)?;
                let triple = |k: &str| -> Option<[f32; 3]> {
                    let a = p.get(k)?.as_array()?;
                    if a.len() != 3 {
                        return None;
                    }
                    Some([
                        a[0].as_f64()? as f32,
                        a[1].as_f64()? as f32,
                        a[2].as_f64()? as f32,
                    ])
                };
                if let (Some(m), Some(s)) = (triple("image_mean"), triple("image_std")) {
                    mean = m;
                    std = s;
                    break;
                }
            }
        }
        let vc = &config.vision_config;
        let video = VideoProcessor {
            patch_size: vc.patch_size,
            temporal_patch_size: vc.temporal_patch_size,
            merge_size: vc.spatial_merge_size,
            mean,
            std,
            min_pixels: cfg.min_pixels,
            max_pixels: cfg.max_pixels,
        };
        if vc.temporal_patch_size != 2 {
            // candle's patch embedding splits the 3-D conv into exactly two 2-D convs.
            return Err(ModelError::BadConfig(format!(
                "temporal_patch_size {} is not supported by candle's qwen3_vl (needs 2)",
                vc.temporal_patch_size
            )));
        }

        let mut eos = Vec::new();
        if cfg
            .weights
            .resolve_optional("generation_config.json")?
            .is_some()
        {
            let g: serde_json::Value = cfg.weights.read_json("generation_config.json")?;
            eos.extend(ids_of(g.get("eos_token_id")));
        }
        if eos.is_empty() {
            eos.extend(ids_of(raw.get("eos_token_id")));
            eos.extend(ids_of(
                raw.get("text_config").and_then(|t| t.get("eos_token_id")),
            ));
        }
        // Chat models end their turn with <|im_end|> even where configs list only <|endoftext|>.
        if let Some(id) = tokenizer.token_to_id("<|im_end|>") {
            eos.push(id);
        }
        eos.sort_unstable();
        eos.dedup();
        for tok in ["<|im_start|>", "<|vision_start|>", "<|vision_end|>"] {
            if tokenizer.token_to_id(tok).is_none() {
                return Err(ModelError::BadConfig(format!(
                    "tokenizer at {} lacks `{tok}`",
                    tok_path.display()
                )));
            }
        }

        let engine = Self {
            tensors,
            config,
            tokenizer,
            device,
            dtype,
            video,
            eos,
            merged_lora,
            model_id: cfg.weights.describe(),
        };
        // Fail at startup, not on the first clip, if the weights do not fit the config.
        engine.build_model(16)?;
        Ok(engine)
    }

    /// A weight as the model sees it (after any LoRA merge, in the model's dtype and device).
    pub fn tensor(&self, key: &str) -> Option<&Tensor> {
        self.tensors.get(key)
    }

    /// Base weight keys the adapter changed.
    pub fn merged_lora_keys(&self) -> &[String] {
        &self.merged_lora
    }

    pub fn eos_ids(&self) -> &[u32] {
        &self.eos
    }

    pub fn video_processor(&self) -> &VideoProcessor {
        &self.video
    }

    pub fn tokenizer(&self) -> &Tokenizer {
        &self.tokenizer
    }

    fn build_model(&self, max_positions: usize) -> Result<Qwen3VLModel, ModelError> {
        let mut cfg = self.config.clone();
        cfg.text_config.max_position_embeddings = max_positions.max(1);
        let vb = VarBuilder::from_tensors(self.tensors.clone(), self.dtype, &self.device);
        Qwen3VLModel::new(&cfg, vb).map_err(|e| ModelError::BadWeights {
            path: self.model_id.clone().into(),
            reason: e.to_string(),
        })
    }

    /// Token ids of the simplest Qwen chat turn with the video in front of the prompt, and the
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

/// [`Reporter`] over a [`QwenVlEngine`]. The engine sits behind a mutex: one generation at a
/// time per model, since a second concurrent one would only contend for the same device and
/// double its activation memory.
pub struct CandleVlmReporter {
    cfg: CandleVlmConfig,
    engine: Arc<Mutex<QwenVlEngine>>,
}

impl CandleVlmReporter {
    /// Blocking (reads and converts every weight): call at startup or in `spawn_blocking`.
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
        Ok(Self {
            cfg,
            engine: Arc::new(Mutex::new(engine)),
        })
    }

    pub fn config(&self) -> &CandleVlmConfig {
        &self.cfg
    }

    /// The shared engine, for inspection (tests, `/readyz`); holding its lock blocks `run`.
    pub fn engine(&self) -> &Arc<Mutex<QwenVlEngine>> {
        &self.engine
    }

    /// Blocking generation with this reporter's settings; `run` wraps it.
    pub fn generate_blocking(
        &self,
        frames: &[Frame],
        cancel: &AtomicBool,
    ) -> Result<Generation, ModelError> {
        generate_with(&self.engine, &self.cfg, frames, cancel)
    }
}

fn generate_with(
    engine: &Mutex<QwenVlEngine>,
    cfg: &CandleVlmConfig,
    frames: &[Frame],
    cancel: &AtomicBool,
) -> Result<Generation, ModelError> {
    let picked: Vec<FrameRef> = video::spread_indices(frames.len(), cfg.frames)
        .into_iter()
        .map(|i| frames[i].as_ref())
        .collect();
    for f in &picked {
        f.validate()?;
    }
    let engine = engine
        .lock()
        .map_err(|_| ModelError::BadConfig("model poisoned by an earlier panic".into()))?;
    let mut sampler = LogitsProcessor::new(cfg.seed, cfg.temperature, cfg.top_p);
    engine.generate(
        &picked,
        &cfg.prompt,
        cfg.max_new_tokens,
        &mut sampler,
        cfg.causal_prefill,
        cancel,
    )
}

impl Reporter for CandleVlmReporter {
    fn name(&self) -> &str {
        &self.cfg.name
    }

    fn run<'a>(&'a self, clip: &'a ClipInput) -> BoxFuture<'a, Result<ReporterOutput, ModelError>> {
        Box::pin(async move {
            let t0 = Instant::now();
            let cancel = Arc::new(AtomicBool::new(false));
            let _guard = CancelOnDrop(cancel.clone());
            let engine = self.engine.clone();
            let cfg = self.cfg.clone();
            let frames = clip.frames.clone();
            let g =
                tokio::task::spawn_blocking(move || generate_with(&engine, &cfg, &frames, &cancel))
                    .await
                    .map_err(|e| {
                        if e.is_panic() {
                            std::panic::resume_unwind(e.into_panic())
                        } else {
                            ModelError::BadConfig(format!("generation task cancelled: {e}"))
                        }
                    })??;
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
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_defaults_from_toml_like_json() {
        let c: CandleVlmConfig =
            serde_json::from_str(r#"{"name":"q","weights":{"path":"/m"}}"#).unwrap();
        assert_eq!(c, CandleVlmConfig::new("q", WeightSource::local("/m")));
        assert_eq!(c.prompt, DEFAULT_PROMPT);
        assert!(c.causal_prefill && c.temperature.is_none());
    }

    #[test]
    fn dtype_defaults_per_device() {
        assert_eq!(parse_dtype(None, &Device::Cpu).unwrap(), DType::F32);
        assert_eq!(
            parse_dtype(Some("BF16"), &Device::Cpu).unwrap(),
            DType::BF16
        );
        assert!(parse_dtype(Some("f8"), &Device::Cpu).is_err());
    }

    #[test]
    fn eos_ids_accept_number_or_list() {
        assert_eq!(ids_of(Some(&serde_json::json!(5))), vec![5]);
        assert_eq!(ids_of(Some(&serde_json::json!([1, 2]))), vec![1, 2]);
        assert!(ids_of(None).is_empty());
    }

    #[test]
    fn config_fields_are_filled_from_hf_layout() {
        let v = serde_json::json!({
            "tie_word_embeddings": true,
            "image_token_id": 1, "video_token_id": 2,
            "vision_start_token_id": 3, "vision_end_token_id": 4,
            "vision_config": {},
            "text_config": {
                "vocab_size": 10, "hidden_size": 8, "intermediate_size": 16,
                "num_hidden_layers": 1, "num_attention_heads": 2, "num_key_value_heads": 1,
                "rope_parameters": {"rope_theta": 1000.0}
            }
        });
        let c = normalise_config(v).unwrap();
        assert!(c.text_config.tie_word_embeddings);
        assert_eq!(c.text_config.rope_theta, 1000.0);
        assert_eq!(c.text_config.head_dim, 4);
        assert!(normalise_config(serde_json::json!({})).is_err());
    }
}
