//! The operator page's reads (`/ui/api/*`, docs/UI.md): the aggregates the writer keeps
//! ([`super::dashboard`]) and bounded reads of the store through a read-only connection of its
//! own, beside the writer's (SQLite's WAL lets readers run while it commits). Nothing here
//! changes state.

use super::{Service, ServiceError};
use crate::wire::Ordered;
use serde::Serialize;
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::sync::atomic::Ordering;
use vlmfuse_store::browse::RoundRow;
use vlmfuse_store::{parse_round_id, Store};

/// Most rounds one page of `/ui/api/rounds` lists.
pub const MAX_PAGE: usize = 100;

/// What the HTTP layer knows that the service does not: requests in flight and the responses
/// it gave, for the health panel.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct EdgeCounts {
    pub in_flight: usize,
    pub limit: usize,
    pub client: u64,
    pub server: u64,
    pub overload: u64,
}

#[derive(Serialize)]
pub struct RoundListItem {
    round_id: String,
    seq: u64,
    created_ms: i64,
    clip: Option<String>,
    labels: Vec<String>,
    reporters: Ordered<Vec<String>>,
    failed: Value,
    decision: Option<String>,
    labelled: bool,
}

#[derive(Serialize)]
pub struct RoundList {
    total: u64,
    rounds: Vec<RoundListItem>,
    next_before: Option<u64>,
}

fn clip_name(request: &Value) -> Option<String> {
    request
        .get("clip")
        .and_then(|c| c.get("file_name"))
        .or_else(|| request.get("id"))
        .and_then(|v| v.as_str())
        .map(str::to_string)
}

