//! `kind = "candle"`: an in-process VLM on the project's own model code
//! ([`crate::models::qwen3_vl`], [`crate::models::video_llava`]), which matches transformers to
//! 1e-4 in f32 (`tests/*_parity.rs`). `config.json`'s `model_type` picks the architecture; the
//! checkpoint's processor configs decide preprocessing. The model is loaded once and shared by
//! every request; each generation owns its KV cache.

mod config;
mod reporter;

pub use crate::models::family::{
    spread_indices, supported_model_types, AnyFamily, InputView, Prepared,
};
pub use config::{parse_dtype, CandleVlmConfig, RawCandleVlmConfig, DEFAULT_QWEN_FRAMES};
pub use reporter::{CandleVlmReporter, Generation, Trace};
