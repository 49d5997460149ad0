//! The service in-process (`app(state)` with `oneshot`, no socket): errors and limits,
//! concurrency, and the clip pipeline. One test binary for all of them, so they link once.

mod concurrency;
mod detect;
mod errors;
mod feedback;
mod hardening;
mod infer_media;
mod infer_pipeline;
mod label;
mod review;
mod signals;
mod support;
mod ui;
