//! Maps the free text of a VLM answer onto a fixed label ontology.
//!
//! The fusion engine only sees binary reports per label, so everything a VLM says must first be
//! turned into a label set. Three backends trade accuracy for cost and independence:
//!
//! * [`EmbeddingLabeler`] (the offline default): sentence embeddings (all-MiniLM-L6-v2) of each
//!   clause against paraphrase prototypes per label, with explicit negation handling, because
//!   embeddings alone cannot tell "brake" from "no need to brake".
//! * [`GgufLabeler`]: a small in-process base LLM (gemma-3-270m) scored with yes/no likelihoods,
//!   for when no embedding prototypes are written for a custom ontology.
//! * [`OpenAiLabeler`]: any OpenAI-compatible chat API, strict JSON validated against the ontology.

pub mod assets;
mod embedding;
mod encoder;
mod encoder_onnx;
mod error;
mod gguf;
mod negation;
mod openai;
mod sp_tokenizer;

pub use embedding::{ClauseSims, EmbeddingConfig, EmbeddingLabeler};
pub use encoder::SentenceEncoder;
pub use encoder_onnx::{OnnxEncoderConfig, OnnxSentenceEncoder, ENCODER_MODEL_CANDIDATES};
pub use error::{LabelerError, LabelerErrorKind};
pub use gguf::{GgufConfig, GgufLabeler};
pub use negation::{is_negated, split_clauses};
pub use openai::{OpenAiConfig, OpenAiLabeler};
pub use sp_tokenizer::SpTokenizer;
pub use vlmfuse_core::{BackendPool, PoolConfig};
pub use vlmfuse_core::{Label, Ontology, OntologyError};

use futures::future::BoxFuture;
use serde::{Deserialize, Serialize};

/// The score one label got for one text. What the number means depends on the backend
/// (cosine similarity, yes-probability, 0/1 for an LLM), so only compare scores within a backend.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabelScore {
    pub id: String,
    pub score: f32,
}

/// Result of labelling one text.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabelerOutput {
    /// Ids of the labels that are on, in ontology order.
    pub labels: Vec<String>,
    /// One score per ontology label, in ontology order, so callers can re-threshold.
    pub scores: Vec<LabelScore>,
}

impl LabelerOutput {
    /// Builds an output from ontology-ordered scores and decisions; keeps the two in step.
    pub(crate) fn from_decisions(ontology: &Ontology, scores: &[f32], on: &[bool]) -> Self {
        let labels = ontology
            .labels()
            .iter()
            .zip(on)
            .filter(|(_, &b)| b)
            .map(|(l, _)| l.id.clone())
            .collect();
        let scores = ontology
            .labels()
            .iter()
            .zip(scores)
            .map(|(l, &s)| LabelScore {
                id: l.id.clone(),
                score: s,
            })
            .collect();
        Self { labels, scores }
    }

    /// Builds an output from ontology-ordered scores, a label being on when its score reaches its
    /// threshold (the rule the embedding and GGUF labelers share).
    pub(crate) fn thresholded(ontology: &Ontology, scores: &[f32], thresholds: &[f32]) -> Self {
        let on: Vec<bool> = scores.iter().zip(thresholds).map(|(s, t)| s >= t).collect();
        Self::from_decisions(ontology, scores, &on)
    }

    pub fn score_of(&self, id: &str) -> Option<f32> {
        self.scores.iter().find(|s| s.id == id).map(|s| s.score)
    }
}

/// A backend that turns one VLM answer into labels, as the service calls it.
///
/// Async because the remote backend waits on the network. Local backends implement
/// [`BlockingLabeler`] instead and get this trait from the one adapter,
/// [`BackendPool`](vlmfuse_core::BackendPool): their own worker thread, a bounded queue, and
/// cancellation when the caller gives up.
pub trait Labeler: Send + Sync {
    /// Stable name for logs and metrics.
    fn name(&self) -> &str;
    fn label<'a>(&'a self, text: &'a str) -> BoxFuture<'a, Result<LabelerOutput, LabelerError>>;
}

/// A local labeler whose model work blocks the calling thread (the embedding and GGUF
/// labelers). Batch tools call it directly; the service wraps it in a [`BackendPool`].
pub trait BlockingLabeler: Send + Sync + 'static {
    /// Stable name for logs and metrics.
    fn name(&self) -> &str;
    /// Labels a text on the calling thread.
    fn label_blocking(&self, text: &str) -> Result<LabelerOutput, LabelerError>;
}

impl<B: BlockingLabeler + ?Sized> Labeler for BackendPool<B> {
    fn name(&self) -> &str {
        self.backend().name()
    }

    fn label<'a>(&'a self, text: &'a str) -> BoxFuture<'a, Result<LabelerOutput, LabelerError>> {
        let text = text.to_string();
        Box::pin(async move { self.call(move |b, _| b.label_blocking(&text)).await? })
    }
}
