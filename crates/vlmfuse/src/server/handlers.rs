//! Route handlers. Names (reporters, labels) live only here at the edge; the engine and store
//! speak indices.

use super::error::ApiError;
use super::writer::{Cmd, FeedbackDone};
use super::AppState;
use axum::extract::{FromRequest, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize, Serializer};
use serde_json::Value;
use std::sync::atomic::Ordering;
use std::time::Instant;
use tokio::sync::oneshot;
use vlmfuse_fusion::{
    Engine, Inference, Label, ReporterStats, RoundRecord, ShapleyMethod, ThresholdMode,
};
use vlmfuse_store::{round_id, NewRound};

/// `axum::Json`, but a body it cannot read becomes an [`ApiError`] (JSON, counted), never axum's
/// plain-text rejection.
pub struct ApiJson<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned> FromRequest<S> for ApiJson<T> {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        match axum::Json::<T>::from_request(req, state).await {
            Ok(axum::Json(v)) => Ok(ApiJson(v)),
            Err(rej) => Err(rej.into()),
        }
    }
}

/// A JSON object whose keys keep the order given (ontology or reporter order), which
/// `BTreeMap` would sort away.
pub struct Ordered<T>(pub Vec<(String, T)>);

impl<T: Serialize> Serialize for Ordered<T> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_map(self.0.iter().map(|(k, v)| (k, v)))
    }
}

#[derive(Serialize)]
pub struct LabelExplanationOut {
    /// Contextual prior `pi_k`.
    prior: f64,
    /// Each present reporter's weighted, guardrailed LLR `w_i * lambda~_ik`.
    contributions: Ordered<f64>,
    /// `logit(pi_k) + sum of contributions`: the posterior before the sigmoid.
    logit: f64,
}

#[derive(Serialize)]
pub struct FuseOut {
    round_id: String,
    /// The client's `id`, echoed when given.
    #[serde(skip_serializing_if = "Option::is_none")]
    id: Option<String>,
    labels: Vec<String>,
    posteriors: Ordered<f64>,
    threshold: f64,
    /// Per-label thresholds, only in the per-label threshold mode.
    #[serde(skip_serializing_if = "Option::is_none")]
    thresholds: Option<Ordered<f64>>,
    coalition: Vec<String>,
    missing: Vec<String>,
    /// The reputations used for this round (all configured reporters).
    reputations: Ordered<f64>,
    explanation: Ordered<LabelExplanationOut>,
}

#[derive(Serialize)]
struct FuseBatchOut {
    rounds: Vec<FuseOut>,
}

fn fuse_out(engine: &Engine, seq: u64, id: Option<String>, inf: &Inference) -> FuseOut {
    let reporters = engine.reporters();
    let ontology = engine.ontology();
    let label = |k: usize| ontology.id(k).to_string();
    let l = ontology.len();
    let present = &inf.signals.coalition;
    let explanation = engine
        .explain(inf)
        .into_iter()
        .enumerate()
        .map(|(k, e)| {
            (
                label(k),
                LabelExplanationOut {
                    prior: e.prior,
                    contributions: Ordered(
                        e.contributions
                            .iter()
                            .map(|&(i, v)| (reporters[i].clone(), v))
                            .collect(),
                    ),
                    logit: e.logit,
                },
            )
        })
        .collect();
    FuseOut {
        round_id: round_id(seq),
        id,
        labels: ontology.decode(&inf.pred),
        posteriors: Ordered((0..l).map(|k| (label(k), inf.q[k])).collect()),
        threshold: inf.thresholds.first().copied().unwrap_or(0.5),
        thresholds: (engine.threshold().mode() == ThresholdMode::PerLabel)
            .then(|| Ordered((0..l).map(|k| (label(k), inf.thresholds[k])).collect())),
        coalition: present.iter().map(|&i| reporters[i].clone()).collect(),
        missing: (0..reporters.len())
            .filter(|i| !present.contains(i))
            .map(|i| reporters[i].clone())
            .collect(),
        reputations: Ordered(
            reporters
                .iter()
                .cloned()
                .zip(inf.w_used.iter().copied())
                .collect(),
        ),
        explanation: Ordered(explanation),
    }
}

