//! Context embedders turn a clip's frames into one vector; the fusion engine's kNN bank compares
//! clips by these vectors, so they must be deterministic and unit-norm.

mod clip;
pub mod image_processor;
mod onnx;
pub mod preprocess;

pub use clip::{ClipEmbedder, ClipVisionSettings};
pub use onnx::{OnnxClipConfig, OnnxClipEmbedder, ONNX_MODEL_CANDIDATES};

use crate::{FrameRef, ModelError};

/// Embeds a clip (its sampled frames) into a fixed-size, unit-norm vector.
///
/// Implementations block (forward passes): call them from `spawn_blocking`, never on the async
/// runtime's threads.
pub trait ContextEmbedder: Send + Sync {
    fn name(&self) -> &str;
    fn dim(&self) -> usize;
    fn embed(&self, frames: &[FrameRef]) -> Result<Vec<f32>, ModelError>;
}
