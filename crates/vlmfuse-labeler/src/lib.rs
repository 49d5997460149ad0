//! Maps the free text of a VLM answer onto a fixed label ontology.
//!
//! The fusion engine only sees binary reports per label, so everything a VLM says must first be
//! turned into a label set. Three backends trade accuracy for cost and independence:
//!
//! * [`EmbeddingLabeler`] (the offline default): the annotation guidelines' rules
//!   (`tests/data/labeler/GUIDELINES.md`: negation, hedge and agent scopes, lexical label rules)
//!   plus sentence embeddings (all-MiniLM-L6-v2) for the paraphrases the rules do not list, all
//!   clauses of a round in one encoder pass.
//! * [`GgufLabeler`]: the paper's LLM labelling step in process: an instruct LLM from a GGUF file
//!   (Llama 3.x, Qwen2/3, Gemma 3) under constrained decoding, so that its answer is always a
//!   valid list of ontology ids.
//! * [`OpenAiLabeler`]: any OpenAI-compatible chat API with the same prompt, its answer validated
//!   against the ontology.
//!
//! Every output carries [`Evidence`]: which clause turned a label on (or was discounted as
//! negated or hedged), so that users can see why a label was chosen.

pub mod assets;
mod embedding;
mod error;
mod gguf;
pub mod llm;
mod openai;
pub mod rules;
pub mod text;
pub mod tiny_gguf;

pub use embedding::{EmbeddingConfig, EmbeddingLabeler, ItemMatch, Reading};
pub use error::{LabelerError, LabelerErrorKind};
pub use gguf::{Generation, GgufConfig, GgufLabeler, TemplateSource};
pub use openai::{OpenAiConfig, OpenAiLabeler};
pub use vlmfuse_core::{BackendPool, PoolConfig};
// The encoders run in the models crate; re-exported because the labeler's configs name them.
pub use vlmfuse_core::{Label, Ontology, OntologyError};
pub use vlmfuse_models::text::{
    CandleEncoder, OnnxEncoderConfig, OnnxSentenceEncoder, SentenceEncoder,
    ENCODER_MODEL_CANDIDATES,
};

use futures::future::BoxFuture;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicBool, Ordering};

/// The score one label got for one text. What the number means depends on the backend
/// (cosine similarity, yes-probability, 0/1 for an LLM), so only compare scores within a backend.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabelScore {
    pub id: String,
    pub score: f32,
}

/// What produced a piece of evidence.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum EvidenceSource {
    /// A lexical rule of the annotation guidelines (e.g. "slow down" is braking).
    Rule,
    /// Sentence-embedding similarity to a paraphrase of the label.
    Embedding,
    /// An LLM chose the label reading the whole answer.
    Llm,
}

/// Why a label is on, or why a mention of it did not count.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Evidence {
    /// Label id.
    pub label: String,
    /// The clause of the answer the evidence comes from; empty for LLM labelers, which read the
    /// whole answer.
    pub clause: String,
    /// Backend-specific strength (rule: 1; embedding: cosine; LLM: the model's probability).
    pub score: f32,
    /// The clause negates the label ("no need to brake").
    pub negated: bool,
    /// The clause hedges it ("be prepared to stop", "brake if ...").
    pub hedged: bool,
    pub source: EvidenceSource,
    /// Whether this evidence turned the label on; negated or hedged mentions are listed too, with
    /// `accepted: false`, so a user can see that they were read and discounted.
    pub accepted: bool,
}

/// Result of labelling one text.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabelerOutput {
    /// Ids of the labels that are on, in ontology order.
    pub labels: Vec<String>,
    /// One score per ontology label, in ontology order, so callers can re-threshold.
    pub scores: Vec<LabelScore>,
    /// Evidence for every label that is on, and for discounted mentions.
    #[serde(default)]
    pub evidence: Vec<Evidence>,
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
        Self {
            labels,
            scores,
            evidence: Vec::new(),
        }
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

    /// Labels several texts (the answers of one round). The embedding labeler overrides this to
    /// encode every clause of every text in one pass; the default labels them one after another.
    /// Outputs are in input order; the first error fails the batch.
    fn label_batch<'a>(
        &'a self,
        texts: &'a [&'a str],
    ) -> BoxFuture<'a, Result<Vec<LabelerOutput>, LabelerError>> {
        Box::pin(async move {
            let mut out = Vec::with_capacity(texts.len());
            for t in texts {
                out.push(self.label(t).await?);
            }
            Ok(out)
        })
    }
}

