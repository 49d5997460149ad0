//! The service layer's one error type. It says what went wrong in the service's terms and keeps
//! the lower layers' errors as sources; it knows nothing of HTTP. `http::error` is the one place
//! that turns it into a status and a `{"error", "kind"}` body.

use vlmfuse_fusion::FusionError;
use vlmfuse_media::MediaError;
use vlmfuse_models::ModelError;
use vlmfuse_store::StoreError;

#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The round or labels break docs/PAPER-METHOD.md §8 (unknown reporter or label, dimension, NaN, ...), or
    /// (`FusionError::Config`) the engine's configuration is unusable.
    #[error("{0}")]
    Fusion(#[from] FusionError),
    /// A round of a batch is refused; the batch is refused whole.
    #[error("rounds[{index}]: {source}")]
    InBatch {
        index: usize,
        #[source]
        source: FusionError,
    },
    /// The operator's side: the database failed. The request changed nothing.
    #[error("storage failed: {0}")]
    Store(#[from] StoreError),
    /// The group commit that held this round failed; nothing of the group was stored.
    #[error("internal error: storing the round failed, nothing was stored: {0}")]
    NotStored(String),
    /// The body is JSON but not the expected shape, or breaks a documented rule.
    #[error("{0}")]
    Invalid(String),
    /// `/v1/fuse` was sent a round with its truth.
    #[error("{0}")]
    TruthNotAccepted(String),
    #[error("more than {0} clips in one request")]
    TooManyClips(usize),
    #[error("round {0:?} does not exist")]
    UnknownRound(String),
    /// Something else a read names that does not exist (a round's thumbnail).
    #[error("{0} does not exist")]
    NotFound(String),
    /// A vehicle-signal track the rules cannot trust (`kind` names why: non-monotonic time,
    /// NaN, out of range, not covering the clip, ...). Nothing is stored.
    #[error("{message}")]
    Signals { kind: &'static str, message: String },
    /// A signal track larger than `[annotate] max_bytes`.
    #[error("the signals track is larger than {0} bytes ([annotate] max_bytes)")]
    SignalsTooLarge(u64),
    /// A second feedback for a round, with other labels.
    #[error("{0}")]
    Conflict(String),
    /// An idempotency key that names another request (other body or route).
    #[error("{0}")]
    IdempotencyKeyReused(String),
    /// A component the request needs is not loaded, or the writer refuses writes.
    #[error("{message}")]
    NotReady {
        message: String,
        not_ready: Vec<String>,
    },
    /// Every reporter of a /v1/infer round failed; nothing was stored.
    #[error("every reporter failed: {}", fmt_failed(.0))]
    ReportersFailed(Vec<(String, String)>),
    /// The upload could not be decoded (the class says whose fault).
    #[error("{0}")]
    Media(#[from] MediaError),
    #[error("internal error: embedder: {0}")]
    Embedder(#[source] ModelError),
    /// The labeler failed on a `/v1/label` request (its kind says whether the model, a remote
    /// server or its queue).
    #[error("labeler: {0}")]
    Labeler(#[source] vlmfuse_labeler::LabelerError),
    /// The writer thread is gone (shutting down, or it panicked).
    #[error("internal error: the writer stopped")]
    WriterStopped,
    #[error("internal error: {0}")]
    Internal(String),
    /// The writer's error answer to a write this replica forwarded (`replica`), passed on as
    /// it came: its status and its `{"error", "kind", ...}` body.
    #[error("{}", .body.get("error").and_then(|e| e.as_str()).unwrap_or("the writer refused the request"))]
    Forwarded {
        status: u16,
        body: serde_json::Value,
    },
}

fn fmt_failed(f: &[(String, String)]) -> String {
    f.iter()
        .map(|(n, why)| format!("{n}: {why}"))
        .collect::<Vec<_>>()
        .join("; ")
}

impl ServiceError {
    /// The service's own failure (a bug, a stopped writer, the disk) rather than the caller's or
    /// a component's readiness: worth an error log line.
    pub fn is_internal(&self) -> bool {
        match self {
            ServiceError::Fusion(FusionError::Config(_)) => true,
            ServiceError::Store(StoreError::Mismatch(_)) => false,
            ServiceError::Store(_) | ServiceError::NotStored(_) => true,
            ServiceError::Media(e) => !e.is_client_error(),
            ServiceError::Embedder(_) | ServiceError::WriterStopped | ServiceError::Internal(_) => {
                true
            }
            ServiceError::Labeler(e) => {
                !matches!(
                    e.kind(),
                    vlmfuse_labeler::LabelerErrorKind::Http
                        | vlmfuse_labeler::LabelerErrorKind::BadAnswer
                ) && !matches!(e, vlmfuse_labeler::LabelerError::Backend(_))
            }
            _ => false,
        }
    }
}
