//! The tests that need the real `vlmfuse` binary: `kill -9` and SIGTERM, and `vlmfuse eval`'s
//! and `vlmfuse label`'s command lines. Everything else runs in-process (the `service` tests).

mod eval_cli;
mod label_cli;
mod readiness;
mod replay;
mod shutdown;
mod slowloris;
mod soak;
mod support;
