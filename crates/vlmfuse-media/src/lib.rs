//! vlmfuse-media
