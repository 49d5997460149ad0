//! Model architectures owned by this crate, in candle-transformers' file layout
//! (`config` / `vision` / `text` per model), where candle-transformers is wrong or lacks what the
//! service needs (input embeddings, batched masks, a reusable KV cache).

pub mod video_llava;
