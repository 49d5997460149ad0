//! In-process model architectures owned by this crate, where candle-transformers is missing one
//! or computes something other than the reference implementation (input embeddings, batched
//! masks, a reusable KV cache). Each follows candle-transformers' layout (`config`, `vision`,
//! `text`, ...) on candle-nn layers and has parity tests against transformers' outputs
//! (`tests/*_parity.rs`).

pub mod common;
pub mod family;
pub mod qwen3_vl;
pub mod video_llava;
pub mod videollama2;
pub mod vlaad;
