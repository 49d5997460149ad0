//! The CLIP context embedder on ONNX Runtime, for CPU deployments (the candle backend stays the
//! choice on CUDA).
//!
//! It loads the layouts that HF exports come in: `onnx/vision_model.onnx` (transformers.js /
//! `CLIPVisionModelWithProjection`, outputs `image_embeds`) or a `model.onnx` (Optimum: either
//! the vision tower with projection, or a whole `CLIPModel` that also wants text inputs), next to
//! the checkpoint's `preprocessor_config.json`. The clip embedding is what the candle backend
//! computes: the projected image embeddings of the frames (`image_embeds`), averaged, then
//! L2-normalised, all frames in one batched run.
//!
//! Threads: the session's intra-op pool is the backend's whole compute budget
//! ([`vlmfuse_ort::SessionOptions`]); preprocessing splits frames over the same number of threads
//! before the run, so the two never overlap. Callers run [`ContextEmbedder::embed`] on one
//! blocking thread, which ONNX Runtime makes its first worker.

use std::num::NonZeroUsize;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use vlmfuse_ort::ort::session::{Session, SessionInputValue};
use vlmfuse_ort::ort::value::{Tensor, TensorElementType, TensorRef};
use vlmfuse_ort::{describe_outlets, OrtError, SessionOptions};

use super::ContextEmbedder;
use crate::imaging::ImageProcessor;
use crate::weights::WeightSource;
use crate::{FrameRef, ModelError};

/// Model files tried in order when none is named: the transformers.js layout first (a vision
/// tower alone is cheaper than a whole CLIPModel), then Optimum's.
pub const ONNX_MODEL_CANDIDATES: &[&str] = &[
    "onnx/vision_model.onnx",
    "vision_model.onnx",
    "model.onnx",
    "onnx/model.onnx",
];

/// Where the ONNX embedder's files come from and how it runs.
#[derive(Debug, Clone, PartialEq)]
pub struct OnnxClipConfig {
    /// The model directory (or HF cache entry) with the ONNX file and `preprocessor_config.json`.
    pub weights: WeightSource,
    /// The ONNX file inside it, when not one of [`ONNX_MODEL_CANDIDATES`] (for example
    /// `onnx/vision_model_fp32.onnx`).
    pub model_file: Option<String>,
    /// Threads and library (see [`SessionOptions`]).
    pub session: SessionOptions,
}

impl OnnxClipConfig {
    pub fn new(weights: WeightSource) -> Self {
        Self {
            weights,
            model_file: None,
            session: SessionOptions::default(),
        }
    }
}

/// A model input the embedder fills with a constant: a whole CLIPModel export insists on text
/// inputs although `image_embeds` does not depend on them.
#[derive(Debug, Clone)]
struct DummyInput {
    name: String,
    value: i64,
}

pub struct OnnxClipEmbedder {
    name: String,
    dim: usize,
    processor: ImageProcessor,
    /// Model input `(width, height)`.
    input_size: (u32, u32),
    pixel_input: String,
    dummies: Vec<DummyInput>,
    /// Whether the model's `image_embeds` are already unit-normalised per frame (CLIPModel).
    per_frame_normalised: bool,
    threads: NonZeroUsize,
    model_path: PathBuf,
    /// `Session::run` needs `&mut`; one run at a time is also what the thread budget assumes.
    session: Mutex<Session>,
}

impl std::fmt::Debug for OnnxClipEmbedder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnnxClipEmbedder")
            .field("name", &self.name)
            .field("model", &self.model_path)
            .field("dim", &self.dim)
            .field("threads", &self.threads)
            .finish()
    }
}

