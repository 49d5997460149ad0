//! Model backends for vlmfuse: the context embedder (CLIP on candle), the reporters (remote
//! OpenAI-compatible VLMs and in-process candle VLMs), weight loading and device placement.
//! Nothing here knows about HTTP serving or the fusion maths.

pub mod chat_template;
pub mod device;
pub mod embed;
mod error;
pub mod generate;
pub mod imaging;
pub mod lora;
pub mod models;
pub mod ops;
pub mod reporter;
pub mod text;
pub mod weights;

pub use device::parse_device;
pub use embed::{ClipEmbedder, ContextEmbedder, Embedder, OnnxClipConfig, OnnxClipEmbedder};
pub use error::{DownloadFailure, ModelError};
pub use reporter::{
    run_all, run_all_batch, CandleVlmConfig, CandleVlmReporter, ClipInput, ClipMeta, LocalReporter,
    OpenAiReporter, OpenAiReporterConfig, Reporter, ReporterFailure, ReporterOutput, RoundReporter,
    DEFAULT_PROMPT,
};
pub use vlmfuse_core::{BackendError, BackendPool, PoolConfig};
pub use vlmfuse_core::{Frame, FrameRef};
pub use weights::WeightSource;
