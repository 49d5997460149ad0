//! The one place where vlmfuse meets ONNX Runtime: finding and loading `libonnxruntime`, the
//! process-wide environment, and the session policy (threads, optimisation) that every ONNX
//! backend shares.
//!
//! Why a crate of its own: the context embedder (in `vlmfuse-models`), the labeler's sentence
//! encoder (in `vlmfuse-labeler`) and the object detector (in `vlmfuse-detect`) all run on ONNX
//! Runtime, none of those crates depends on another, and ONNX Runtime allows exactly one
//! environment per process. Keeping the library lookup, the environment and the thread policy
//! here means every backend loads the same library once and sizes its pool by the same rule,
//! and only this crate names `ort`'s loading API.
//!
//! Why `load-dynamic`: `ort`'s default features download a prebuilt runtime at build time, which
//! cannot work offline; instead the shared library of the PyPI wheel `onnxruntime==1.31.1` is
//! opened at run time (`scripts/fetch-assets.sh` puts it in the asset cache). A missing or wrong
//! library is then an ordinary error at start-up, never a panic inside `ort`.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

pub use ort;
use ort::environment::Environment;
use ort::session::builder::GraphOptimizationLevel;
use ort::session::Session;

/// The ONNX Runtime release this build is written and tested against (its C API version 31 is
/// what `ort`'s `api-31` feature requires; newer 1.x releases also load).
pub const ORT_VERSION: &str = "1.31.1";
/// File name of the shared library inside the wheel and the asset cache.
pub const LIBRARY_FILE: &str = "libonnxruntime.so.1.31.1";
/// Environment variable naming the shared library explicitly (the name `ort` itself uses).
pub const DYLIB_ENV: &str = "ORT_DYLIB_PATH";
/// Environment variable that overrides the asset cache root (shared with the fetch script).
pub const ASSETS_ENV: &str = "VLMFUSE_ASSETS";

/// Why ONNX Runtime could not be used. One type for the whole crate; the backends map it into
/// their own layer's error.
#[derive(Debug, thiserror::Error)]
pub enum OrtError {
    /// No library at any of the places searched. Fix: `scripts/fetch-assets.sh`, or point
    /// `ORT_DYLIB_PATH` (or the config's library path) at `libonnxruntime.so`.
    #[error("ONNX Runtime library not found; looked in: {}. Run scripts/fetch-assets.sh or set {DYLIB_ENV}", fmt_paths(.searched))]
    LibraryMissing { searched: Vec<PathBuf> },

    /// The file exists but is not a usable ONNX Runtime (not a shared library, too old, ...).
    #[error("cannot load ONNX Runtime from {path}: {reason}")]
    LibraryLoad { path: PathBuf, reason: String },

    /// ONNX Runtime refused to create its environment.
    #[error("ONNX Runtime environment: {0}")]
    Environment(String),

    /// The session options were rejected (for example a thread count).
    #[error("ONNX Runtime session options: {0}")]
    Options(String),

    /// A model file could not be turned into a session (not ONNX, unsupported operator, its
    /// external weights missing or outside the model's directory, ...).
    #[error("cannot load ONNX model {path}: {reason}")]
    Model { path: PathBuf, reason: String },

    /// A model loaded but its inputs or outputs are not what the backend needs.
    #[error("ONNX model {path} does not fit: {reason}")]
    Signature { path: PathBuf, reason: String },

    /// A forward pass failed.
    #[error("ONNX Runtime run failed: {0}")]
    Run(String),
}