impl OnnxClipEmbedder {
    /// Finds the model, opens the session and checks its signature, then embeds one grey frame
    /// so that a model that cannot run fails here, at start-up, rather than on the first clip.
    pub fn load(cfg: &OnnxClipConfig) -> Result<Self, ModelError> {
        let model_path = find_model(&cfg.weights, cfg.model_file.as_deref())?;
        let mut session = vlmfuse_ort::session_from_file(&model_path, &cfg.session)?;
        let sig = |reason: String| {
            ModelError::Onnx(OrtError::Signature {
                path: model_path.clone(),
                reason,
            })
        };

        // Inputs: one float image tensor [batch, 3, H, W]; any int64 text inputs get constants.
        let mut pixel: Option<(String, Vec<i64>)> = None;
        let mut dummies = Vec::new();
        for o in session.inputs() {
            let ty = o.dtype().tensor_type();
            let shape: Vec<i64> = o
                .dtype()
                .tensor_shape()
                .map(|s| s.iter().copied().collect())
                .unwrap_or_default();
            match (o.name(), ty) {
                ("input_ids", Some(TensorElementType::Int64)) => dummies.push(DummyInput {
                    name: o.name().into(),
                    value: 0,
                }),
                ("attention_mask", Some(TensorElementType::Int64)) => dummies.push(DummyInput {
                    name: o.name().into(),
                    value: 1,
                }),
                (_, Some(TensorElementType::Float32)) if shape.len() == 4 && pixel.is_none() => {
                    pixel = Some((o.name().into(), shape))
                }
                _ => {
                    return Err(sig(format!(
                        "unexpected input `{}: {}`; a CLIP image export takes float \
                         pixel_values [batch, 3, H, W] (inputs: {})",
                        o.name(),
                        o.dtype(),
                        describe_outlets(session.inputs())
                    )))
                }
            }
        }
        let Some((pixel_input, shape)) = pixel else {
            return Err(sig(format!(
                "no float [batch, 3, H, W] image input (inputs: {}); fp16 and quantised-input \
                 exports are not supported",
                describe_outlets(session.inputs())
            )));
        };
        if shape[1] != 3 && shape[1] >= 0 {
            return Err(sig(format!(
                "image input has {} channels, frames are RGB",
                shape[1]
            )));
        }
        if !session.outputs().iter().any(|o| o.name() == "image_embeds") {
            return Err(sig(format!(
                "no `image_embeds` output (outputs: {}); export the vision tower with its \
                 projection (CLIPVisionModelWithProjection) or a whole CLIPModel",
                describe_outlets(session.outputs())
            )));
        }

        let processor = match cfg.weights.resolve_optional("preprocessor_config.json")? {
            Some(p) => {
                let text = std::fs::read_to_string(&p).map_err(|source| ModelError::Io {
                    path: p.clone(),
                    source,
                })?;
                let v: serde_json::Value = serde_json::from_str(&text)
                    .map_err(|e| ModelError::BadConfig(format!("{}: {e}", p.display())))?;
                ImageProcessor::from_preprocessor_config(&v)?
            }
            None => {
                let side = if shape[2] > 0 { shape[2] as u32 } else { 224 };
                tracing::warn!(source = %cfg.weights.describe(), side,
                    "no preprocessor_config.json; using CLIPImageProcessor's defaults");
                ImageProcessor::clip(side)
            }
        };
        let input_size = match processor.fixed_output_size() {
            Some(s) => s,
            None => {
                return Err(ModelError::BadConfig(
                    "preprocessor_config.json neither crops nor resizes to a fixed size; CLIP \
                     needs one input size"
                        .into(),
                ))
            }
        };
        let (mw, mh) = (shape[3], shape[2]);
        if (mw > 0 && mw != input_size.0 as i64) || (mh > 0 && mh != input_size.1 as i64) {
            return Err(ModelError::BadConfig(format!(
                "preprocessor_config.json makes {}x{} inputs but the model takes {mw}x{mh}",
                input_size.0, input_size.1
            )));
        }
        let per_frame_normalised = !dummies.is_empty();
        if per_frame_normalised {
            tracing::warn!(model = %model_path.display(),
                "a whole CLIPModel export: its image_embeds are unit-normalised per frame, so \
                 clip embeddings differ slightly from the candle backend's; export \
                 onnx/vision_model.onnx for identical ones");
        }

        let threads =
            NonZeroUsize::new(cfg.session.resolved_threads()).unwrap_or(NonZeroUsize::MIN);
        let dim = {
            // Warm-up: one frame of the training mean colour (all zeros once normalised) through
            // the real run path; also gives the dimension
            // when the export leaves it symbolic.
            let px = vec![0f32; 3 * input_size.0 as usize * input_size.1 as usize];
            let mut dummies_vals = Vec::new();
            let out = run(
                &mut session,
                &pixel_input,
                &px,
                1,
                input_size,
                &dummies,
                &mut dummies_vals,
            )?;
            out.len()
        };
        if dim == 0 {
            return Err(sig("image_embeds is empty".into()));
        }
        tracing::info!(model = %model_path.display(), dim, threads = threads.get(),
            width = input_size.0, height = input_size.1, "loaded CLIP embedder on ONNX Runtime");
        Ok(Self {
            name: format!("clip-onnx:{}", cfg.weights.describe()),
            dim,
            processor,
            input_size,
            pixel_input,
            dummies,
            per_frame_normalised,
            threads,
            model_path,
            session: Mutex::new(session),
        })
    }

