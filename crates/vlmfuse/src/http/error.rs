//! The one place where a failure becomes an HTTP status: every handler and middleware returns
//! [`ApiError`], and the service's errors reach the wire only through [`ApiError::Service`], so
//! the status, the `{"error", "kind"}` body and the rejection metric cannot disagree between
//! routes. Lower layers classify (`FusionError::kind`, `MediaError::class`, ...); only this file
//! knows what a class means in HTTP.

use crate::service::ServiceError;
use axum::extract::multipart::{MultipartError, MultipartRejection};
use axum::extract::rejection::JsonRejection;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use vlmfuse_fusion::FusionError;
use vlmfuse_labeler::{LabelerError, LabelerErrorKind};
use vlmfuse_media::{MediaError, MediaErrorClass};
use vlmfuse_models::BackendError;
use vlmfuse_store::StoreError;

#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    #[error(transparent)]
    Service(#[from] ServiceError),
    /// Axum could not read the body (JSON or multipart); `status` is what axum would have used.
    #[error("{message}")]
    Body {
        status: StatusCode,
        kind: &'static str,
        message: String,
    },
    #[error("missing or wrong bearer token")]
    Unauthorized,
    #[error("the server is at its concurrency limit ({0} requests in flight); retry later")]
    Overloaded(usize),
    #[error("the request took longer than {0} s; a feedback may still have been applied, and repeating it is safe")]
    Timeout(f64),
    #[error("no route {0}")]
    NotFound(String),
    #[error("method not allowed on this route")]
    MethodNotAllowed,
    #[error("internal error: {0}")]
    Internal(String),
}

impl From<MediaError> for ApiError {
    fn from(e: MediaError) -> Self {
        ApiError::Service(e.into())
    }
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

/// What a class of media failure means to an HTTP client.
pub fn media_status(class: MediaErrorClass) -> StatusCode {
    match class {
        MediaErrorClass::Oversized => StatusCode::PAYLOAD_TOO_LARGE,
        MediaErrorClass::Unsupported => StatusCode::UNSUPPORTED_MEDIA_TYPE,
        MediaErrorClass::Malformed => StatusCode::BAD_REQUEST,
        MediaErrorClass::Rejected => StatusCode::UNPROCESSABLE_ENTITY,
        MediaErrorClass::Internal => StatusCode::INTERNAL_SERVER_ERROR,
        MediaErrorClass::Interrupted => StatusCode::SERVICE_UNAVAILABLE,
    }
}

/// What a labeler failure means to an HTTP client: the labeler is the server's component, so
/// never the caller's fault. A remote LLM that failed or answered nonsense is a bad gateway; a
/// full or slow worker queue is a retry-later.
fn labeler_status(e: &LabelerError) -> (StatusCode, &'static str) {
    match e {
        LabelerError::Backend(BackendError::QueueFull { .. }) => {
            (StatusCode::SERVICE_UNAVAILABLE, "labeler_busy")
        }
        LabelerError::Backend(BackendError::TimedOut { .. }) => {
            (StatusCode::SERVICE_UNAVAILABLE, "timeout")
        }
        e => match e.kind() {
            LabelerErrorKind::Http | LabelerErrorKind::BadAnswer => {
                (StatusCode::BAD_GATEWAY, "labeler_upstream")
            }
            _ => (StatusCode::INTERNAL_SERVER_ERROR, "internal"),
        },
    }
}

fn service_status(e: &ServiceError) -> StatusCode {
    use ServiceError as S;
    match e {
        S::Fusion(FusionError::Config(_)) => StatusCode::INTERNAL_SERVER_ERROR,
        S::Fusion(_) | S::InBatch { .. } => StatusCode::UNPROCESSABLE_ENTITY,
        S::Store(StoreError::Mismatch(_)) => StatusCode::UNPROCESSABLE_ENTITY,
        S::Store(_) | S::NotStored(_) => StatusCode::INTERNAL_SERVER_ERROR,
        S::Invalid(_) | S::TruthNotAccepted(_) | S::TooManyClips(_) => {
            StatusCode::UNPROCESSABLE_ENTITY
        }
        S::UnknownRound(_) | S::NotFound(_) => StatusCode::NOT_FOUND,
        S::Signals { .. } => StatusCode::UNPROCESSABLE_ENTITY,
        S::SignalsTooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
        S::Conflict(_) => StatusCode::CONFLICT,
        S::IdempotencyKeyReused(_) => StatusCode::UNPROCESSABLE_ENTITY,
        S::NotReady { .. } | S::ReportersFailed(_) => StatusCode::SERVICE_UNAVAILABLE,
        S::Media(m) => media_status(m.class()),
        S::Embedder(_) | S::WriterStopped | S::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        S::Labeler(l) => labeler_status(l).0,
        S::Forwarded { status, .. } => {
            StatusCode::from_u16(*status).unwrap_or(StatusCode::BAD_GATEWAY)
        }
    }
}

fn service_kind(e: &ServiceError) -> &'static str {
    use ServiceError as S;
    match e {
        S::Fusion(f) | S::InBatch { source: f, .. } => f.kind(),
        S::Store(StoreError::Mismatch(_)) => "dimension_mismatch",
        S::Store(_) => "storage",
        S::Invalid(_) => "invalid_request",
        S::TruthNotAccepted(_) => "truth_not_accepted",
        S::TooManyClips(_) => "too_many_clips",
        S::UnknownRound(_) => "unknown_round",
        S::NotFound(_) => "not_found",
        S::Signals { .. } => "bad_signals",
        S::SignalsTooLarge(_) => "signals_too_large",
        S::Conflict(_) => "conflict",
        S::IdempotencyKeyReused(_) => "idempotency_key_reused",
        S::NotReady { .. } => "not_ready",
        S::ReportersFailed(_) => "reporters_failed",
        S::Media(m) if m.is_client_error() => m.kind(),
        S::Labeler(l) => labeler_status(l).1,
        // The writer's own kind is in the body, passed on as it came.
        S::Forwarded { .. } => "forwarded",
        S::Media(_) | S::NotStored(_) | S::Embedder(_) | S::WriterStopped | S::Internal(_) => {
            "internal"
        }
    }
}

