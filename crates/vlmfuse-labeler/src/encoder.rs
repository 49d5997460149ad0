//! The sentence-encoder seam of the embedding labeler.
//!
//! Why a trait: the matcher only needs "texts in, unit vectors out", while the engine that runs
//! the encoder is a deployment choice (candle on CUDA machines, ONNX Runtime on CPU-only ones).
//! Keeping the engine behind this trait lets both run the very same matcher, so the labeler that
//! is evaluated is the labeler that is served, whatever the engine.

use crate::LabelerError;

/// A sentence encoder: mean-pooled, L2-normalised embeddings.
///
/// Implementations are blocking (they run model work on the calling thread or their own pool);
/// callers on an async runtime go through the service's blocking-backend adapter.
pub trait SentenceEncoder: Send + Sync {
    /// The engine, for logs and `/readyz` ("candle", "onnx").
    fn engine(&self) -> &str;
    /// Embedding dimension.
    fn dim(&self) -> usize;
    /// One unit-L2 embedding per text, in order, computed in one batched pass (padding with an
    /// attention mask), so that all clauses of all answers of a round cost one forward call.
    /// An empty input gives an empty output.
    fn encode(&self, texts: &[&str]) -> Result<Vec<Vec<f32>>, LabelerError>;
}
