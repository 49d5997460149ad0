//! The tests that need the real `vlmfuse` binary: `kill -9` and SIGTERM, and the command lines
//! of `vlmfuse eval`, `vlmfuse label` and `vlmfuse describe`. Everything else runs in-process
//! (the `service` tests).

mod annotate_cli;
mod describe_cli;
mod detect_cli;
mod eval_cli;
mod label_cli;
mod readiness;
mod replay;
mod replicas;
mod shutdown;
mod slowloris;
mod soak;
mod support;
mod ui_browser;