    /// Overrides the name reported to the fusion engine and metrics.
    pub fn with_name(mut self, name: impl Into<String>) -> Self {
        self.name = name.into();
        self
    }

    /// The ONNX file in use.
    pub fn model_path(&self) -> &Path {
        &self.model_path
    }

    /// The preprocessing in use.
    pub fn processor(&self) -> &ImageProcessor {
        &self.processor
    }

    /// The intra-op pool size (and the number of preprocessing threads).
    pub fn threads(&self) -> usize {
        self.threads.get()
    }

    /// Whether per-frame embeddings come out unit-normalised (a whole CLIPModel export).
    pub fn per_frame_normalised(&self) -> bool {
        self.per_frame_normalised
    }

    /// The model's input `(width, height)`.
    pub fn input_size(&self) -> (u32, u32) {
        self.input_size
    }

    /// Per-frame `image_embeds`, one row per frame, as the model returns them.
    pub fn frame_embeddings(&self, frames: &[FrameRef]) -> Result<Vec<Vec<f32>>, ModelError> {
        if frames.is_empty() {
            return Err(ModelError::InvalidInput("no frames to embed".into()));
        }
        let (px, size) = self.processor.process_batch(frames, self.threads)?;
        debug_assert_eq!(size, self.input_size);
        self.pixel_embeddings(&px, frames.len())
    }

    /// Per-frame `image_embeds` of already preprocessed pixels (`[n, 3, H, W]`, normalised), so
    /// that tests and benchmarks can feed two engines exactly the same input.
    pub fn pixel_embeddings(&self, pixels: &[f32], n: usize) -> Result<Vec<Vec<f32>>, ModelError> {
        let per = 3 * self.input_size.0 as usize * self.input_size.1 as usize;
        if n == 0 || pixels.len() != n * per {
            return Err(ModelError::InvalidInput(format!(
                "{} pixel values for {n} frames of {}x{} (need {})",
                pixels.len(),
                self.input_size.0,
                self.input_size.1,
                n * per
            )));
        }
        let mut session = self.session.lock().unwrap_or_else(|p| p.into_inner());
        let mut scratch = Vec::new();
        let flat = run(
            &mut session,
            &self.pixel_input,
            pixels,
            n,
            self.input_size,
            &self.dummies,
            &mut scratch,
        )?;
        if flat.len() != n * self.dim {
            return Err(ModelError::Onnx(OrtError::Signature {
                path: self.model_path.clone(),
                reason: format!(
                    "image_embeds has {} values for {n} frames of dimension {}",
                    flat.len(),
                    self.dim
                ),
            }));
        }
        Ok(flat.chunks_exact(self.dim).map(<[f32]>::to_vec).collect())
    }

    /// The clip embedding of preprocessed pixels (see [`pixel_embeddings`](Self::pixel_embeddings)).
    pub fn embed_pixels(&self, pixels: &[f32], n: usize) -> Result<Vec<f32>, ModelError> {
        mean_unit(&self.pixel_embeddings(pixels, n)?)
    }
}

