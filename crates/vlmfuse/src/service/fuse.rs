//! `/v1/fuse` and the one fuse-and-store path that `/v1/infer` shares, plus feedback.

use super::writer::{Cmd, FeedbackDone, Idem, Inserted};
use super::{Service, ServiceError};
use crate::wire::{feedback_out, fuse_out, FuseOut, Fused};
use serde_json::Value;
use sha2::{Digest, Sha256};
use std::time::Instant;
use tokio::sync::oneshot;
use vlmfuse_fusion::{FusionError, RoundRecord};
use vlmfuse_store::browse::Thumbnail;
use vlmfuse_store::{round_id, NewRound};

/// The answer of a storing route (`/v1/fuse`, `/v1/infer`): the JSON body, and whether it
/// repeats the stored answer of an earlier request with the same idempotency key.
pub struct Answer {
    pub body: Value,
    pub replayed: bool,
}

/// Turns a request's numbered rounds into its JSON answer. The same function writes the answer
/// a keyed request stores and the one it sends, so a retry gets exactly the first answer.
pub type Render = Box<dyn FnOnce(Vec<Fused>) -> Value + Send>;

/// A request's idempotency key and a hash of what it asked.
pub struct IdemRequest {
    pub key: String,
    pub fingerprint: String,
}

/// Longest idempotency key.
pub const MAX_KEY_LEN: usize = 255;

/// The request's idempotency key, from the `Idempotency-Key` header or the body's
/// `request_id` (the same key if both are given): 1 to 255 visible ASCII characters.
pub fn idempotency_key(
    header: Option<&str>,
    field: Option<&str>,
) -> Result<Option<String>, ServiceError> {
    let key = match (header, field) {
        (Some(h), Some(f)) if h != f => {
            return Err(ServiceError::Invalid(format!(
                "the Idempotency-Key header ({h:?}) and request_id ({f:?}) differ; send one, \
                 or the same key in both"
            )))
        }
        (Some(k), _) | (None, Some(k)) => k,
        (None, None) => return Ok(None),
    };
    if key.is_empty() || key.len() > MAX_KEY_LEN || !key.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(ServiceError::Invalid(format!(
            "idempotency key {key:?} must be 1 to {MAX_KEY_LEN} visible ASCII characters"
        )));
    }
    Ok(Some(key.to_string()))
}

