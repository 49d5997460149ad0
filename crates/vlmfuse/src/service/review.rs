//! `GET /v1/review`: which stored rounds a person should label next (docs/METHOD.md, "The
//! review queue"). The ranking is `vlmfuse_fusion::review` (no I/O); this reads its candidates,
//! the latest `window` rounds, through the operator page's read-only connection, off the async
//! threads. Nothing here changes state.

use super::{Service, ServiceError};
use serde::Serialize;
use std::sync::atomic::Ordering;
use vlmfuse_fusion::review::{rank, Candidate};
use vlmfuse_fusion::UNKNOWN;

/// Most rounds one queue lists.
pub const MAX_LIMIT: usize = 100;
/// Most rounds one queue is built over: the ranking costs `window^2` cosines.
pub const MAX_WINDOW: usize = 2000;
/// Rounds a queue is built over when the request does not say.
pub const DEFAULT_WINDOW: usize = 1000;

#[derive(Debug, Serialize)]
pub struct ReviewItem {
    round_id: String,
    seq: u64,
    created_ms: i64,
    /// The weighted share of the window's unlabelled rounds this one came to stand for.
    score: f64,
    /// Candidates whose closest labelled-or-queued round it became.
    represents: usize,
    /// 1 - the best cosine to a labelled or earlier-queued round.
    novelty: f64,
    /// Mean over its unknown labels of `4 p (1 - p)` (`p`: the share of reporters saying yes).
    disagreement: f64,
    /// Mean over its unknown labels of `1 - |2q - 1|` (`q`: the posterior it was served).
    uncertainty: f64,
    /// The labels whose truth would be new (all, unless feedback gave some).
    unknown: Vec<String>,
    /// Those of them on which the reporters split.
    disputed: Vec<String>,
    /// Why, in words.
    reasons: Vec<String>,
}

#[derive(Debug, Serialize)]
pub struct ReviewQueue {
    /// Rounds stored when the queue was built.
    rounds: u64,
    /// The window asked for, and the rounds read (the latest ones).
    window: usize,
    considered: usize,
    /// Of those: rounds with every label known (they only cover), and candidates.
    labelled: usize,
    candidates: usize,
    rule: &'static str,
    queue: Vec<ReviewItem>,
}

const RULE: &str = "weighted facility location over the window's contexts: each pick is the \
                    round that best stands for the unlabelled rounds no labelled or queued round \
                    is close to, a round where the reporters split weighing up to three times \
                    one where they agree";

impl Service {
    /// `GET /v1/review?limit=&window=`.
    pub async fn review(&self, limit: usize, window: usize) -> Result<ReviewQueue, ServiceError> {
        if limit == 0 || limit > MAX_LIMIT {
            return Err(ServiceError::Invalid(format!(
                "limit must be between 1 and {MAX_LIMIT}, got {limit}"
            )));
        }
        if window == 0 || window > MAX_WINDOW {
            return Err(ServiceError::Invalid(format!(
                "window must be between 1 and {MAX_WINDOW}, got {window}"
            )));
        }
        let total = self.shared.rounds.load(Ordering::SeqCst);
        let (names, ont) = {
            let eng = self.shared.engine.read().await;
            (eng.reporters().len(), eng.ontology().clone())
        };
        let l = ont.labels().len();
        let ids: Vec<String> = ont.labels().iter().map(|x| x.id.clone()).collect();
        self.with_reader(move |s| {
            let rows = s.recent_rounds(Some(total), window)?;
            let mut labelled = Vec::new();
            let mut cands = Vec::new();
            let mut created = std::collections::HashMap::new();
            for row in &rows {
                let mut known = vec![false; l];
                if row.labelled {
                    for fb in s.feedback(row.seq)? {
                        for (k, &t) in fb.truth.iter().enumerate().take(l) {
                            known[k] |= t != UNKNOWN;
                        }
                    }
                }
                let context = unit(&row.round.context);
                if known.iter().all(|&k| k) {
                    labelled.push(context);
                    continue;
                }
                let mut present = row.round.present.clone();
                present.resize(names, false);
                let mut reports = row.round.reports.clone();
                reports.resize(names * l, 0);
                let mut q = row.inference.q.clone();
                q.resize(l, 0.5);
                created.insert(row.seq, row.created_ms);
                cands.push(Candidate {
                    seq: row.seq,
                    context,
                    present,
                    reports,
                    q,
                    known,
                });
            }
            let picks = rank(&cands, &labelled, l, limit);
            let name = |ks: &[usize]| ks.iter().map(|&k| ids[k].clone()).collect::<Vec<_>>();
            let queue = picks
                .into_iter()
                .map(|p| {
                    let mut reasons = vec![format!(
                        "the closest queued round to {} unlabelled round(s) of the window{}",
                        p.represents,
                        if p.novelty >= 0.5 {
                            " in a scene no labelled round is close to"
                        } else {
                            ""
                        }
                    )];
                    if !p.disputed.is_empty() {
                        reasons.push(format!(
                            "the reporters split on {}",
                            name(&p.disputed).join(", ")
                        ));
                    }
                    if p.unknown.len() < l {
                        reasons.push(format!(
                            "partly labelled: {} still unknown",
                            name(&p.unknown).join(", ")
                        ));
                    }
                    ReviewItem {
                        round_id: vlmfuse_store::round_id(p.seq),
                        seq: p.seq,
                        created_ms: created.get(&p.seq).copied().unwrap_or(0),
                        score: p.score,
                        represents: p.represents,
                        novelty: p.novelty,
                        disagreement: p.disagreement,
                        uncertainty: p.uncertainty,
                        unknown: name(&p.unknown),
                        disputed: name(&p.disputed),
                        reasons,
                    }
                })
                .collect();
            Ok(ReviewQueue {
                rounds: total,
                window,
                considered: rows.len(),
                labelled: labelled.len(),
                candidates: cands.len(),
                rule: RULE,
                queue,
            })
        })
        .await
    }
}

/// The context scaled to unit norm (all zeros stays all zeros).
fn unit(x: &[f64]) -> Vec<f64> {
    let n = x.iter().map(|v| v * v).sum::<f64>().sqrt();
    if n > 0.0 && n.is_finite() {
        x.iter().map(|v| v / n).collect()
    } else {
        vec![0.0; x.len()]
    }
}
