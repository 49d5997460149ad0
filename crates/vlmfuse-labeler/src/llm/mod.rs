//! The pieces of the LLM labelers: the shared prompt and validator, chat templates, GGUF
//! tokenizers and models, and the constrained decoder.

pub mod constrain;
pub mod gemma3;
pub mod model;
pub mod prompt;
pub mod template;
pub mod tokenizer;
