//! One error type for every backend, so that the service can map failures to a reporter state
//! (failed vs. misconfigured) without knowing which backend produced them.

/// Coarse classification of a [`LabelerError`], stable for metrics and HTTP mapping.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LabelerErrorKind {
    /// The label set itself is unusable (empty, duplicate ids).
    Ontology,
    /// A configuration value is out of range.
    Config,
    /// A model file is missing; fetching the assets fixes it.
    AssetMissing,
    /// The model failed to load or run.
    Model,
    /// Tokenisation failed.
    Tokenizer,
    /// The remote service could not be reached or answered with an HTTP error.
    Http,
    /// The remote LLM answered, but not with a valid label set (after the allowed retries).
    BadAnswer,
    /// File-system error.
    Io,
    /// A worker thread panicked or was cancelled.
    Internal,
}

#[derive(Debug, thiserror::Error)]
pub enum LabelerError {
    #[error("invalid ontology: {0}")]
    Ontology(#[from] vlmfuse_core::OntologyError),
    #[error("invalid labeler config: {0}")]
    Config(String),
    #[error("asset not found: {0} (run scripts/fetch-assets.sh)")]
    AssetMissing(String),
    #[error("model error: {0}")]
    Model(String),
    #[error("tokenizer error: {0}")]
    Tokenizer(String),
    /// The remote chat server failed (after the shared client's retries).
    #[error("http error: {0}")]
    Chat(#[from] vlmfuse_core::ChatError),
    #[error("model error: {0}")]
    Candle(#[from] candle_core::Error),
    /// The labeler's worker refused or lost the call (queue full, stopped, panicked).
    #[error("labeler worker failed: {0}")]
    Backend(#[from] vlmfuse_core::BackendError),
    #[error("bad answer from labeler {labeler} after {attempts} attempt(s): {reason}")]
    BadAnswer {
        labeler: String,
        attempts: u32,
        reason: String,
    },
    #[error("io error: {0}")]
    Io(#[from] std::io::Error),
    #[error("internal error: {0}")]
    Internal(String),
    /// The caller gave up (its timeout passed, the client left) and the work stopped early.
    #[error("labelling cancelled: the caller no longer waits")]
    Cancelled,
}

impl LabelerError {
    pub fn kind(&self) -> LabelerErrorKind {
        match self {
            LabelerError::Ontology(_) => LabelerErrorKind::Ontology,
            LabelerError::Config(_) => LabelerErrorKind::Config,
            LabelerError::AssetMissing(_) => LabelerErrorKind::AssetMissing,
            LabelerError::Model(_) => LabelerErrorKind::Model,
            LabelerError::Tokenizer(_) => LabelerErrorKind::Tokenizer,
            LabelerError::Chat(_) => LabelerErrorKind::Http,
            LabelerError::Candle(_) => LabelerErrorKind::Model,
            LabelerError::Backend(_) => LabelerErrorKind::Internal,
            LabelerError::BadAnswer { .. } => LabelerErrorKind::BadAnswer,
            LabelerError::Io(_) => LabelerErrorKind::Io,
            LabelerError::Internal(_) | LabelerError::Cancelled => LabelerErrorKind::Internal,
        }
    }
}

/// Model code runs in `vlmfuse-models`; its failures keep their meaning here (a missing file is
/// still a missing asset, a bad config still a config error), so `/readyz` and the HTTP mapping
/// need not know where the model code lives.
impl From<vlmfuse_models::ModelError> for LabelerError {
    fn from(e: vlmfuse_models::ModelError) -> Self {
        use vlmfuse_models::ModelError as M;
        match e {
            M::MissingWeights { .. } => LabelerError::AssetMissing(e.to_string()),
            M::Onnx(vlmfuse_ort::OrtError::LibraryMissing { .. }) => {
                LabelerError::AssetMissing(e.to_string())
            }
            M::BadConfig(m) => LabelerError::Config(m),
            M::Tokenizer(m) => LabelerError::Tokenizer(m),
            M::Candle(e) => LabelerError::Candle(e),
            M::Chat(e) => LabelerError::Chat(e),
            M::Backend(e) => LabelerError::Backend(e),
            M::Io { path, source } => LabelerError::Io(std::io::Error::new(
                source.kind(),
                format!("{}: {source}", path.display()),
            )),
            other => LabelerError::Model(other.to_string()),
        }
    }
}