/// One run: the image tensor (borrowed, no copy) plus the constant inputs, returning the
/// flattened `image_embeds`.
fn run(
    session: &mut Session,
    pixel_input: &str,
    pixels: &[f32],
    n: usize,
    (w, h): (u32, u32),
    dummies: &[DummyInput],
    scratch: &mut Vec<Tensor<i64>>,
) -> Result<Vec<f32>, ModelError> {
    let run_err = |e: vlmfuse_ort::ort::Error| ModelError::Onnx(OrtError::Run(e.to_string()));
    let image =
        TensorRef::from_array_view(([n, 3, h as usize, w as usize], pixels)).map_err(run_err)?;
    scratch.clear();
    for d in dummies {
        scratch.push(Tensor::from_array(([1usize, 1], vec![d.value])).map_err(run_err)?);
    }
    let mut inputs: Vec<(&str, SessionInputValue<'_>)> = vec![(pixel_input, image.into())];
    for (d, t) in dummies.iter().zip(scratch.iter()) {
        inputs.push((d.name.as_str(), t.into()));
    }
    let outputs = session.run(inputs).map_err(run_err)?;
    let value = outputs
        .get("image_embeds")
        .ok_or_else(|| ModelError::Onnx(OrtError::Run("no image_embeds in the outputs".into())))?;
    let (shape, data) = value.try_extract_tensor::<f32>().map_err(run_err)?;
    if shape.len() != 2 || shape[0] != n as i64 {
        return Err(ModelError::Onnx(OrtError::Run(format!(
            "image_embeds has shape {shape:?}, expected [{n}, dim]"
        ))));
    }
    Ok(data.to_vec())
}

/// L2-normalised mean of the rows, accumulated in f64 (the candle path's definition).
fn mean_unit(rows: &[Vec<f32>]) -> Result<Vec<f32>, ModelError> {
    let dim = rows.first().map_or(0, Vec::len);
    let mut mean = vec![0f64; dim];
    for r in rows {
        for (m, v) in mean.iter_mut().zip(r) {
            *m += *v as f64;
        }
    }
    let n = mean.iter().map(|x| x * x).sum::<f64>().sqrt();
    if !n.is_finite() || n == 0.0 {
        return Err(ModelError::InvalidInput(format!(
            "clip embedding has norm {n}; cannot normalise"
        )));
    }
    Ok(mean.iter().map(|x| (x / n) as f32).collect())
}

fn find_model(source: &WeightSource, named: Option<&str>) -> Result<PathBuf, ModelError> {
    if let Some(f) = named {
        let p = Path::new(f);
        if p.is_absolute() {
            return if p.is_file() {
                Ok(p.to_path_buf())
            } else {
                Err(ModelError::MissingWeights {
                    file: f.into(),
                    searched: vec![p.to_path_buf()],
                })
            };
        }
        return source.resolve(f);
    }
    let mut searched = Vec::new();
    for c in ONNX_MODEL_CANDIDATES {
        match source.resolve(c) {
            Ok(p) => return Ok(p),
            Err(ModelError::MissingWeights { searched: s, .. }) => searched.extend(s),
            Err(e) => return Err(e),
        }
    }
    searched.dedup();
    Err(ModelError::MissingWeights {
        file: ONNX_MODEL_CANDIDATES.join(" or "),
        searched,
    })
}

impl ContextEmbedder for OnnxClipEmbedder {
    fn name(&self) -> &str {
        &self.name
    }

    fn dim(&self) -> usize {
        self.dim
    }

    fn embed(&self, frames: &[FrameRef]) -> Result<Vec<f32>, ModelError> {
        mean_unit(&self.frame_embeddings(frames)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_unit_is_the_normalised_mean() {
        let v = mean_unit(&[vec![3.0, 0.0], vec![1.0, 4.0]]).unwrap();
        // mean (2, 2) → (1/√2, 1/√2)
        assert!((v[0] - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-7);
        assert!((v[1] - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-7);
        assert_eq!(
            mean_unit(&[vec![0.0, 0.0]]).unwrap_err().kind(),
            "invalid_input"
        );
    }

    #[test]
    fn missing_model_names_every_candidate() {
        let dir = tempfile::tempdir().unwrap();
        let e = find_model(&WeightSource::local(dir.path()), None).unwrap_err();
        assert_eq!(e.kind(), "missing_weights");
        let s = e.to_string();
        for c in ONNX_MODEL_CANDIDATES {
            assert!(s.contains(&dir.path().join(c).display().to_string()), "{s}");
        }
        let e = find_model(&WeightSource::local(dir.path()), Some("/abs/x.onnx")).unwrap_err();
        assert!(e.to_string().contains("/abs/x.onnx"), "{e}");
    }
}
