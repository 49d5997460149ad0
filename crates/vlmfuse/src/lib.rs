//! `vlmfuse`: the service, the evaluation protocol and the benchmarks, as a library under a thin
//! binary. The data flow of `/v1/infer`, module by module:
//!
//! ```text
//! http (multipart upload) -> service::infer: media (frames) -> models (context, reports)
//!     -> labeler (labels) -> service::fuse: fusion engine -> store (writer) -> wire -> http
//! ```
//!
//! * [`config`]: one TOML + flag + environment struct per section;
//! * [`service`]: the engine, the writer thread, the clip pipeline; its own error type, no HTTP;
//! * [`conn`]: the socket edge: connection cap, header-read and idle timeouts;
//! * [`http`]: the route table, middleware, and the one place errors become statuses;
//! * [`wire`]: the JSON shapes of the answers;
//! * [`serve`], [`eval`], [`bench`], [`label`], [`describe`]: the subcommands ([`cli`]).

pub mod annotate;
pub mod bench;
pub mod cli;
pub mod config;
pub mod conn;
pub mod describe;
pub mod detect;
pub mod eval;
pub mod http;
pub mod import;
pub mod label;
mod plots;
pub mod serve;
pub mod service;
pub mod telemetry;
pub mod wire;

pub use config::{Config, ServeArgs};
pub use http::{app, AppState};