impl OrtError {
    /// A short stable tag for logs and metrics.
    pub fn kind(&self) -> &'static str {
        match self {
            OrtError::LibraryMissing { .. } => "runtime_missing",
            OrtError::LibraryLoad { .. } => "runtime_load",
            OrtError::Environment(_) => "runtime_environment",
            OrtError::Options(_) => "session_options",
            OrtError::Model { .. } => "bad_model",
            OrtError::Signature { .. } => "bad_model",
            OrtError::Run(_) => "run",
        }
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

/// The asset cache root: `$VLMFUSE_ASSETS`, else `$HOME/.cache/vlmfuse-assets` (where the fetch
/// script puts the library and the models).
pub fn assets_root() -> PathBuf {
    if let Some(p) = std::env::var_os(ASSETS_ENV).filter(|p| !p.is_empty()) {
        return PathBuf::from(p);
    }
    let home = std::env::var_os("HOME").unwrap_or_else(|| ".".into());
    Path::new(&home).join(".cache").join("vlmfuse-assets")
}

/// Where the fetch script puts the library.
pub fn cached_library() -> PathBuf {
    assets_root().join("onnxruntime").join(LIBRARY_FILE)
}

/// The library to load: `explicit` (from config) if given, else `$ORT_DYLIB_PATH`, else the
/// asset cache. A path that is named but missing is an error rather than a fall-through, so a
/// typo in config never silently loads another runtime.
pub fn library_path(explicit: Option<&Path>) -> Result<PathBuf, OrtError> {
    let named = explicit.map(Path::to_path_buf).or_else(|| {
        std::env::var_os(DYLIB_ENV)
            .filter(|p| !p.is_empty())
            .map(PathBuf::from)
    });
    let candidate = named.clone().unwrap_or_else(cached_library);
    if candidate.is_file() {
        Ok(candidate)
    } else {
        Err(OrtError::LibraryMissing {
            searched: vec![candidate],
        })
    }
}

struct Loaded {
    env: Environment,
    library: PathBuf,
}

static RUNTIME: OnceLock<Loaded> = OnceLock::new();
static INIT: Mutex<()> = Mutex::new(());

/// The process-wide ONNX Runtime environment, loading the library on first use (see
/// [`library_path`] for where it is looked for).
///
/// ONNX Runtime allows one environment per process, so the first successful call fixes the
/// library; a later call that names another file gets the loaded one and a warning. A failed
/// call leaves nothing behind, so a retry (after fetching the library) can succeed.
pub fn environment(explicit_library: Option<&Path>) -> Result<&'static Environment, OrtError> {
    if let Some(l) = RUNTIME.get() {
        warn_if_other(l, explicit_library);
        return Ok(&l.env);
    }
    let _guard = INIT.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(l) = RUNTIME.get() {
        warn_if_other(l, explicit_library);
        return Ok(&l.env);
    }
    let library = library_path(explicit_library)?;
    let builder = ort::init_from(&library).map_err(|e| OrtError::LibraryLoad {
        path: library.clone(),
        reason: e.to_string(),
    })?;
    let env = builder
        .with_name("vlmfuse")
        .with_telemetry(false)
        .build()
        .map_err(|e| OrtError::Environment(e.to_string()))?;
    tracing::info!(library = %library.display(), "loaded ONNX Runtime");
    Ok(&RUNTIME.get_or_init(|| Loaded { env, library }).env)
}

fn warn_if_other(l: &Loaded, explicit: Option<&Path>) {
    if let Some(p) = explicit {
        if p != l.library {
            tracing::warn!(requested = %p.display(), loaded = %l.library.display(),
                "ONNX Runtime is already loaded from another file; one runtime per process");
        }
    }
}

/// The library that [`environment`] loaded, if it has run successfully.
pub fn loaded_library() -> Option<&'static Path> {
    RUNTIME.get().map(|l| l.library.as_path())
}

/// The number of cores this process may use (the default pool size).
pub fn default_threads() -> usize {
    std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1)
}

/// How a backend's sessions run. One value per backend, from its config section.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct SessionOptions {
    /// Threads of the session's intra-op pool, counting the thread that calls `run` (ONNX
    /// Runtime makes it the pool's first worker). `None`: the core count. This is the whole
    /// compute budget of the backend: inter-op parallelism is off (one thread walks the graph),
    /// and callers run sessions from one blocking thread, not from the async runtime's workers,
    /// so a pool of N keeps N cores busy and no more.
    pub threads: Option<usize>,
    /// Library override (config); `None` uses `ORT_DYLIB_PATH` or the asset cache.
    pub library: Option<PathBuf>,
}

