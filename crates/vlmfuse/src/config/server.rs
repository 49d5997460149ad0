//! `[server]` and `[limits]`: where the service listens, where its state lives, who may write,
//! and how much one client may ask of it.

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

pub const DEFAULT_LISTEN: &str = "127.0.0.1:8080";
pub const DEFAULT_DATA_DIR: &str = "./data";

#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    /// Address to listen on [default: 127.0.0.1:8080].
    #[arg(long, env = "VLMFUSE_LISTEN", required = false)]
    pub listen: String,
    /// Directory of the embedded database [default: ./data].
    #[arg(long, env = "VLMFUSE_DATA_DIR", required = false)]
    pub data_dir: PathBuf,
    /// Bearer token required on the writing routes (/v1/fuse, /v1/infer, /v1/feedback); unset
    /// leaves them open (a loopback default). An empty variable means no key.
    #[arg(
        long,
        env = "VLMFUSE_API_KEY",
        hide_env_values = true,
        required = false
    )]
    pub api_key: Option<String>,
    /// Seconds between health probes of each remote reporter (`GET /v1/models` of its base
    /// URL); `/readyz` reports the last one. A probe waits at most this long, and 5 s.
    #[arg(long, env = "VLMFUSE_PROBE_INTERVAL_S", required = false)]
    pub probe_interval_s: f64,
    /// Seconds a client has to send a whole request head once its first byte arrived; a
    /// slower one (slowloris) is disconnected.
    #[arg(long, env = "VLMFUSE_HEADER_READ_TIMEOUT_S", required = false)]
    pub header_read_timeout_s: f64,
    /// Seconds a connection may sit idle (no request in flight, nothing received) before it is
    /// closed, after accept or between keep-alive requests.
    #[arg(long, env = "VLMFUSE_IDLE_TIMEOUT_S", required = false)]
    pub idle_timeout_s: f64,
    /// Most open client connections; past it new connections wait, unserved, until one closes.
    #[arg(long, env = "VLMFUSE_MAX_CONNECTIONS", required = false)]
    pub max_connections: usize,
    /// Free bytes the data directory's filesystem must keep; below it `/readyz` is 503 (the
    /// store cannot be trusted to commit the next round), so a balancer stops sending writes
    /// before SQLite fails them. 0 disables the check.
    #[arg(long, env = "VLMFUSE_MIN_FREE_BYTES", required = false)]
    pub min_free_bytes: u64,
    /// Seconds a shutdown (SIGTERM, Ctrl-C) waits for open connections to finish their
    /// requests before the process exits anyway; rounds already acknowledged are committed
    /// either way (the writer drains its queue after the connections are gone).
    #[arg(long, env = "VLMFUSE_SHUTDOWN_TIMEOUT_S", required = false)]
    pub shutdown_timeout_s: f64,
    /// Events (stored rounds plus feedbacks) after which the writer snapshots the engine, so
    /// that a restart replays at most about this many events instead of the whole history.
    /// 0: never by count. Written in the background from a copy; a snapshot is only a cache,
    /// the database stays the truth.
    #[arg(long, env = "VLMFUSE_SNAPSHOT_EVERY", required = false)]
    pub snapshot_every: u64,
    /// Seconds after which any new events are snapshotted even below `snapshot_every` (and on
    /// a clean shutdown), so a quiet service also restarts fast. 0: never by time.
    #[arg(long, env = "VLMFUSE_SNAPSHOT_INTERVAL_S", required = false)]
    pub snapshot_interval_s: f64,
    /// Snapshots kept (the newest; at least 1). Two leave one to fall back on if the newest is
    /// damaged.
    #[arg(long, env = "VLMFUSE_SNAPSHOT_KEEP", required = false)]
    pub snapshot_keep: usize,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            listen: DEFAULT_LISTEN.into(),
            data_dir: DEFAULT_DATA_DIR.into(),
            api_key: None,
            probe_interval_s: 10.0,
            header_read_timeout_s: 10.0,
            idle_timeout_s: 60.0,
            max_connections: 1024,
            min_free_bytes: 64 * 1024 * 1024,
            shutdown_timeout_s: 10.0,
            snapshot_every: 10_000,
            snapshot_interval_s: 600.0,
            snapshot_keep: 2,
        }
    }
}

#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    /// Largest request body in bytes (413 above).
    #[arg(long, env = "VLMFUSE_MAX_BODY_BYTES", required = false)]
    pub max_body_bytes: usize,
    /// Requests in flight on the /v1 routes before new ones get 429.
    #[arg(long, env = "VLMFUSE_CONCURRENCY_LIMIT", required = false)]
    pub concurrency_limit: usize,
    /// Seconds before a request is answered 503 (timeout).
    #[arg(long, env = "VLMFUSE_REQUEST_TIMEOUT_S", required = false)]
    pub request_timeout_s: f64,
    /// Most rounds in one `{"rounds": [...]}` request to /v1/fuse.
    #[arg(long, env = "VLMFUSE_MAX_BATCH_ROUNDS", required = false)]
    pub max_batch_rounds: usize,
    /// Most texts in one `{"text": [...]}` request to /v1/label (they are labelled as one
    /// round, in one call, so this bounds one request's hold on the labeler).
    #[arg(long, env = "VLMFUSE_MAX_LABEL_TEXTS", required = false)]
    pub max_label_texts: usize,
    /// Seconds an idempotency key (`Idempotency-Key` or `request_id` on /v1/fuse and
    /// /v1/infer) is remembered: a retry within it gets the stored answer; later the key is
    /// forgotten (pruned from the database).
    #[arg(long, env = "VLMFUSE_IDEMPOTENCY_TTL_S", required = false)]
    pub idempotency_ttl_s: f64,
    /// Longest context vector a `/v1/fuse` round may carry (422 above). The first round fixes
    /// the dimension for good and every round is kept in the bank, so an unbounded one lets a
    /// single client cost memory and disk without limit.
    #[arg(long, env = "VLMFUSE_MAX_CONTEXT_DIM", required = false)]
    pub max_context_dim: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_body_bytes: 8 * 1024 * 1024,
            concurrency_limit: 512,
            request_timeout_s: 30.0,
            max_batch_rounds: 1024,
            max_label_texts: 64,
            idempotency_ttl_s: 86_400.0,
            max_context_dim: 4096,
        }
    }
}
