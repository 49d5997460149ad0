//! `/v1/fuse` and the one fuse-and-store path that `/v1/infer` shares, plus feedback.

use super::writer::{Cmd, FeedbackDone};
use super::{Service, ServiceError};
use crate::wire::{feedback_out, fuse_out, FeedbackOut, FuseOut};
use serde_json::Value;
use std::time::Instant;
use tokio::sync::oneshot;
use vlmfuse_fusion::{FusionError, RoundRecord};
use vlmfuse_store::{round_id, NewRound};

/// What `/v1/fuse` answers: the rounds, and whether the request was a batch.
pub struct Fused {
    pub rounds: Vec<FuseOut>,
    pub batch: bool,
}

impl Service {
    /// `POST /v1/fuse`: one SPEC §8 round (without truth) or `{"rounds": [...]}`.
    pub async fn fuse(&self, body: Value) -> Result<Fused, ServiceError> {
        let delay = self.hooks.fuse_delay();
        if !delay.is_zero() {
            tokio::time::sleep(delay).await;
        }
        let (records, batch) = parse_fuse_body(body, self.cfg.limits.max_batch_rounds)?;
        let records = records
            .into_iter()
            .map(|rec| {
                let request = serde_json::json!({ "id": rec.id, "reports": rec.reports });
                (rec, request)
            })
            .collect();
        let rounds = self.fuse_and_store(records, batch).await?;
        Ok(Fused { rounds, batch })
    }

    /// The one store/fuse path of /v1/fuse and /v1/infer: validates every record, infers each
    /// against the state as it stands (off the async threads, under the read lock), then hands
    /// the rounds to the writer and returns them numbered. `request` is what the database keeps
    /// with the round. All or nothing.
    pub(super) async fn fuse_and_store(
        &self,
        records: Vec<(RoundRecord, Value)>,
        batch: bool,
    ) -> Result<Vec<FuseOut>, ServiceError> {
        let shared = self.shared.clone();
        let metrics = self.metrics.clone();
        let hold = self.hooks.fuse_hold();
        // Inference is CPU work (about a millisecond at a 10k bank): off the async threads,
        // under a read lock only, so concurrent fuse requests run in parallel and feedback waits
        // for none.
        let (outs, new_rounds) = tokio::task::spawn_blocking(move || {
            metrics.scope(|| {
                let eng = shared.engine.blocking_read();
                if !hold.is_zero() {
                    std::thread::sleep(hold);
                }
                let mut dim = eng.dim();
                let mut parsed = Vec::with_capacity(records.len());
                for (idx, (rec, request)) in records.into_iter().enumerate() {
                    let at = |e: FusionError| -> ServiceError {
                        if batch {
                            ServiceError::InBatch {
                                index: idx,
                                source: e,
                            }
                        } else {
                            e.into()
                        }
                    };
                    if let (Some(e), d) = (dim, rec.context.len()) {
                        if e != d && d > 0 {
                            return Err(at(FusionError::Dimension {
                                expected: e,
                                got: d,
                            }));
                        }
                    }
                    let (round, _) = eng.parse(&rec).map_err(at)?;
                    dim.get_or_insert(round.context.len());
                    parsed.push((rec, request, round));
                }
                let infer_start = Instant::now();
                let mut outs = Vec::with_capacity(parsed.len());
                let mut new_rounds = Vec::with_capacity(parsed.len());
                let created_ms = vlmfuse_store::timestamp_ms();
                for (rec, request, round) in parsed {
                    let inf = eng.infer(&round);
                    // The round id is set once the writer has numbered the round.
                    outs.push(fuse_out(&eng, 0, rec.id.clone(), &inf));
                    new_rounds.push(NewRound {
                        round,
                        inference: inf,
                        request,
                        created_ms,
                    });
                }
                metrics::histogram!("vlmfuse_fusion_duration_seconds")
                    .record(infer_start.elapsed().as_secs_f64());
                Ok::<_, ServiceError>((outs, new_rounds))
            })
        })
        .await
        .map_err(|e| ServiceError::Internal(format!("inference task failed: {e}")))??;

        let (tx, rx) = oneshot::channel();
        self.send(Cmd::Insert {
            rounds: new_rounds,
            reply: tx,
        })?;
        let first = rx.await.map_err(|_| ServiceError::WriterStopped)??;

        let mut rounds = outs;
        for (i, r) in rounds.iter_mut().enumerate() {
            r.round_id = round_id(first + i as u64);
        }
        Ok(rounds)
    }

    /// `POST /v1/feedback`: labels a fused round; idempotent per round. Returns the answer and
    /// whether it repeats an earlier feedback.
    pub async fn feedback(
        &self,
        round_id: String,
        labels: &[String],
    ) -> Result<(FeedbackOut, bool), ServiceError> {
        let truth = {
            let eng = self.shared.engine.read().await;
            eng.encode_truth(labels)?
        };
        let (tx, rx) = oneshot::channel();
        // Once sent, the writer finishes the feedback even if this request is dropped (timeout,
        // client gone); a repeat then answers with the committed result.
        self.send(Cmd::Feedback {
            round_id,
            truth,
            reply: tx,
        })?;
        let done: FeedbackDone = rx.await.map_err(|_| ServiceError::WriterStopped)??;
        let eng = self.shared.engine.read().await;
        Ok((feedback_out(&eng, &done), done.repeated))
    }
}

/// Splits the body into records, refusing truth (feedback has its own route, so a round cannot
/// be labelled twice by two paths) and batches over the limit.
fn parse_fuse_body(
    body: Value,
    max_batch: usize,
) -> Result<(Vec<RoundRecord>, bool), ServiceError> {
    let Value::Object(obj) = body else {
        return Err(ServiceError::Invalid(
            "the body must be a JSON object: one round, or {\"rounds\": [...]}".into(),
        ));
    };
    let (values, batch) = if obj.contains_key("rounds") && !obj.contains_key("context") {
        if obj.len() != 1 {
            return Err(ServiceError::Invalid(
                "a batch is {\"rounds\": [...]} with no other field".into(),
            ));
        }
        match obj.into_iter().next().map(|(_, v)| v) {
            Some(Value::Array(a)) => (a, true),
            _ => return Err(ServiceError::Invalid("\"rounds\" must be an array".into())),
        }
    } else {
        (vec![Value::Object(obj)], false)
    };
    if values.is_empty() {
        return Err(ServiceError::Invalid("\"rounds\" is empty".into()));
    }
    if values.len() > max_batch {
        return Err(ServiceError::Invalid(format!(
            "{} rounds in one request; the limit is {max_batch}",
            values.len()
        )));
    }
    let mut out = Vec::with_capacity(values.len());
    for (i, v) in values.into_iter().enumerate() {
        let at = |m: String| {
            if batch {
                format!("rounds[{i}]: {m}")
            } else {
                m
            }
        };
        if !v.is_object() {
            return Err(ServiceError::Invalid(at(
                "a round must be a JSON object".into()
            )));
        }
        if v.get("truth").is_some_and(|t| !t.is_null()) {
            return Err(ServiceError::TruthNotAccepted(at(
                "/v1/fuse does not take \"truth\": fuse the round, then send its labels to \
                 POST /v1/feedback with the returned round_id"
                    .into(),
            )));
        }
        let rec: RoundRecord =
            serde_json::from_value(v).map_err(|e| ServiceError::Invalid(at(e.to_string())))?;
        out.push(rec);
    }
    Ok((out, batch))
}