/// `POST /v1/fuse`: one SPEC §8 round (without truth) or `{"rounds": [...]}`.
pub async fn fuse(
    State(st): State<AppState>,
    ApiJson(body): ApiJson<Value>,
) -> Result<Response, ApiError> {
    if st.cfg.limits.debug_fuse_delay_ms > 0 {
        tokio::time::sleep(std::time::Duration::from_millis(
            st.cfg.limits.debug_fuse_delay_ms,
        ))
        .await;
    }
    let (records, batch) = parse_fuse_body(body, st.cfg.limits.max_batch_rounds)?;
    let records = records
        .into_iter()
        .map(|rec| {
            let request = serde_json::json!({ "id": rec.id, "reports": rec.reports });
            (rec, request)
        })
        .collect();
    let rounds = fuse_and_store(&st, records, batch).await?;
    Ok(if batch {
        axum::Json(FuseBatchOut { rounds }).into_response()
    } else {
        axum::Json(rounds.into_iter().next().expect("one round")).into_response()
    })
}

/// The one store/fuse path of /v1/fuse and /v1/infer: validates every record, infers each
/// against the state as it stands (off the async threads, under the read lock), then hands the
/// rounds to the writer and returns them numbered. `request` is what the database keeps with the
/// round. All or nothing.
pub(super) async fn fuse_and_store(
    st: &AppState,
    records: Vec<(RoundRecord, Value)>,
    batch: bool,
) -> Result<Vec<FuseOut>, ApiError> {
    let shared = st.shared.clone();
    // Inference is CPU work (about a millisecond at a 10k bank): off the async threads, under a
    // read lock only, so concurrent fuse requests run in parallel and feedback waits for none.
    let (outs, new_rounds) = tokio::task::spawn_blocking(move || {
        let eng = shared.engine.read().unwrap_or_else(|e| e.into_inner());
        let mut dim = eng.dim();
        let mut parsed = Vec::with_capacity(records.len());
        for (idx, (rec, request)) in records.into_iter().enumerate() {
            let at = |e: ApiError| -> ApiError {
                if batch {
                    match e {
                        ApiError::Fusion(f) => ApiError::Body {
                            status: StatusCode::UNPROCESSABLE_ENTITY,
                            kind: f.kind(),
                            message: format!("rounds[{idx}]: {f}"),
                        },
                        other => other,
                    }
                } else {
                    e
                }
            };
            if let (Some(e), d) = (dim, rec.context.len()) {
                if e != d && d > 0 {
                    return Err(at(vlmfuse_fusion::FusionError::Dimension {
                        expected: e,
                        got: d,
                    }
                    .into()));
                }
            }
            let (round, _) = eng.parse(&rec).map_err(|e| at(e.into()))?;
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
        Ok::<_, ApiError>((outs, new_rounds))
    })
    .await
    .map_err(|e| ApiError::Internal(format!("inference task failed: {e}")))??;

    let (tx, rx) = oneshot::channel();
    st.send(Cmd::Insert {
        rounds: new_rounds,
        reply: tx,
    })?;
    let first = rx
        .await
        .map_err(|_| ApiError::Internal("the writer stopped".into()))??;

    let mut rounds = outs;
    for (i, r) in rounds.iter_mut().enumerate() {
        r.round_id = round_id(first + i as u64);
    }
    Ok(rounds)
}

/// Splits the body into records, refusing truth (feedback has its own route, so a round cannot
/// be labelled twice by two paths) and batches over the limit.
fn parse_fuse_body(body: Value, max_batch: usize) -> Result<(Vec<RoundRecord>, bool), ApiError> {
    let Value::Object(obj) = body else {
        return Err(ApiError::Invalid(
            "the body must be a JSON object: one round, or {\"rounds\": [...]}".into(),
        ));
    };
    let (values, batch) = if obj.contains_key("rounds") && !obj.contains_key("context") {
        if obj.len() != 1 {
            return Err(ApiError::Invalid(
                "a batch is {\"rounds\": [...]} with no other field".into(),
            ));
        }
        match obj.into_iter().next().map(|(_, v)| v) {
            Some(Value::Array(a)) => (a, true),
            _ => return Err(ApiError::Invalid("\"rounds\" must be an array".into())),
        }
    } else {
        (vec![Value::Object(obj)], false)
    };
    if values.is_empty() {
        return Err(ApiError::Invalid("\"rounds\" is empty".into()));
    }
    if values.len() > max_batch {
        return Err(ApiError::Invalid(format!(
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
            return Err(ApiError::Invalid(
                at("a round must be a JSON object".into()),
            ));
        }
        if v.get("truth").is_some_and(|t| !t.is_null()) {
            return Err(ApiError::Body {
                status: StatusCode::UNPROCESSABLE_ENTITY,
                kind: "truth_not_accepted",
                message: at(
                    "/v1/fuse does not take \"truth\": fuse the round, then send its labels to \
                     POST /v1/feedback with the returned round_id"
                        .into(),
                ),
            });
        }
        let rec: RoundRecord =
            serde_json::from_value(v).map_err(|e| ApiError::Invalid(at(e.to_string())))?;
        out.push(rec);
    }
    Ok((out, batch))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FeedbackIn {
    round_id: String,
    labels: Vec<String>,
}

#[derive(Serialize)]
pub struct FeedbackOut {
    round_id: String,
    labels: Vec<String>,
    /// Shapley value of each reporter present in the round.
    shapley: Ordered<f64>,
    shapley_method: &'static str,
    /// Standard error of each sampled Shapley value (sampled method only).
    #[serde(skip_serializing_if = "Option::is_none")]
    shapley_std_error: Option<Ordered<f64>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    shapley_samples: Option<usize>,
    /// `v(N)`: the coalition's log-score gain over the prior (the sum of the Shapley values).
    value: f64,
    reputations_before: Ordered<f64>,
    reputations: Ordered<f64>,
    labelled_rounds: u64,
}

fn feedback_out(engine: &Engine, done: &FeedbackDone) -> FeedbackOut {
    let names = engine.reporters();
    let o = &done.feedback.outcome;
    let members = |v: &[f64]| {
        Ordered(
            done.coalition
                .iter()
                .zip(v)
                .map(|(&i, &x)| (names[i].clone(), x))
                .collect(),
        )
    };
    let all = |v: &[f64]| Ordered(names.iter().cloned().zip(v.iter().copied()).collect());
    let (se, samples) = match &o.credit.method {
        ShapleyMethod::Sampled { samples, std_error } => (Some(members(std_error)), Some(*samples)),
        _ => (None, None),
    };
    FeedbackOut {
        round_id: done.round_id.clone(),
        labels: engine.ontology().decode(&done.feedback.truth),
        shapley: members(&o.credit.phi),
        shapley_method: o.credit.method.name(),
        shapley_std_error: se,
        shapley_samples: samples,
        value: o.credit.v_full,
        reputations_before: all(&o.w_before),
        reputations: all(&o.w_after),
        labelled_rounds: done.feedback.labelled_order + 1,
    }
}

/// `POST /v1/feedback`: labels a fused round; idempotent per round.
pub async fn feedback(
    State(st): State<AppState>,
    ApiJson(body): ApiJson<FeedbackIn>,
) -> Result<Response, ApiError> {
    let truth = {
        let eng = st.shared.engine.read().unwrap_or_else(|e| e.into_inner());
        eng.encode_truth(&body.labels)?
    };
    let (tx, rx) = oneshot::channel();
    // Once sent, the writer finishes the feedback even if this request is dropped (timeout,
    // client gone); a repeat then answers with the committed result.
    st.send(Cmd::Feedback {
        round_id: body.round_id,
        truth,
        reply: tx,
    })?;
    let done = rx
        .await
        .map_err(|_| ApiError::Internal("the writer stopped".into()))??;
    let out = {
        let eng = st.shared.engine.read().unwrap_or_else(|e| e.into_inner());
        feedback_out(&eng, &done)
    };
    let mut resp = axum::Json(out).into_response();
    if done.repeated {
        resp.headers_mut()
            .insert("x-vlmfuse-repeated", HeaderValue::from_static("true"));
    }
    Ok(resp)
}

#[derive(Serialize)]
struct StateOut {
    reputations: Ordered<f64>,
    labelled_rounds: u64,
    threshold: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    thresholds: Option<Ordered<f64>>,
    reporters: Ordered<ReporterStats>,
    /// Rounds fused and stored (labelled or not).
    rounds: u64,
    /// Context dimension in force; null until the first round.
    dim: Option<usize>,
}

/// `GET /v1/state`.
pub async fn state(State(st): State<AppState>) -> Response {
    let eng = st.shared.engine.read().unwrap_or_else(|e| e.into_inner());
    let names = eng.reporters();
    let l = eng.ontology().len();
    let out = StateOut {
        reputations: Ordered(
            names
                .iter()
                .cloned()
                .zip(eng.reputations().iter().copied())
                .collect(),
        ),
        labelled_rounds: eng.labelled(),
        threshold: eng.threshold().scalar(),
        thresholds: (eng.threshold().mode() == ThresholdMode::PerLabel).then(|| {
            Ordered(
                (0..l)
                    .map(|k| {
                        (
                            eng.ontology().id(k).to_string(),
                            eng.threshold().thresholds()[k],
                        )
                    })
                    .collect(),
            )
        }),
        reporters: Ordered(
            names
                .iter()
                .cloned()
                .zip(eng.stats().iter().cloned())
                .collect(),
        ),
        rounds: st.shared.rounds.load(Ordering::SeqCst),
        dim: eng.dim(),
    };
    drop(eng);
    axum::Json(out).into_response()
}

#[derive(Serialize)]
struct OntologyOut<'a> {
    labels: &'a [Label],
}

/// `GET /v1/ontology`.
pub async fn ontology(State(st): State<AppState>) -> Response {
    let eng = st.shared.engine.read().unwrap_or_else(|e| e.into_inner());
    axum::Json(OntologyOut {
        labels: eng.ontology().labels(),
    })
    .into_response()
}

/// `GET /healthz`: the process answers.
pub async fn healthz() -> Response {
    axum::Json(serde_json::json!({"status": "ok"})).into_response()
}

/// `GET /readyz`: every configured component is loaded, or a 503 that lists what is not.
pub async fn readyz(State(st): State<AppState>) -> Result<Response, ApiError> {
    let not_ready = st.not_ready();
    if not_ready.is_empty() {
        let p = &st.pipeline;
        let mut components = vec!["store".to_string(), "engine".to_string()];
        if p.embedder.is_some() {
            components.push("embedder".into());
        }
        for r in &p.reporters {
            components.push(format!("reporter {}", r.reporter.name()));
        }
        if p.labeler.is_some() {
            components.push(format!("labeler {}", p.labeler_name));
        }
        let blockers = p.infer_blockers();
        Ok(axum::Json(serde_json::json!({
            "status": "ready",
            "components": components,
            // /v1/infer needs an embedder, reporters and a labeler; what the config leaves out.
            "infer": {"ready": blockers.is_empty(), "not_ready": blockers},
        }))
        .into_response())
    } else {
        Err(ApiError::NotReady {
            message: format!("not ready: {}", not_ready.join("; ")),
            not_ready,
        })
    }
}

/// `GET /metrics`: Prometheus text.
pub async fn metrics(State(st): State<AppState>) -> Response {
    let mut h = HeaderMap::new();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
    );
    (h, st.metrics.render()).into_response()
}

pub const OPENAPI: &str = include_str!("../../../../openapi.yaml");

/// `GET /openapi.yaml`: the contract at the repository root, compiled in.
pub async fn openapi() -> Response {
    (
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/yaml"),
        )],
        OPENAPI,
    )
        .into_response()
}

pub async fn not_found(req: Request) -> ApiError {
    ApiError::NotFound(format!("{} {}", req.method(), req.uri().path()))
}

pub async fn method_not_allowed() -> ApiError {
    ApiError::MethodNotAllowed
}
