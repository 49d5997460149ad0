//! vlmfuse-fusion
