//! Text models: the sentence encoders behind the embedding labeler (BERT/MiniLM on candle or
//! ONNX Runtime) and the instruct LLMs of the GGUF labeler (decoders and the tokenizers GGUF
//! metadata describes).
//!
//! Why here and not in the labeler: the labeler's job is rules, matching, prompts and
//! constrained decoding; running a model is this crate's, with the same error type, weights
//! handling and parity discipline as the VLMs. The labeler uses these through
//! [`SentenceEncoder`] and [`gguf::Decoder`].

mod bert;
mod encoder;
pub mod gguf;
mod onnx_encoder;

pub use bert::{CandleEncoder, MAX_TOKENS};
pub use encoder::SentenceEncoder;
pub use onnx_encoder::{OnnxEncoderConfig, OnnxSentenceEncoder, ENCODER_MODEL_CANDIDATES};