/// Hex SHA-256 of the given parts, each length-prefixed (so that parts cannot run together).
pub fn fingerprint(parts: &[&[u8]]) -> String {
    let mut h = Sha256::new();
    for p in parts {
        h.update((p.len() as u64).to_le_bytes());
        h.update(p);
    }
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

/// Answers fused here, for a rendering.
fn local(outs: Vec<FuseOut>) -> Vec<Fused> {
    outs.into_iter()
        .map(|o| Fused::Local(Box::new(o)))
        .collect()
}

/// Sets each round's id from the first `seq`.
fn number(rounds: &mut [FuseOut], first: u64) {
    for (i, r) in rounds.iter_mut().enumerate() {
        r.round_id = round_id(first + i as u64);
    }
}

/// Removes and returns a top-level `request_id` string field.
fn take_request_id(body: &mut Value) -> Result<Option<String>, ServiceError> {
    let Some(obj) = body.as_object_mut() else {
        return Ok(None);
    };
    match obj.remove("request_id") {
        None | Some(Value::Null) => Ok(None),
        Some(Value::String(s)) => Ok(Some(s)),
        Some(_) => Err(ServiceError::Invalid(
            "\"request_id\" must be a string (an idempotency key)".into(),
        )),
    }
}

impl Service {
    /// `POST /v1/fuse`: one docs/PAPER-METHOD.md §8 round (without truth) or `{"rounds": [...]}`, with an
    /// optional idempotency key (`key` from the header, or the body's `request_id`).
    pub async fn fuse(&self, mut body: Value, key: Option<&str>) -> Result<Answer, ServiceError> {
        // A follower passes the request to the writer as it came (`replica`).
        if let Some(f) = self.following() {
            let fw = f.forward("/v1/fuse", &body, key).await?;
            return Ok(Answer {
                body: fw.body,
                replayed: fw.replayed,
            });
        }
        let delay = self.hooks.fuse_delay();
        if !delay.is_zero() {
            tokio::time::sleep(delay).await;
        }
        let field = take_request_id(&mut body)?;
        let idem = idempotency_key(key, field.as_deref())?.map(|key| IdemRequest {
            key,
            fingerprint: fingerprint(&[
                b"/v1/fuse",
                &serde_json::to_vec(&body).unwrap_or_default(),
            ]),
        });
        let (records, batch) = parse_fuse_body(body, &self.cfg.limits)?;
        let records = records
            .into_iter()
            .map(|rec| {
                let request = serde_json::json!({ "id": rec.id, "reports": rec.reports });
                (rec, request, Vec::new())
            })
            .collect();
        let render: Render = Box::new(move |mut rounds| {
            if batch {
                serde_json::to_value(crate::wire::FuseBatchOut { rounds })
            } else {
                serde_json::to_value(rounds.remove(0))
            }
            .unwrap_or_else(|e| serde_json::json!({"error": format!("serialising: {e}")}))
        });
        self.fuse_and_store(records, batch, "/v1/fuse", idem, render)
            .await
    }

    /// The one store/fuse path of /v1/fuse and /v1/infer: validates every record, infers each
    /// against the state as it stands (off the async threads, under the read lock), then hands
    /// the rounds to the writer and returns them numbered. `request` is what the database keeps
    /// with the round. All or nothing.
    pub(super) async fn fuse_and_store(
        &self,
        records: Vec<(RoundRecord, Value, Vec<Thumbnail>)>,
        batch: bool,
        route: &'static str,
        idem: Option<IdemRequest>,
        render: Render,
    ) -> Result<Answer, ServiceError> {
        if let Some(f) = self.following() {
            // A follower's fuse step is the writer's (`replica`): it infers against the one
            // engine every event goes through, stores, and numbers; its answer per round goes
            // into this request's own rendering. The key is the request's, under its route.
            let n = records.len();
            let rounds: Vec<Value> = records
                .iter()
                .map(|(rec, _, _)| {
                    let mut r = serde_json::json!({"context": rec.context, "reports": rec.reports});
                    if let Some(id) = &rec.id {
                        r["id"] = id.clone().into();
                    }
                    r
                })
                .collect();
            let key = idem.as_ref().map(|i| format!("{route}:{}", i.key));
            let fw = f
                .forward(
                    "/v1/fuse",
                    &serde_json::json!({ "rounds": rounds }),
                    key.as_deref(),
                )
                .await?;
            let outs = match fw.body.get("rounds").and_then(Value::as_array) {
                Some(a) if a.len() == n => a.clone(),
                _ => {
                    return Err(ServiceError::Internal(format!(
                        "the writer answered a fuse of {n} rounds with something else: {}",
                        fw.body
                    )))
                }
            };
            return Ok(Answer {
                body: render(outs.into_iter().map(Fused::Remote).collect()),
                replayed: fw.replayed,
            });
        }
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
                for (idx, (rec, request, thumbs)) in records.into_iter().enumerate() {
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
                    parsed.push((rec, request, thumbs, round));
                }
                let infer_start = Instant::now();
                let mut outs = Vec::with_capacity(parsed.len());
                let mut new_rounds = Vec::with_capacity(parsed.len());
                let created_ms = vlmfuse_store::timestamp_ms();
                for (rec, mut request, thumbnails, round) in parsed {
                    let inf = eng.infer(&round);
                    // The round id is set once the writer has numbered the round.
                    let out = fuse_out(&eng, 0, rec.id.clone(), &inf);
                    // Which predictor served it, for the operator page's history.
                    if let Some(obj) = request.as_object_mut() {
                        obj.insert("decision".into(), out.decision.into());
                    }
                    outs.push(out);
                    new_rounds.push(NewRound {
                        round,
                        inference: inf,
                        request,
                        created_ms,
                        thumbnails,
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
        let mut outs = Some(outs);
        let mut render = Some(render);
        let idem = idem.map(|i| {
            let (mut outs, render) = (outs.take().expect("once"), render.take().expect("once"));
            Idem {
                key: i.key,
                route,
                fingerprint: i.fingerprint,
                render: Box::new(move |first| {
                    number(&mut outs, first);
                    render(local(outs))
                }),
            }
        });
        self.send(Cmd::Insert {
            rounds: new_rounds,
            idem,
            reply: tx,
        })?;
        let delay = self.hooks.after_queue_delay();
        if !delay.is_zero() {
            tokio::time::sleep(delay).await;
        }
        match rx.await.map_err(|_| ServiceError::WriterStopped)?? {
            Inserted::Replay(body) => Ok(Answer {
                body,
                replayed: true,
            }),
            Inserted::Fresh {
                body: Some(body), ..
            } => Ok(Answer {
                body,
                replayed: false,
            }),
            Inserted::Fresh { first, body: None } => {
                let (mut outs, render) = (
                    outs.take().ok_or(ServiceError::WriterStopped)?,
                    render.take().ok_or(ServiceError::WriterStopped)?,
                );
                number(&mut outs, first);
                Ok(Answer {
                    body: render(local(outs)),
                    replayed: false,
                })
            }
        }
    }

    /// The stored answer of an idempotency key, if the key names this very request; an error
    /// if it names another; `None` if it is new (or expired). `/v1/infer` asks before it runs
    /// any model; the writer checks again when it stores.
    pub(super) async fn replay(
        &self,
        route: &'static str,
        idem: &IdemRequest,
    ) -> Result<Option<Answer>, ServiceError> {
        // A follower's keys are the writer's to check, when the fuse step arrives there.
        if self.following().is_some() {
            return Ok(None);
        }
        let (tx, rx) = oneshot::channel();
        self.send(Cmd::LookupKey {
            key: idem.key.clone(),
            reply: tx,
        })?;
        match rx.await.map_err(|_| ServiceError::WriterStopped)?? {
            Some(rec) if rec.route == route && rec.fingerprint == idem.fingerprint => {
                metrics::counter!("vlmfuse_idempotent_replays_total").increment(1);
                Ok(Some(Answer {
                    body: rec.response,
                    replayed: true,
                }))
            }
            Some(rec) => Err(super::writer::key_reused(&idem.key, route, &rec.route)),
            None => Ok(None),
        }
    }

    /// `POST /v1/feedback`: labels a fused round; idempotent per round. Returns the answer and
    /// whether it repeats an earlier feedback.
    pub async fn feedback(
        &self,
        round_id: String,
        given: FeedbackGiven,
    ) -> Result<(Value, bool), ServiceError> {
        if let Some(f) = self.following() {
            let mut body = serde_json::json!({ "round_id": round_id });
            for (k, v) in [("labels", &given.labels), ("known", &given.known)] {
                if let Some(v) = v {
                    body[k] = serde_json::json!(v);
                }
            }
            for (k, v) in [("source", &given.source), ("signals", &given.signals)] {
                if let Some(v) = v {
                    body[k] = v.clone().into();
                }
            }
            let fw = f.forward("/v1/feedback", &body, None).await?;
            return Ok((fw.body, fw.repeated));
        }
        let (truth, source) = {
            let eng = self.shared.engine.read().await;
            given.encode(&eng)?
        };
        self.feedback_with(round_id, truth, source, given.signals.as_deref())
            .await
    }

    /// A feedback whose truth is already encoded (the derived labels of a clip's track).
    pub(crate) async fn feedback_truth(
        &self,
        round_id: String,
        truth: Vec<u8>,
        source: String,
    ) -> Result<(Value, bool), ServiceError> {
        if let Some(f) = self.following() {
            let (labels, known) = {
                let eng = self.shared.engine.read().await;
                let ont = eng.ontology();
                let ids = |keep: &dyn Fn(u8) -> bool| -> Vec<String> {
                    (0..truth.len())
                        .filter(|&k| keep(truth[k]))
                        .map(|k| ont.id(k).to_string())
                        .collect()
                };
                (ids(&|t| t == 1), ids(&|t| t != vlmfuse_fusion::UNKNOWN))
            };
            let body = serde_json::json!({
                "round_id": round_id, "labels": labels, "known": known, "source": source,
            });
            let fw = f.forward("/v1/feedback", &body, None).await?;
            return Ok((fw.body, fw.repeated));
        }
        self.feedback_with(round_id, truth, source, None).await
    }

    async fn feedback_with(
        &self,
        round_id: String,
        truth: Vec<u8>,
        source: String,
        signals: Option<&str>,
    ) -> Result<(Value, bool), ServiceError> {
        let derive = match signals {
            Some(text) => Some(Box::new((
                super::annotate::parse_track(&self.cfg.annotate, text.as_bytes())?,
                self.cfg.annotate.clone(),
            ))),
            None => None,
        };
        let (tx, rx) = oneshot::channel();
        // Once sent, the writer finishes the feedback even if this request is dropped (timeout,
        // client gone); a repeat then answers with the committed result.
        self.send(Cmd::Feedback {
            round_id,
            truth,
            source,
            derive,
            reply: tx,
        })?;
        let done: FeedbackDone = rx.await.map_err(|_| ServiceError::WriterStopped)??;
        let eng = self.shared.engine.read().await;
        let out = serde_json::to_value(feedback_out(&eng, &done))
            .map_err(|e| ServiceError::Internal(format!("serialising a feedback answer: {e}")))?;
        Ok((out, done.repeated))
    }
}

/// A feedback as a caller gives it: the labels present, the labels whose truth it gives
/// (`None`: all) and who gives it (`None`: a person).
#[derive(Debug, Clone, Default)]
pub struct FeedbackGiven {
    /// `None` only with `signals`.
    pub labels: Option<Vec<String>>,
    pub known: Option<Vec<String>>,
    pub source: Option<String>,
    /// A vehicle-signal track the labels are derived from instead.
    pub signals: Option<String>,
}

/// Longest `source` name accepted.
const MAX_SOURCE: usize = 64;

impl FeedbackGiven {
    /// The truth vector (0/1 for the labels it gives, `UNKNOWN` for the rest) and the checked
    /// source. Refuses a label outside the ontology, a present label it does not call known,
    /// an empty `known`, and a source that is empty, long or not `[A-Za-z0-9_.:-]`.
    pub fn encode(&self, eng: &vlmfuse_fusion::Engine) -> Result<(Vec<u8>, String), ServiceError> {
        let bad = |m: String| ServiceError::Invalid(m);
        let default = if self.signals.is_some() {
            super::annotate::KINEMATICS
        } else {
            "human"
        };
        let source = self.source.clone().unwrap_or_else(|| default.into());
        if source.is_empty()
            || source.len() > MAX_SOURCE
            || !source
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"_.:-".contains(&b))
        {
            return Err(bad(format!(
                "\"source\" must be 1 to {MAX_SOURCE} characters of A-Z a-z 0-9 _ . : - \
                 (e.g. \"human\", \"kinematics\", \"detector\"), not {source:?}"
            )));
        }
        if self.signals.is_some() {
            if self.labels.is_some() || self.known.is_some() {
                return Err(bad(
                    "give either \"signals\" (the labels are derived from them) or \"labels\" \
                     (and \"known\"), not both"
                        .into(),
                ));
            }
            // Derived by the writer, which knows the round's clip.
            return Ok((Vec::new(), source));
        }
        let Some(labels) = &self.labels else {
            return Err(bad(
                "missing field \"labels\" (the labels that are present; or \"signals\", a \
                 vehicle-signal track to derive them from)"
                    .into(),
            ));
        };
        let present = eng.encode_truth(labels)?;
        let truth = match &self.known {
            None => present,
            Some(known) => {
                if known.is_empty() {
                    return Err(bad(
                        "\"known\" is empty: a feedback must give the truth of at least one \
                         label (leave \"known\" out to give all of them)"
                            .into(),
                    ));
                }
                let k = eng.encode_truth(known)?;
                if let Some(i) = (0..k.len()).find(|&i| present[i] == 1 && k[i] == 0) {
                    return Err(bad(format!(
                        "label {:?} is in \"labels\" but not in \"known\"",
                        eng.ontology().labels()[i].id
                    )));
                }
                k.iter()
                    .zip(&present)
                    .map(|(&kn, &p)| if kn == 1 { p } else { vlmfuse_fusion::UNKNOWN })
                    .collect()
            }
        };
        Ok((truth, source))
    }
}

/// The keys of a round on `/v1/fuse` (`truth` is known, to be refused with its own reason).
const ROUND_FIELDS: [&str; 4] = ["id", "context", "reports", "truth"];

/// Splits the body into records, refusing truth (feedback has its own route, so a round cannot
/// be labelled twice by two paths) and batches over the limit.
fn parse_fuse_body(
    body: Value,
    limits: &crate::config::Limits,
) -> Result<(Vec<RoundRecord>, bool), ServiceError> {
    let max_batch = limits.max_batch_rounds;
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
        // A misspelled key (`requestId`, `truths`) would otherwise be dropped by serde and the
        // round stored as if it were fine: a retry with the misspelled key would store another.
        if let Some(k) = v
            .as_object()
            .and_then(|o| o.keys().find(|k| !ROUND_FIELDS.contains(&k.as_str())))
        {
            let hint = if batch {
                "a round has id, context, reports (request_id goes at the top level)"
            } else {
                "a round has id, context, reports and an optional top-level request_id"
            };
            return Err(ServiceError::Invalid(at(format!(
                "unknown field {k:?}; {hint}"
            ))));
        }
        if v.get("truth").is_some_and(|t| !t.is_null()) {
            return Err(ServiceError::TruthNotAccepted(at(
                "/v1/fuse does not take \"truth\": fuse the round, then send its labels to \
                 POST /v1/feedback with the returned round_id"
                    .into(),
            )));
        }
        // Before serde builds the vector: a 4-million-entry context is refused unread.
        let dim = v
            .get("context")
            .and_then(Value::as_array)
            .map_or(0, Vec::len);
        if dim > limits.max_context_dim {
            return Err(ServiceError::Invalid(at(format!(
                "the context has {dim} dimensions; at most {} (limits.max_context_dim)",
                limits.max_context_dim
            ))));
        }
        let rec: RoundRecord =
            serde_json::from_value(v).map_err(|e| ServiceError::Invalid(at(e.to_string())))?;
        out.push(rec);
    }
    Ok((out, batch))
}
