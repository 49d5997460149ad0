//! Context embedders turn a clip's frames into one vector; the fusion engine's kNN bank compares
//! clips by these vectors, so they must be deterministic and unit-norm.

mod clip;
mod onnx;

pub use clip::{ClipEmbedder, ClipVisionSettings};
pub use onnx::{OnnxClipConfig, OnnxClipEmbedder, ONNX_MODEL_CANDIDATES};

use std::sync::Arc;

use vlmfuse_core::{BackendPool, PoolConfig};

use crate::{Frame, FrameRef, ModelError};

/// Embeds a clip (its sampled frames) into a fixed-size, unit-norm vector.
///
/// Implementations block (forward passes). Async callers go through [`Embedder`], never call
/// this on the runtime's threads.
pub trait ContextEmbedder: Send + Sync + 'static {
    fn name(&self) -> &str;
    fn dim(&self) -> usize;
    fn embed(&self, frames: &[FrameRef]) -> Result<Vec<f32>, ModelError>;
}

/// The async face of a context embedder: its own worker thread and bounded queue
/// ([`BackendPool`]), so concurrent clips queue for the model instead of each holding a thread.
pub struct Embedder {
    pool: BackendPool<dyn ContextEmbedder>,
}

impl Embedder {
    pub fn new(embedder: Arc<dyn ContextEmbedder>, cfg: PoolConfig) -> std::io::Result<Self> {
        let name = embedder.name().to_string();
        Ok(Self {
            pool: BackendPool::new(name, embedder, cfg)?,
        })
    }

    pub fn name(&self) -> &str {
        self.pool.backend().name()
    }

    pub fn dim(&self) -> usize {
        self.pool.backend().dim()
    }

    /// Embeds the frames on the embedder's worker.
    pub async fn embed(&self, frames: Arc<[Frame]>) -> Result<Vec<f32>, ModelError> {
        self.pool
            .call(move |e, _| {
                let refs: Vec<FrameRef> = frames.iter().map(Frame::as_ref).collect();
                e.embed(&refs)
            })
            .await?
    }
}
