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

mod checkpoint;
mod config;
mod generate;
mod reporter;
pub mod video;

pub use checkpoint::QwenVlEngine;
pub use config::CandleVlmConfig;
pub use generate::Generation;
pub use reporter::CandleVlmReporter;
pub use video::{smart_resize, VideoPatches, VideoProcessor, QWEN_DEFAULT_MEAN, QWEN_DEFAULT_STD};
