//! Route handlers: read the request, call the service, write the answer. No logic of their own.

use super::error::ApiError;
use super::AppState;
use crate::service::ServiceError;
use axum::extract::{FromRequest, Request, State};
use axum::http::{header, HeaderMap, HeaderValue};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::Value;

/// `axum::Json`, but a body it cannot read becomes an [`ApiError`] (JSON, counted), never axum's
/// plain-text rejection.
#[derive(FromRequest)]
#[from_request(via(axum::Json), rejection(ApiError))]
pub struct ApiJson<T>(pub T);

/// The `Idempotency-Key` header, if any (its value is checked by the service).
pub fn idempotency_header(h: &HeaderMap) -> Result<Option<String>, ApiError> {
    match h.get("idempotency-key") {
        None => Ok(None),
        Some(v) => v.to_str().map(|s| Some(s.to_string())).map_err(|_| {
            ServiceError::Invalid("the Idempotency-Key header is not visible ASCII".into()).into()
        }),
    }
}

/// A storing route's answer; a replay of a stored one says so in `Idempotent-Replayed: true`.
pub fn answer_response(a: crate::service::Answer) -> Response {
    let mut resp = axum::Json(a.body).into_response();
    if a.replayed {
        resp.headers_mut()
            .insert("idempotent-replayed", HeaderValue::from_static("true"));
    }
    resp
}

/// `POST /v1/fuse`: one docs/PAPER-METHOD.md §8 round (without truth) or `{"rounds": [...]}`.
pub async fn fuse(
    State(st): State<AppState>,
    headers: HeaderMap,
    ApiJson(body): ApiJson<Value>,
) -> Result<Response, ApiError> {
    let key = idempotency_header(&headers)?;
    let answer = st.service.fuse(body, key.as_deref()).await?;
    Ok(with_position(&st, answer_response(answer)).await)
}

/// A write's answer with `x-vlmfuse-position: rounds,labelled`, where the engine stands after
/// it: a follower that forwarded the write waits until its own copy of the engine holds it.
pub async fn with_position(st: &AppState, mut resp: Response) -> Response {
    let p = st.service.position().await;
    if let Ok(v) = HeaderValue::from_str(&format!("{},{}", p.rounds, p.labelled)) {
        resp.headers_mut()
            .insert(crate::service::replica::POSITION_HEADER, v);
    }
    resp
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FeedbackIn {
    round_id: String,
    /// The labels that are present (required unless `signals` gives them).
    #[serde(default)]
    labels: Option<Vec<String>>,
    /// The labels whose truth this feedback gives (present or not); absent: all of them.
    #[serde(default)]
    known: Option<Vec<String>>,
    /// Who says so: `human` (the default), `kinematics`, `detector` or a caller's name.
    #[serde(default)]
    source: Option<String>,
    /// A vehicle-signal track (CSV or JSON lines) to derive the labels from, instead of
    /// `labels` and `known` (source `kinematics` unless given).
    #[serde(default)]
    signals: Option<String>,
}

/// `POST /v1/feedback`: labels a fused round, wholly or in part; idempotent per label.
pub async fn feedback(
    State(st): State<AppState>,
    ApiJson(body): ApiJson<FeedbackIn>,
) -> Result<Response, ApiError> {
    let given = crate::service::FeedbackGiven {
        labels: body.labels,
        known: body.known,
        source: body.source,
        signals: body.signals,
    };
    let (out, repeated) = st.service.feedback(body.round_id, given).await?;
    let mut resp = axum::Json(out).into_response();
    if repeated {
        resp.headers_mut()
            .insert("x-vlmfuse-repeated", HeaderValue::from_static("true"));
    }
    Ok(with_position(&st, resp).await)
}

/// `POST /v1/label`: `{"text": "..."}` or `{"text": ["...", ...]}` → labels with evidence.
pub async fn label(
    State(st): State<AppState>,
    ApiJson(body): ApiJson<Value>,
) -> Result<Response, ApiError> {
    let (texts, batch) = label_texts(&body)?;
    let out = st.service.label(&texts).await?;
    let mut results = out.outputs.into_iter().map(crate::wire::LabelOut::from);
    Ok(if batch {
        axum::Json(crate::wire::LabelBatchOut {
            labeler: out.labeler,
            label_ms: out.label_ms,
            results: results.collect(),
        })
        .into_response()
    } else {
        axum::Json(crate::wire::LabelOneOut {
            labeler: out.labeler,
            label_ms: out.label_ms,
            result: results.next().expect("one output per text"),
        })
        .into_response()
    })
}

/// Reads `/v1/label`'s body by hand, so that every mistake is named exactly (serde's untagged
/// enums only say "did not match any variant").
fn label_texts(body: &Value) -> Result<(Vec<String>, bool), ServiceError> {
    let bad = |m: String| ServiceError::Invalid(m);
    let obj = body
        .as_object()
        .ok_or_else(|| bad("the body must be a JSON object {\"text\": ...}".into()))?;
    if let Some(k) = obj.keys().find(|k| k.as_str() != "text") {
        return Err(bad(format!(
            "unknown field {k:?}; the only field is \"text\""
        )));
    }
    match obj.get("text") {
        None => Err(bad(
            "missing field \"text\" (a string or a list of strings)".into(),
        )),
        Some(Value::String(t)) => Ok((vec![t.clone()], false)),
        Some(Value::Array(xs)) => xs
            .iter()
            .enumerate()
            .map(|(i, x)| {
                x.as_str()
                    .map(str::to_string)
                    .ok_or_else(|| bad(format!("text[{i}] is not a string")))
            })
            .collect::<Result<Vec<_>, _>>()
            .map(|v| (v, true)),
        Some(_) => Err(bad("\"text\" must be a string or a list of strings".into())),
    }
}

/// `GET /v1/state`.
pub async fn state(State(st): State<AppState>) -> Response {
    axum::Json(st.service.state().await).into_response()
}

/// `GET /v1/review` query: `limit` (default 20) and `window` (default
/// [`crate::service::REVIEW_DEFAULT_WINDOW`]).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReviewQuery {
    limit: Option<usize>,
    window: Option<usize>,
}