/// A local labeler whose model work blocks the calling thread (the embedding and GGUF
/// labelers). Batch tools call it directly; the service wraps it in a [`BackendPool`].
pub trait BlockingLabeler: Send + Sync + 'static {
    /// Stable name for logs and metrics.
    fn name(&self) -> &str;
    /// Labels a text on the calling thread.
    fn label_blocking(&self, text: &str) -> Result<LabelerOutput, LabelerError>;

    /// Labels several texts on the calling thread, outputs in input order. The embedding
    /// labeler overrides it to run every clause of every text in one encoder pass; the default
    /// labels them one after another.
    fn label_batch_blocking(&self, texts: &[&str]) -> Result<Vec<LabelerOutput>, LabelerError> {
        texts.iter().map(|t| self.label_blocking(t)).collect()
    }

    /// As [`BlockingLabeler::label_batch_blocking`], stopping with [`LabelerError::Cancelled`]
    /// once `cancel` is set (the service's adapter sets it when the caller gives up), so that an
    /// abandoned round does not hold the worker. The default checks between texts; a labeler
    /// that batches all texts in one fast pass may ignore it, and a slow one (token-by-token
    /// generation) checks at every step.
    fn label_batch_cancellable(
        &self,
        texts: &[&str],
        cancel: &AtomicBool,
    ) -> Result<Vec<LabelerOutput>, LabelerError> {
        let mut out = Vec::with_capacity(texts.len());
        for t in texts {
            if cancel.load(Ordering::Relaxed) {
                return Err(LabelerError::Cancelled);
            }
            out.push(self.label_blocking(t)?);
        }
        Ok(out)
    }
}

impl<B: BlockingLabeler + ?Sized> Labeler for BackendPool<B> {
    fn name(&self) -> &str {
        self.backend().name()
    }

    fn label<'a>(&'a self, text: &'a str) -> BoxFuture<'a, Result<LabelerOutput, LabelerError>> {
        let text = text.to_string();
        Box::pin(async move {
            self.call(move |b, cancel| {
                b.label_batch_cancellable(&[&text], cancel)?
                    .pop()
                    .ok_or_else(|| LabelerError::Internal("no output for the text".into()))
            })
            .await?
        })
    }

    /// One pool call for the whole round, so that the backend's batching (one encoder pass)
    /// survives the adapter and the round waits in the queue once, not once per answer.
    fn label_batch<'a>(
        &'a self,
        texts: &'a [&'a str],
    ) -> BoxFuture<'a, Result<Vec<LabelerOutput>, LabelerError>> {
        let texts: Vec<String> = texts.iter().map(|t| t.to_string()).collect();
        Box::pin(async move {
            self.call(move |b, cancel| {
                let refs: Vec<&str> = texts.iter().map(String::as_str).collect();
                b.label_batch_cancellable(&refs, cancel)
            })
            .await?
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicUsize;
    use std::sync::Arc;

    /// Counts its calls and cancels the round after the first one, as a caller giving up would.
    struct Slow {
        calls: AtomicUsize,
        cancel_after_first: Arc<AtomicBool>,
    }

    impl BlockingLabeler for Slow {
        fn name(&self) -> &str {
            "slow"
        }
        fn label_blocking(&self, _text: &str) -> Result<LabelerOutput, LabelerError> {
            self.calls.fetch_add(1, Ordering::SeqCst);
            self.cancel_after_first.store(true, Ordering::SeqCst);
            Ok(LabelerOutput {
                labels: Vec::new(),
                scores: Vec::new(),
                evidence: Vec::new(),
            })
        }
    }

    #[test]
    fn a_cancelled_round_stops_between_texts() {
        let cancel = Arc::new(AtomicBool::new(false));
        let l = Slow {
            calls: AtomicUsize::new(0),
            cancel_after_first: cancel.clone(),
        };
        let r = l.label_batch_cancellable(&["a", "b", "c"], &cancel);
        assert!(matches!(r, Err(LabelerError::Cancelled)), "{r:?}");
        assert_eq!(l.calls.load(Ordering::SeqCst), 1);
        // Not cancelled: every text, in order.
        let l = Slow {
            calls: AtomicUsize::new(0),
            cancel_after_first: Arc::new(AtomicBool::new(false)),
        };
        let never = AtomicBool::new(false);
        assert_eq!(
            l.label_batch_cancellable(&["a", "b", "c"], &never)
                .unwrap()
                .len(),
            3
        );
    }
}
