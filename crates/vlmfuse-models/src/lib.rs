//! vlmfuse-models