/// `GET /v1/review?limit=&window=`: the rounds a person should label next, with the reasons.
pub async fn review(
    State(st): State<AppState>,
    q: Result<axum::extract::Query<ReviewQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Response, ApiError> {
    let axum::extract::Query(q) = q.map_err(|r| ApiError::Body {
        status: r.status(),
        kind: "invalid_request",
        message: r.body_text(),
    })?;
    let out = st
        .service
        .review(
            q.limit.unwrap_or(20),
            q.window.unwrap_or(crate::service::REVIEW_DEFAULT_WINDOW),
        )
        .await?;
    Ok(axum::Json(out).into_response())
}

/// `GET /v1/ontology`.
pub async fn ontology(State(st): State<AppState>) -> Response {
    axum::Json(st.service.ontology().await).into_response()
}

/// `GET /healthz`: the process answers.
pub async fn healthz() -> Response {
    axum::Json(serde_json::json!({"status": "ok"})).into_response()
}

/// `GET /readyz`: each component's state; 503 when `/v1/infer` (if configured) cannot serve or
/// the store refuses writes. The route is open to anyone, so the reasons it gives name no
/// internal address (`http://10.0.0.7:8000/v1/models` reads `<address>/v1/models`) unless the
/// request carries the configured token; the full reasons are in the log either way.
pub async fn readyz(State(st): State<AppState>, headers: HeaderMap) -> Response {
    let mut r = st.service.readiness();
    if !super::has_token(&st, &headers) {
        redact_addresses(&mut r.body);
    }
    let status = if r.ready {
        axum::http::StatusCode::OK
    } else {
        axum::http::StatusCode::SERVICE_UNAVAILABLE
    };
    (status, axum::Json(r.body)).into_response()
}

/// Replaces the `scheme://authority` of every URL in every string of `v` with `<address>`,
/// keeping the path (which says what failed: `/v1/models`, `/v1/chat/completions`).
fn redact_addresses(v: &mut Value) {
    match v {
        Value::String(s) if s.contains("://") => *s = redact_str(s),
        Value::Array(a) => a.iter_mut().for_each(redact_addresses),
        Value::Object(o) => o.values_mut().for_each(redact_addresses),
        _ => {}
    }
}

fn redact_str(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    let mut rest = s;
    while let Some(i) = rest.find("://") {
        // The scheme: letters, digits, `+`, `-`, `.` before `://`.
        let start = rest[..i]
            .rfind(|c: char| !(c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.')))
            .map_or(0, |j| j + 1);
        let after = &rest[i + 3..];
        let end = after
            .find(|c: char| c == '/' || c.is_whitespace() || "\"'<>),;`".contains(c))
            .unwrap_or(after.len());
        if start == i {
            // No scheme: not a URL.
            out.push_str(&rest[..i + 3]);
            rest = after;
            continue;
        }
        out.push_str(&rest[..start]);
        out.push_str("<address>");
        rest = &after[end..];
    }
    out.push_str(rest);
    out
}

/// `GET /metrics`: Prometheus text.
pub async fn metrics(State(st): State<AppState>) -> Response {
    let mut h = HeaderMap::new();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
    );
    st.service.publish_replica_gauges();
    (h, st.service.metrics().render()).into_response()
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_are_redacted_paths_kept() {
        assert_eq!(
            redact_str("GET http://10.0.0.7:8000/v1/models: connection refused"),
            "GET <address>/v1/models: connection refused"
        );
        assert_eq!(
            redact_str("`https://user:pw@vllm.internal` and http://[::1]:9/x"),
            "`<address>` and <address>/x"
        );
        assert_eq!(redact_str("no url :// here"), "no url :// here");
        let mut v = serde_json::json!({"a": ["x http://h:1/p"], "b": {"c": "ftp://q"}, "d": 3});
        redact_addresses(&mut v);
        assert_eq!(
            v,
            serde_json::json!({"a": ["x <address>/p"], "b": {"c": "<address>"}, "d": 3})
        );
    }
}
