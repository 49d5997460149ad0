//! Model backends for vlmfuse: the context embedder (CLIP on candle), the reporters (remote
//! OpenAI-compatible VLMs and in-process candle VLMs), weight loading and device placement.
//! Nothing here knows about HTTP serving or the fusion maths.

pub mod device;
pub mod embed;
mod error;
pub mod fixtures;
mod frames;
pub mod lora;
pub mod reporter;
pub mod weights;

pub use device::parse_device;
pub use embed::{ClipEmbedder, ContextEmbedder, OnnxClipConfig, OnnxClipEmbedder};
pub use error::ModelError;
pub use frames::{Frame, FrameRef};
pub use reporter::{
    run_all, CandleVlmConfig, CandleVlmReporter, ClipInput, ClipMeta, OpenAiReporter,
    OpenAiReporterConfig, Reporter, ReporterFailure, ReporterOutput, DEFAULT_PROMPT,
};
pub use weights::WeightSource;
