//! The one place where a failure becomes an HTTP status: every handler and middleware returns
//! [`ApiError`], so the status, the `{"error", "kind"}` body and the rejection metric cannot
//! disagree between routes.

use axum::extract::rejection::JsonRejection;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use vlmfuse_fusion::FusionError;
use vlmfuse_store::StoreError;

#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// The round or labels break SPEC §8 (unknown reporter or label, dimension, NaN, ...).
    #[error("{0}")]
    Fusion(#[from] FusionError),
    /// The operator's side: the database failed. The request changed nothing.
    #[error("storage failed: {0}")]
    Store(#[from] StoreError),
    /// Axum could not read the body as JSON; `status` is what axum would have used.
    #[error("{message}")]
    Body {
        status: StatusCode,
        kind: &'static str,
        message: String,
    },
    /// The body is JSON but not the expected shape, or breaks a documented rule.
    #[error("{0}")]
    Invalid(String),
    #[error("round {0:?} does not exist")]
    UnknownRound(String),
    #[error("{0}")]
    Conflict(String),
    #[error("missing or wrong bearer token")]
    Unauthorized,
    #[error("the server is at its concurrency limit ({0} requests in flight); retry later")]
    Overloaded(usize),
    #[error("the request took longer than {0} s; a feedback may still have been applied, and repeating it is safe")]
    Timeout(f64),
    #[error("{message}")]
    NotReady {
        message: String,
        not_ready: Vec<String>,
    },
    /// Every reporter of a /v1/infer round failed; nothing was stored.
    #[error("every reporter failed: {}", fmt_failed(.0))]
    ReportersFailed(Vec<(String, String)>),
    #[error("no route {0}")]
    NotFound(String),
    #[error("method not allowed on this route")]
    MethodNotAllowed,
    #[error("internal error: {0}")]
    Internal(String),
}

#[derive(Serialize)]
struct Body<'a> {
    error: String,
    kind: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    not_ready: Option<&'a [String]>,
    /// Reporter name -> why it failed (kind `reporters_failed`).
    #[serde(skip_serializing_if = "Option::is_none")]
    failed: Option<serde_json::Map<String, serde_json::Value>>,
}

fn fmt_failed(f: &[(String, String)]) -> String {
    f.iter()
        .map(|(n, why)| format!("{n}: {why}"))
        .collect::<Vec<_>>()
        .join("; ")
}

impl ApiError {
    pub fn status(&self) -> StatusCode {
        match self {
            ApiError::Fusion(FusionError::Config(_)) => StatusCode::INTERNAL_SERVER_ERROR,
            ApiError::Fusion(_) | ApiError::Invalid(_) => StatusCode::UNPROCESSABLE_ENTITY,
            ApiError::Store(StoreError::Mismatch(_)) => StatusCode::UNPROCESSABLE_ENTITY,
            ApiError::Store(_) | ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
            ApiError::Body { status, .. } => *status,
            ApiError::UnknownRound(_) | ApiError::NotFound(_) => StatusCode::NOT_FOUND,
            ApiError::Conflict(_) => StatusCode::CONFLICT,
            ApiError::Unauthorized => StatusCode::UNAUTHORIZED,
            ApiError::Overloaded(_) => StatusCode::TOO_MANY_REQUESTS,
            ApiError::Timeout(_) | ApiError::NotReady { .. } | ApiError::ReportersFailed(_) => {
                StatusCode::SERVICE_UNAVAILABLE
            }
            ApiError::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
        }
    }

    pub fn kind(&self) -> &'static str {
        match self {
            ApiError::Fusion(e) => e.kind(),
            ApiError::Store(StoreError::Mismatch(_)) => "dimension_mismatch",
            ApiError::Store(_) => "storage",
            ApiError::Body { kind, .. } => kind,
            ApiError::Invalid(_) => "invalid_request",
            ApiError::UnknownRound(_) => "unknown_round",
            ApiError::Conflict(_) => "conflict",
            ApiError::Unauthorized => "unauthorized",
            ApiError::Overloaded(_) => "overloaded",
            ApiError::Timeout(_) => "timeout",
            ApiError::NotReady { .. } => "not_ready",
            ApiError::ReportersFailed(_) => "reporters_failed",
            ApiError::NotFound(_) => "not_found",
            ApiError::MethodNotAllowed => "method_not_allowed",
            ApiError::Internal(_) => "internal",
        }
    }
}

impl From<JsonRejection> for ApiError {
    fn from(rej: JsonRejection) -> Self {
        let status = rej.status();
        let kind = match status {
            StatusCode::BAD_REQUEST => "malformed_json",
            StatusCode::PAYLOAD_TOO_LARGE => "payload_too_large",
            StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_media_type",
            StatusCode::UNPROCESSABLE_ENTITY => "invalid_request",
            _ => "bad_request",
        };
        ApiError::Body {
            status,
            kind,
            message: rej.body_text(),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        let kind = self.kind();
        metrics::counter!("vlmfuse_rejected_requests_total", "kind" => kind).increment(1);
        if status.is_server_error()
            && !matches!(
                self,
                ApiError::NotReady { .. } | ApiError::ReportersFailed(_)
            )
        {
            tracing::error!(kind, "{self}");
        }
        let not_ready = match &self {
            ApiError::NotReady { not_ready, .. } => Some(not_ready.as_slice()),
            _ => None,
        };
        let failed = match &self {
            ApiError::ReportersFailed(f) => Some(
                f.iter()
                    .map(|(n, why)| (n.clone(), serde_json::Value::String(why.clone())))
                    .collect(),
            ),
            _ => None,
        };
        let body = Body {
            error: self.to_string(),
            kind,
            not_ready,
            failed,
        };
        let mut resp = (status, axum::Json(body)).into_response();
        if matches!(self, ApiError::Unauthorized) {
            resp.headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        if matches!(self, ApiError::Overloaded(_)) {
            resp.headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from_static("1"));
        }
        resp
    }
}
