//! Test tooling for the vlmfuse workspace (`publish = false`): what the tests, examples and
//! benchmarks share, kept out of the library crates' APIs. It depends on nothing heavier than
//! `vlmfuse-core` (and, behind the `server` feature, axum), so the engine's tests stay free of
//! the model stack; the model fixtures, the real-asset lookup and the labeler evaluation live in
//! `vlmfuse-testkit-models`.
//!
//! * [`rng`]: the one splitmix64 and the one LCG;
//! * [`rounds`], [`clips`], [`multipart`], [`resp`]: rounds files, test clips, upload bodies,
//!   HTTP answers as tests see them;
//! * `server` (feature `server`): local and fake OpenAI-compatible servers.

pub mod clips;
pub mod multipart;
pub mod netcut;
pub mod pg;
pub mod resp;
pub mod rng;
pub mod rounds;
#[cfg(feature = "server")]
pub mod server;
