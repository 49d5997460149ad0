//! Tiny random-weight models in the real on-disk formats. No real weights can be downloaded
//! where this is built, so tests here and in the service crate load these through the same code
//! paths as production checkpoints.

pub mod qwen3_vl;
pub mod video_llava;

pub use qwen3_vl::TinyQwen3Vl;
pub use video_llava::TinyVideoLlava;

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};

use crate::ModelError;

/// Deterministic PRNG (splitmix64) so fixtures are identical across runs and machines; candle's
/// `randn` draws from an unseeded thread RNG.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [-1, 1).
    pub fn uniform(&mut self) -> f32 {
        ((self.next_u64() >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }

    /// A tensor with entries `center + scale * U(-1, 1)`.
    pub fn tensor(&mut self, shape: &[usize], center: f32, scale: f32) -> Tensor {
        let n: usize = shape.iter().product();
        let v: Vec<f32> = (0..n).map(|_| center + scale * self.uniform()).collect();
        Tensor::from_vec(v, shape, &Device::Cpu).expect("shape matches length")
    }
}

/// Shape of a tiny CLIP; field names follow HF `vision_config`.
#[derive(Debug, Clone)]
pub struct TinyClip {
    pub image_size: usize,
    pub patch_size: usize,
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub projection_dim: usize,
}

impl Default for TinyClip {
    fn default() -> Self {
        Self {
            image_size: 32,
            patch_size: 8,
            hidden_size: 32,
            intermediate_size: 64,
            num_hidden_layers: 2,
            num_attention_heads: 2,
            projection_dim: 16,
        }
    }
}

impl TinyClip {
    /// `config.json` in the layout of openai/clip-vit-base-patch32 (a full `CLIPConfig`).
    pub fn config_json(&self) -> serde_json::Value {
        serde_json::json!({
            "architectures": ["CLIPModel"],
            "model_type": "clip",
            "projection_dim": self.projection_dim,
            "logit_scale_init_value": 2.6592,
            "text_config": {
                "hidden_size": 16, "intermediate_size": 32, "num_attention_heads": 2,
                "num_hidden_layers": 1, "vocab_size": 64, "max_position_embeddings": 8,
                "projection_dim": self.projection_dim, "hidden_act": "quick_gelu"
            },
            "vision_config": {
                "hidden_size": self.hidden_size,
                "intermediate_size": self.intermediate_size,
                "num_hidden_layers": self.num_hidden_layers,
                "num_attention_heads": self.num_attention_heads,
                "image_size": self.image_size,
                "patch_size": self.patch_size,
                "projection_dim": self.projection_dim,
                "hidden_act": "quick_gelu",
                "layer_norm_eps": 1e-5,
                "num_channels": 3,
                "model_type": "clip_vision_model"
            }
        })
    }

    /// Random weights under the key names of HF CLIP checkpoints (vision tower, projection, and a
    /// couple of text-side tensors so loading must ignore what it does not use).
    pub fn tensors(&self, seed: u64) -> HashMap<String, Tensor> {
        let mut r = Rng::new(seed);
        let h = self.hidden_size;
        let i = self.intermediate_size;
        let p = self.patch_size;
        let n_pos = (self.image_size / p).pow(2) + 1;
        let mut t = HashMap::new();
        let v = "vision_model";
        let w = 1.0 / (h as f32).sqrt();
        t.insert(
            format!("{v}.embeddings.class_embedding"),
            r.tensor(&[h], 0.0, 0.5),
        );
        t.insert(
            format!("{v}.embeddings.patch_embedding.weight"),
            r.tensor(&[h, 3, p, p], 0.0, 1.0 / ((3 * p * p) as f32).sqrt()),
        );
        t.insert(
            format!("{v}.embeddings.position_embedding.weight"),
            r.tensor(&[n_pos, h], 0.0, 0.1),
        );
        for ln in ["pre_layrnorm", "post_layernorm"] {
            t.insert(format!("{v}.{ln}.weight"), r.tensor(&[h], 1.0, 0.1));
            t.insert(format!("{v}.{ln}.bias"), r.tensor(&[h], 0.0, 0.1));
        }
        for l in 0..self.num_hidden_layers {
            let pre = format!("{v}.encoder.layers.{l}");
            for proj in ["q_proj", "k_proj", "v_proj", "out_proj"] {
                t.insert(
                    format!("{pre}.self_attn.{proj}.weight"),
                    r.tensor(&[h, h], 0.0, w),
                );
                t.insert(
                    format!("{pre}.self_attn.{proj}.bias"),
                    r.tensor(&[h], 0.0, 0.02),
                );
            }
            for ln in ["layer_norm1", "layer_norm2"] {
                t.insert(format!("{pre}.{ln}.weight"), r.tensor(&[h], 1.0, 0.1));
                t.insert(format!("{pre}.{ln}.bias"), r.tensor(&[h], 0.0, 0.1));
            }
            t.insert(format!("{pre}.mlp.fc1.weight"), r.tensor(&[i, h], 0.0, w));
            t.insert(format!("{pre}.mlp.fc1.bias"), r.tensor(&[i], 0.0, 0.02));
            t.insert(
                format!("{pre}.mlp.fc2.weight"),
                r.tensor(&[h, i], 0.0, 1.0 / (i as f32).sqrt()),
            );
            t.insert(format!("{pre}.mlp.fc2.bias"), r.tensor(&[h], 0.0, 0.02));
        }
        t.insert(
            "visual_projection.weight".into(),
            r.tensor(&[self.projection_dim, h], 0.0, w),
        );
        t.insert(
            "text_projection.weight".into(),
            r.tensor(&[self.projection_dim, 16], 0.0, 0.25),
        );
        t.insert("logit_scale".into(), r.tensor(&[], 2.6592, 0.0));
        t
    }

    /// Writes `config.json` + `model.safetensors` into `dir` (created if needed).
    pub fn write(&self, dir: &Path, seed: u64) -> Result<(), ModelError> {
        std::fs::create_dir_all(dir).map_err(|source| ModelError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let cfg = serde_json::to_string_pretty(&self.config_json()).expect("json");
        std::fs::write(dir.join("config.json"), cfg).map_err(|source| ModelError::Io {
            path: dir.join("config.json"),
            source,
        })?;
        candle_core::safetensors::save(&self.tensors(seed), dir.join("model.safetensors"))?;
        Ok(())
    }
}

/// Lays out `files` (already written in `src_dir`) as an HF hub cache entry under `cache_root`:
/// blobs + `snapshots/<commit>/` symlinks + `refs/<revision>`, as `huggingface_hub` does.
pub fn write_hf_cache_entry(
    cache_root: &Path,
    repo_id: &str,
    revision: &str,
    commit: &str,
    src_dir: &Path,
    files: &[&str],
) -> Result<(), ModelError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| ModelError::Io { path, source }
    };
    let repo = cache_root.join(format!("models--{}", repo_id.replace('/', "--")));
    let blobs = repo.join("blobs");
    let snap = repo.join("snapshots").join(commit);
    let refs = repo.join("refs").join(revision);
    std::fs::create_dir_all(&blobs).map_err(io(&blobs))?;
    std::fs::create_dir_all(&snap).map_err(io(&snap))?;
    std::fs::create_dir_all(refs.parent().expect("has parent")).map_err(io(&refs))?;
    std::fs::write(&refs, commit).map_err(io(&refs))?;
    for (k, f) in files.iter().enumerate() {
        // Real blob names are content hashes; any unique name exercises the symlink layout.
        let blob = blobs.join(format!("{k:040x}"));
        std::fs::copy(src_dir.join(f), &blob).map_err(io(&blob))?;
        let link = snap.join(f);
        #[cfg(unix)]
        std::os::unix::fs::symlink(Path::new("../../blobs").join(format!("{k:040x}")), &link)
            .map_err(io(&link))?;
        #[cfg(not(unix))]
        std::fs::copy(&blob, &link).map_err(io(&link))?;
    }
    Ok(())
}
