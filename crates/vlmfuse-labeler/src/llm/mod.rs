//! The pieces of the LLM labelers: the shared prompt and validator, chat templates and the
//! constrained decoder. The GGUF decoders and tokenizers they drive are model code and live in
//! `vlmfuse_models::text::gguf`.

pub mod constrain;
pub mod prompt;
pub mod template;
