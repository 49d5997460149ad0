//! vlmfuse-store
