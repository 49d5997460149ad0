//! One error type for every backend, so the HTTP layer can map failures to statuses in one place
//! and `/readyz` can say why a backend is not ready.

use std::path::PathBuf;
use std::time::Duration;

use vlmfuse_core::chat::ChatError;
use vlmfuse_core::BackendError;

/// What a failed Hub download names.
#[derive(Debug)]
pub struct DownloadFailure {
    pub repo: String,
    pub revision: String,
    pub file: String,
    /// The cache root searched.
    pub cache: PathBuf,
    pub reason: String,
}

/// Why a model backend failed.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// A weight/config/tokenizer file is not where we looked. Carries every place searched,
    /// because with an offline cache the fix is nearly always "put the file there".
    #[error("missing model file `{file}`; looked in: {}", fmt_paths(.searched))]
    MissingWeights {
        file: String,
        searched: Vec<PathBuf>,
    },

    /// A Hub file that is not in the cache and could not be downloaded either (boxed: the
    /// error stays small on the hot paths that return it).
    #[error(
        "cannot get `{}` of {}@{}: not in the HF cache {} and the download failed: {} (set HF_ENDPOINT or the weights' `endpoint` for a mirror, or fill the cache with `huggingface-cli download {} --revision {}`)",
        .0.file, .0.repo, .0.revision, .0.cache.display(), .0.reason, .0.repo, .0.revision
    )]
    Download(Box<DownloadFailure>),

    /// A file exists but cannot be used (truncated safetensors, wrong tensor shapes, ...).
    #[error("unusable weights in {path}: {reason}")]
    BadWeights { path: PathBuf, reason: String },

    /// The model's config (or ours) is malformed or asks for something unsupported.
    #[error("bad config: {0}")]
    BadConfig(String),

    /// The requested device does not exist or was not compiled in.
    #[error("device: {0}")]
    Device(String),

    /// The caller handed us something we cannot process (no frames, wrong buffer size, ...).
    #[error("invalid input: {0}")]
    InvalidInput(String),

    /// An error from candle during a forward pass or tensor manipulation.
    #[error("candle: {0}")]
    Candle(#[from] candle_core::Error),

    /// ONNX Runtime: its library, a model file, or a forward pass (the ONNX backends).
    #[error(transparent)]
    Onnx(#[from] vlmfuse_ort::OrtError),

    /// Local I/O (reading a clip to upload, a config file).
    #[error("i/o on {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// A remote server failed: an error status, no answer, a timeout or an unusable body, after
    /// the shared chat client's retries.
    #[error(transparent)]
    Chat(#[from] ChatError),

    /// A tokenizer could not be built from its files or could not encode a text.
    #[error("tokenizer: {0}")]
    Tokenizer(String),

    /// Something took longer than it was allowed to.
    #[error("{what} timed out after {:.3}s", .after.as_secs_f64())]
    Timeout { what: String, after: Duration },

    /// The local backend's worker pool refused or lost the call (queue full, stopped, panicked).
    #[error(transparent)]
    Backend(#[from] BackendError),
}

impl From<vlmfuse_core::FrameError> for ModelError {
    fn from(e: vlmfuse_core::FrameError) -> Self {
        ModelError::InvalidInput(e.to_string())
    }
}

fn fmt_paths(p: &[PathBuf]) -> String {
    if p.is_empty() {
        return "(nowhere)".into();
    }
    p.iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

impl ModelError {
    /// A short stable tag for logs, metrics labels and API error bodies, where the full message
    /// (paths, URLs) would explode cardinality.
    pub fn kind(&self) -> &'static str {
        match self {
            ModelError::MissingWeights { .. } => "missing_weights",
            ModelError::Download(_) => "download_failed",
            ModelError::BadWeights { .. } => "bad_weights",
            ModelError::BadConfig(_) => "bad_config",
            ModelError::Device(_) => "device",
            ModelError::InvalidInput(_) => "invalid_input",
            ModelError::Candle(_) => "candle",
            ModelError::Onnx(e) => e.kind(),
            ModelError::Io { .. } => "io",
            ModelError::Chat(ChatError::Remote { .. }) => "remote",
            ModelError::Chat(ChatError::Timeout { .. }) => "timeout",
            ModelError::Chat(ChatError::BadResponse { .. }) => "bad_response",
            ModelError::Tokenizer(_) => "tokenizer",
            ModelError::Timeout { .. } => "timeout",
            ModelError::Backend(BackendError::QueueFull { .. }) => "busy",
            ModelError::Backend(BackendError::TimedOut { .. }) => "timeout",
            ModelError::Backend(BackendError::Stopped { .. }) => "stopped",
            ModelError::Backend(BackendError::Panicked { .. }) => "panic",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_weights_message_names_file_and_places() {
        let e = ModelError::MissingWeights {
            file: "model.safetensors".into(),
            searched: vec!["/a".into(), "/b/snap".into()],
        };
        let s = e.to_string();
        assert!(
            s.contains("model.safetensors") && s.contains("/a") && s.contains("/b/snap"),
            "{s}"
        );
        assert_eq!(e.kind(), "missing_weights");
    }

    #[test]
    fn remote_message_has_status_and_attempts() {
        let e = ModelError::Chat(ChatError::Remote {
            endpoint: "http://x/v1/chat/completions".into(),
            status: Some(503),
            attempts: 3,
            message: "overloaded".into(),
        });
        let s = e.to_string();
        assert!(s.contains("503") && s.contains("3 attempt"), "{s}");
        assert_eq!(e.kind(), "remote");
    }
}