/// Each present reporter's labels in a round, in configured order.
fn reporter_labels<'a>(
    names: &'a [String],
    ont: &'a vlmfuse_fusion::Ontology,
    round: &'a vlmfuse_fusion::Round,
) -> impl Iterator<Item = (&'a String, Vec<String>)> + 'a {
    let l = ont.labels().len();
    names
        .iter()
        .enumerate()
        .filter(|(i, _)| round.present.get(*i).copied().unwrap_or(false))
        .map(move |(i, n)| {
            let rep = round.reports.get(i * l..(i + 1) * l).unwrap_or(&[]);
            (n, ont.decode(rep))
        })
}

impl Service {
    /// Runs `f` on the page's read-only connection, opened on first use, off the async threads.
    pub(super) async fn with_reader<T: Send + 'static>(
        &self,
        f: impl FnOnce(&Store) -> Result<T, ServiceError> + Send + 'static,
    ) -> Result<T, ServiceError> {
        let reader = self.reader.clone();
        let at = self.cfg.store.location(&self.cfg.server.data_dir);
        tokio::task::spawn_blocking(move || {
            let mut guard = reader
                .lock()
                .map_err(|_| ServiceError::Internal("the page's reader panicked".into()))?;
            if guard.is_none() {
                *guard = Some(Store::open_read_only_at(&at)?);
            }
            let res = f(guard.as_ref().expect("opened"));
            // A PostgreSQL session that broke (a restarted server, a cut network) is opened
            // anew by the next read instead of failing every read after it.
            if res.is_err() && guard.as_ref().is_some_and(|s| !s.alive()) {
                *guard = None;
            }
            res
        })
        .await
        .map_err(|e| ServiceError::Internal(format!("reader task failed: {e}")))?
    }

    /// `GET /ui/api/summary`.
    pub async fn ui_summary(&self, edge: EdgeCounts) -> Value {
        let state = self.state().await;
        let (reporters, labels, serving_now) = {
            let eng = self.shared.engine.read().await;
            (
                eng.reporters().to_vec(),
                eng.ontology()
                    .labels()
                    .iter()
                    .map(|l| json!({"id": l.id, "name": l.name}))
                    .collect::<Vec<_>>(),
                crate::wire::serving_predictor(&eng),
            )
        };
        let panels = self
            .shared
            .dashboard
            .lock()
            .map(|d| d.panels(&reporters))
            .ok();
        let ready = self.readiness();
        let comps = &ready.body["components"];
        let health_reporters: Vec<Value> = reporters
            .iter()
            .enumerate()
            .map(|(i, name)| {
                let c = &comps["reporters"][name];
                let h = panels.as_ref().and_then(|p| p.reporters_health.get(i));
                json!({
                    "name": name,
                    "configured": !c.is_null(),
                    "ready": c.get("ready").and_then(Value::as_bool),
                    "detail": c.get("error").cloned().unwrap_or(Value::Null),
                    "kind": c.get("kind").cloned().unwrap_or(Value::Null),
                    "latency_ms": h.map(|h| serde_json::to_value(&h.latency_ms).unwrap_or_default()),
                    "failures": h.map_or(0, |h| h.failures),
                })
            })
            .collect();
        let labeler = &comps["labeler"];
        let embedder = &comps["embedder"];
        let mut out = json!({
            "generated_ms": vlmfuse_store::timestamp_ms(),
            "state": state,
            "reporters": reporters,
            "labels": labels,
            "poll_ms": self.cfg.ui.poll_ms,
            "health": {
                "ready": ready.ready,
                "not_ready": ready.body["not_ready"],
                "queue_depth": edge.in_flight,
                "concurrency_limit": edge.limit,
                "errors": {"client": edge.client, "server": edge.server, "overload": edge.overload},
                "labeler": labeler.get("name").or_else(|| labeler.get("kind")).cloned().unwrap_or(Value::Null),
                "embedder": if embedder["configured"] == Value::Bool(false) {
                    Value::Null
                } else {
                    embedder.get("engine").cloned().unwrap_or(Value::Null)
                },
                "reporters": health_reporters,
            },
        });
        if let Some(p) = panels {
            let label_ids: Vec<String> = labels
                .iter()
                .filter_map(|l| l["id"].as_str().map(str::to_string))
                .collect();
            out["reputation_history"] = json!(p.reputation_history);
            out["drift"] = json!(p.drift);
            out["reliability"] = json!(p.reliability);
            out["calibration"] = json!(p.calibration);
            out["serving"] = json!({
                "method": out["state"]["method"].clone(),
                "window": p.serving.window,
                "decisions": p.serving.decisions,
                "agreement": reporters.iter().cloned().zip(p.serving.agreement.iter().copied())
                    .collect::<BTreeMap<_, _>>(),
                // Both predictors decide every label at once: the one serving now serves all.
                "labels": label_ids.iter().map(|k| (k.clone(), serving_now)).collect::<BTreeMap<_, _>>(),
            });
        }
        out
    }

    /// `GET /ui/api/rounds`: a page of rounds, newest first, before `before`.
    pub async fn ui_rounds(
        &self,
        before: Option<u64>,
        limit: usize,
    ) -> Result<RoundList, ServiceError> {
        let limit = limit.clamp(1, MAX_PAGE);
        let total = self.shared.rounds.load(Ordering::SeqCst);
        // Rounds the writer has not yet made visible are not listed.
        let before = Some(before.map_or(total, |b| b.min(total)));
        let rows = self
            .with_reader(move |s| Ok(s.recent_rounds(before, limit)?))
            .await?;
        let (names, ont) = {
            let eng = self.shared.engine.read().await;
            (eng.reporters().to_vec(), eng.ontology().clone())
        };
        let next_before = if rows.len() == limit {
            rows.last().map(|r| r.seq).filter(|&s| s > 0)
        } else {
            None
        };
        let rounds = rows
            .into_iter()
            .map(|r| RoundListItem {
                reporters: Ordered(
                    reporter_labels(&names, &ont, &r.round)
                        .map(|(n, labels)| (n.clone(), labels))
                        .collect(),
                ),
                labels: ont.decode(&r.inference.pred),
                clip: clip_name(&r.request),
                failed: r.request.get("failed").cloned().unwrap_or(json!({})),
                decision: r
                    .request
                    .get("decision")
                    .and_then(Value::as_str)
                    .map(str::to_string),
                round_id: r.round_id,
                seq: r.seq,
                created_ms: r.created_ms,
                labelled: r.labelled,
            })
            .collect();
        Ok(RoundList {
            total,
            rounds,
            next_before,
        })
    }

    /// `GET /ui/api/rounds/{id}`.
    pub async fn ui_round(&self, id: &str) -> Result<Value, ServiceError> {
        let unknown = || ServiceError::UnknownRound(id.to_string());
        let seq = parse_round_id(id).ok_or_else(unknown)?;
        if seq >= self.shared.rounds.load(Ordering::SeqCst) {
            return Err(unknown());
        }
        let (row, events, thumbs) = self
            .with_reader(move |s| {
                let row: Option<RoundRow> = s.round_row(seq)?;
                Ok((row, s.feedback(seq)?, s.thumbnail_index(seq)?))
            })
            .await?;
        let row = row.ok_or_else(unknown)?;
        let eng = self.shared.engine.read().await;
        let ont = eng.ontology();
        let names = eng.reporters();
        let l = ont.labels().len();
        let label = |k: usize| ont.labels()[k].id.clone();
        let inf = &row.inference;
        let explain = eng.explain(inf);
        let explanation: Vec<(String, Value)> = explain
            .iter()
            .enumerate()
            .map(|(k, e)| {
                let contributions: BTreeMap<String, f64> = e
                    .contributions
                    .iter()
                    .map(|&(i, c)| (names[i].clone(), c))
                    .collect();
                (
                    label(k),
                    json!({"prior": e.prior, "contributions": contributions, "logit": e.logit}),
                )
            })
            .collect();
        let (merged, sources) = super::writer::merged_truth(l, &events);
        let raw = row.request.get("raw");
        let reporters: Vec<(String, Value)> = reporter_labels(names, ont, &row.round)
            .map(|(n, labels)| {
                let text = raw
                    .and_then(|r| r.get(n))
                    .and_then(|r| r.get("text"))
                    .cloned()
                    .unwrap_or(Value::Null);
                (n.clone(), json!({"labels": labels, "text": text}))
            })
            .collect();
        let present: Vec<usize> = inf.signals.coalition.clone();
        let per_label = eng.threshold().mode() == vlmfuse_fusion::ThresholdMode::PerLabel;
        Ok(json!({
            "round_id": row.round_id,
            "seq": row.seq,
            "created_ms": row.created_ms,
            "clip": clip_name(&row.request),
            "method": eng.method().name(),
            "decision": row.request.get("decision"),
            "threshold": inf.thresholds.first().copied().unwrap_or(0.5),
            "thresholds": per_label.then(|| (0..l).map(|k| (label(k), inf.thresholds[k])).collect::<BTreeMap<_, _>>()),
            "labels": ont.decode(&inf.pred),
            "posteriors": Ordered((0..l).map(|k| (label(k), inf.q[k])).collect()),
            "coalition": present.iter().map(|&i| names[i].clone()).collect::<Vec<_>>(),
            "missing": (0..names.len()).filter(|i| !present.contains(i)).map(|i| names[i].clone()).collect::<Vec<_>>(),
            "reporters": Ordered(reporters),
            "failed": row.request.get("failed").cloned().unwrap_or(json!({})),
            "explanation": Ordered(explanation),
            "truth": Ordered((0..l).map(|k| (label(k), match merged[k] { 0 => json!(false), 1 => json!(true), _ => Value::Null })).collect()),
            "truth_source": (0..l).filter_map(|k| sources[k].clone().map(|s| (label(k), s))).collect::<BTreeMap<_, _>>(),
            "feedback": events.iter().map(|f| json!({
                "source": f.source,
                "labels": ont.decode(&f.truth),
                "known": (0..l).filter(|&k| f.truth[k] <= 1).map(label).collect::<Vec<_>>(),
                "labelled": f.labelled_order + 1,
            })).collect::<Vec<_>>(),
            "frames": thumbs.iter().map(|(i, t)| json!({
                "index": i, "t_s": t, "url": format!("/ui/api/rounds/{}/frames/{i}", row.round_id),
            })).collect::<Vec<_>>(),
        }))
    }

    /// `GET /ui/api/rounds/{id}/frames/{index}`: the thumbnail's JPEG.
    pub async fn ui_frame(&self, id: &str, index: u32) -> Result<Vec<u8>, ServiceError> {
        let seq = parse_round_id(id).ok_or_else(|| ServiceError::UnknownRound(id.to_string()))?;
        let what = format!("frame {index} of {id}");
        self.with_reader(move |s| s.thumbnail(seq, index)?.ok_or(ServiceError::NotFound(what)))
            .await
    }
}