impl SessionOptions {
    pub fn with_threads(threads: usize) -> Self {
        Self {
            threads: Some(threads),
            ..Default::default()
        }
    }

    /// The intra-op pool size these options resolve to.
    pub fn resolved_threads(&self) -> usize {
        self.threads.unwrap_or_else(default_threads).max(1)
    }
}

/// Opens an ONNX model file as a CPU session with the shared policy: all graph optimisations,
/// sequential execution (inter-op 1), an intra-op pool of [`SessionOptions::resolved_threads`].
///
/// Loads from a path (never from bytes) so that weights stored as external data beside the
/// model (large exports, and the MiniLM graph that reads a `model.safetensors`) resolve.
pub fn session_from_file(path: &Path, opts: &SessionOptions) -> Result<Session, OrtError> {
    if opts.threads == Some(0) {
        return Err(OrtError::Options("threads must be at least 1".into()));
    }
    if !path.is_file() {
        return Err(OrtError::Model {
            path: path.to_path_buf(),
            reason: "no such file".into(),
        });
    }
    let env = environment(opts.library.as_deref())?;
    let threads = opts.resolved_threads();
    let opt_err =
        |e: ort::Error<ort::session::builder::SessionBuilder>| OrtError::Options(e.to_string());
    let mut builder = Session::builder(env)
        .map_err(|e| OrtError::Options(e.to_string()))?
        .with_optimization_level(GraphOptimizationLevel::All)
        .map_err(opt_err)?
        .with_parallel_execution(false)
        .map_err(opt_err)?
        .with_inter_threads(1)
        .map_err(opt_err)?
        .with_intra_threads(threads)
        .map_err(opt_err)?;
    let session = builder
        .commit_from_file(path)
        .map_err(|e| OrtError::Model {
            path: path.to_path_buf(),
            reason: explain_model_error(e.message()),
        })?;
    tracing::debug!(model = %path.display(), threads, "ONNX session ready");
    Ok(session)
}

/// Adds the fix to ONNX Runtime's messages that users hit with real model directories.
fn explain_model_error(msg: &str) -> String {
    if msg.contains("escapes model directory") {
        format!(
            "{msg} (external weights must be regular files inside the model's directory; \
             replace a symlinked weights file by a hard link or a copy)"
        )
    } else {
        msg.to_string()
    }
}

/// A human-readable list of a session's inputs or outputs (`name: type`), for errors that say
/// what a model offers when it lacks what a backend needs.
pub fn describe_outlets(outlets: &[ort::value::Outlet]) -> String {
    outlets
        .iter()
        .map(|o| format!("{}: {}", o.name(), o.dtype()))
        .collect::<Vec<_>>()
        .join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn explicit_missing_library_is_an_error_naming_it() {
        let e = library_path(Some(Path::new("/nonexistent/libonnxruntime.so"))).unwrap_err();
        assert_eq!(e.kind(), "runtime_missing");
        let s = e.to_string();
        assert!(s.contains("/nonexistent/libonnxruntime.so"), "{s}");
        assert!(
            s.contains("fetch-assets.sh") && s.contains(DYLIB_ENV),
            "{s}"
        );
    }

    #[test]
    fn zero_threads_is_refused_before_anything_loads() {
        let e =
            session_from_file(Path::new("/x.onnx"), &SessionOptions::with_threads(0)).unwrap_err();
        assert_eq!(e.kind(), "session_options");
        assert_eq!(
            SessionOptions::default().resolved_threads(),
            default_threads()
        );
    }

    #[test]
    fn missing_model_file_is_an_error_before_the_runtime_loads() {
        let e = session_from_file(Path::new("/nonexistent/m.onnx"), &SessionOptions::default())
            .unwrap_err();
        assert_eq!(e.kind(), "bad_model");
        assert!(e.to_string().contains("/nonexistent/m.onnx"), "{e}");
    }

    #[test]
    fn escaping_external_data_gets_the_fix() {
        let s = explain_model_error("External data path escapes model directory.");
        assert!(s.contains("hard link"), "{s}");
        assert_eq!(explain_model_error("other"), "other");
    }
}