impl ApiError {
    pub fn status(&self) -> StatusCode {
        match self {
            ApiError::Service(e) => service_status(e),
            ApiError::Body { status, .. } => *status,
            ApiError::NotFound(_) => StatusCode::NOT_FOUND,
            ApiError::Unauthorized => StatusCode::UNAUTHORIZED,
            ApiError::Overloaded(_) => StatusCode::TOO_MANY_REQUESTS,
            ApiError::Timeout(_) => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    pub fn kind(&self) -> &'static str {
        match self {
            ApiError::Service(e) => service_kind(e),
            ApiError::Body { kind, .. } => kind,
            ApiError::Unauthorized => "unauthorized",
            ApiError::Overloaded(_) => "overloaded",
            ApiError::Timeout(_) => "timeout",
            ApiError::NotFound(_) => "not_found",
            ApiError::MethodNotAllowed => "method_not_allowed",
            ApiError::Internal(_) => "internal",
        }
    }

    fn message(&self) -> String {
        match self {
            ApiError::Service(ServiceError::Media(m)) if !m.is_client_error() => {
                format!("internal error: media: {m}")
            }
            other => other.to_string(),
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

fn multipart_error(status: StatusCode, message: String) -> ApiError {
    let kind = match status {
        StatusCode::PAYLOAD_TOO_LARGE => "payload_too_large",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_media_type",
        _ => "invalid_multipart",
    };
    ApiError::Body {
        status,
        kind,
        message,
    }
}

impl From<MultipartRejection> for ApiError {
    fn from(r: MultipartRejection) -> Self {
        multipart_error(r.status(), r.body_text())
    }
}

impl From<MultipartError> for ApiError {
    fn from(r: MultipartError) -> Self {
        multipart_error(r.status(), r.body_text())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        if let ApiError::Service(ServiceError::Forwarded { body, .. }) = self {
            return (status, axum::Json(body)).into_response();
        }
        let kind = self.kind();
        metrics::counter!("vlmfuse_rejected_requests_total", "kind" => kind).increment(1);
        let (not_ready, failed) = match &self {
            ApiError::Service(ServiceError::NotReady { not_ready, .. }) => {
                (Some(not_ready.as_slice()), None)
            }
            ApiError::Service(ServiceError::ReportersFailed(f)) => (
                None,
                Some(
                    f.iter()
                        .map(|(n, why)| (n.clone(), serde_json::Value::String(why.clone())))
                        .collect(),
                ),
            ),
            _ => (None, None),
        };
        let message = self.message();
        if status.is_server_error() && not_ready.is_none() && failed.is_none() {
            tracing::error!(kind, "{message}");
        }
        let body = Body {
            error: message,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The statuses media errors have always had: 413 over the size limit, 415 for what cannot
    /// be read, 400 for nothing usable, 422 for a real but refused video, 500 for our side.
    #[test]
    fn media_errors_map_to_their_statuses() {
        let cases: Vec<(MediaError, u16)> = vec![
            (
                MediaError::TooLarge {
                    bytes: 2,
                    max_bytes: 1,
                },
                413,
            ),
            (MediaError::NotVideo, 415),
            (MediaError::UnsupportedCodec("x".into()), 415),
            (MediaError::Empty, 400),
            (MediaError::InvalidOptions("x".into()), 400),
            (MediaError::NoVideoStream, 422),
            (MediaError::Corrupt("x".into()), 422),
            (
                MediaError::TooLong {
                    duration_s: 2.0,
                    max_duration_s: 1.0,
                },
                422,
            ),
            (
                MediaError::ResolutionTooHigh {
                    width: 2,
                    height: 2,
                    max_width: 1,
                    max_height: 1,
                },
                422,
            ),
            (
                MediaError::TooManySamples {
                    table: "stsz",
                    declared: 2,
                    limit: 1,
                },
                422,
            ),
            (MediaError::Io(std::io::Error::other("disk")), 500),
            (MediaError::Internal("x".into()), 500),
        ];
        for (e, want) in cases {
            let kind = e.kind();
            let client = e.is_client_error();
            let api = ApiError::from(e);
            assert_eq!(api.status().as_u16(), want, "{api}");
            assert_eq!(api.kind(), if client { kind } else { "internal" });
            assert!(!api.message().is_empty());
        }
    }

    #[test]
    fn service_errors_keep_their_kinds_and_statuses() {
        let e = ApiError::from(ServiceError::InBatch {
            index: 1,
            source: FusionError::EmptyCoalition,
        });
        assert_eq!((e.status().as_u16(), e.kind()), (422, "empty_coalition"));
        assert!(e.message().starts_with("rounds[1]: "), "{}", e.message());
        let e = ApiError::from(ServiceError::UnknownRound("r-1".into()));
        assert_eq!((e.status().as_u16(), e.kind()), (404, "unknown_round"));
        let e = ApiError::from(ServiceError::Store(StoreError::Mismatch("dim".into())));
        assert_eq!((e.status().as_u16(), e.kind()), (422, "dimension_mismatch"));
        let e = ApiError::from(ServiceError::WriterStopped);
        assert_eq!((e.status().as_u16(), e.kind()), (500, "internal"));
        let e = ApiError::from(ServiceError::Labeler(LabelerError::BadAnswer {
            labeler: "openai:x".into(),
            attempts: 2,
            reason: "unknown label".into(),
        }));
        assert_eq!((e.status().as_u16(), e.kind()), (502, "labeler_upstream"));
        let e = ApiError::from(ServiceError::Labeler(LabelerError::Backend(
            BackendError::QueueFull {
                backend: "embedding".into(),
                capacity: 64,
            },
        )));
        assert_eq!((e.status().as_u16(), e.kind()), (503, "labeler_busy"));
        let e = ApiError::from(ServiceError::Labeler(LabelerError::Model("nan".into())));
        assert_eq!((e.status().as_u16(), e.kind()), (500, "internal"));
    }
}
