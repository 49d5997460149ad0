//! The label set. It lives in `vlmfuse-core`, shared with the labelers (which need the
//! descriptions); the engine addresses labels by index and uses names only at the edges.

pub use vlmfuse_core::ontology::*;
