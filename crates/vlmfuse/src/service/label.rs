//! `POST /v1/label`: VLM answers → labels with their evidence, through the very labeler that
//! `/v1/infer` runs (the one `labeler_eval` scores), so a user can see why a label was chosen.

use super::pipeline::LabelerUnavailable;
use super::{stage, Service, ServiceError};
use std::time::Instant;
use vlmfuse_labeler::LabelerOutput;

/// Longest text `/v1/label` takes. A VLM answer is a few hundred words; a text this long is a
/// mistake, and labelling it would hold the labeler's worker for everyone.
pub const MAX_LABEL_TEXT_BYTES: usize = 64 * 1024;

/// What the labeler made of each text, in input order.
pub struct Labelled {
    /// The labeler's name, as `/v1/infer` reports it.
    pub labeler: String,
    pub outputs: Vec<LabelerOutput>,
    /// Wall time of the labelling call, queue wait included.
    pub label_ms: f64,
}

impl Service {
    /// Labels `texts` as one round (one `label_batch` call). Refuses an empty list and more
    /// than `limits.max_label_texts` texts; answers `NotReady` when the labeler cannot load.
    pub async fn label(&self, texts: &[String]) -> Result<Labelled, ServiceError> {
        let max = self.cfg.limits.max_label_texts;
        if texts.is_empty() {
            return Err(ServiceError::Invalid(
                "`text` is an empty list: send a string or a non-empty list of strings".into(),
            ));
        }
        if texts.len() > max {
            return Err(ServiceError::Invalid(format!(
                "{} texts in one request; at most {max} (limits.max_label_texts)",
                texts.len()
            )));
        }
        if let Some((i, t)) = texts
            .iter()
            .enumerate()
            .find(|(_, t)| t.len() > MAX_LABEL_TEXT_BYTES)
        {
            return Err(ServiceError::Invalid(format!(
                "text[{i}] has {} bytes; at most {MAX_LABEL_TEXT_BYTES}",
                t.len()
            )));
        }
        let labeler =
            self.pipeline
                .label_route_labeler()
                .await
                .map_err(|LabelerUnavailable(why)| ServiceError::NotReady {
                    message: format!("the labeler is not available: {why}"),
                    not_ready: vec![why],
                })?;
        let refs: Vec<&str> = texts.iter().map(String::as_str).collect();
        let start = Instant::now();
        let outputs = labeler
            .label_batch(&refs)
            .await
            .map_err(ServiceError::Labeler)?;
        let label_ms = stage("label", start);
        metrics::counter!("vlmfuse_labelled_texts_total").increment(texts.len() as u64);
        Ok(Labelled {
            labeler: labeler.name().to_string(),
            outputs,
            label_ms,
        })
    }
}
