//! Instruct LLMs from a GGUF file: the decoder families candle runs (Llama, Qwen2, Qwen3, and
//! Gemma 3 on this crate's own decoder) and the tokenizer the file's metadata describes.

pub mod gemma3;
pub mod model;
pub mod sp_tokenizer;
pub mod tokenizer;

pub use model::{Decoder, Family};
pub use sp_tokenizer::SpTokenizer;
pub use tokenizer::{bytes_to_unicode, GgufTokenizer};
