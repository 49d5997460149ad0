//! The service layer: what `vlmfuse serve` does, with no HTTP in it. It owns the engine (in
//! memory, behind an `RwLock`), the single writer thread that is the only code changing it, and
//! the clip pipeline; it takes requests already read off the wire and answers with the shapes of
//! [`crate::wire`] or a [`ServiceError`]. The HTTP layer (`crate::http`) reads requests, calls
//! these methods and maps errors to statuses.
//!
//! Reads (`fuse` inference, `state`) take the engine's read lock (tokio's: an async path waits
//! for it without holding a runtime thread); the writer ([`writer`]) is the only code that takes
//! the write lock. The database (vlmfuse-store) is the truth the engine is
//! rebuilt from on start.

pub mod annotate;
mod browse;
pub mod dashboard;
pub mod detect;
mod error;
mod fuse;
mod infer;
mod label;
pub mod pipeline;
mod readiness;
pub mod replica;
mod review;
mod thumbs;
pub mod writer;

pub use browse::{EdgeCounts, MAX_PAGE};
pub use error::ServiceError;
pub use fuse::{fingerprint, idempotency_key, Answer, FeedbackGiven, IdemRequest};

/// Longest idempotency key (`Idempotency-Key` or `request_id`).
pub fn fuse_max_key_len() -> usize {
    fuse::MAX_KEY_LEN
}
pub(crate) use infer::stage;
pub use infer::Upload;
pub use label::Labelled;
pub use pipeline::Pipeline;
pub use readiness::Readiness;
pub use review::{DEFAULT_WINDOW as REVIEW_DEFAULT_WINDOW, MAX_LIMIT as REVIEW_MAX_LIMIT};

use crate::config::Config;
use crate::telemetry::Metrics;
use crate::wire::{state_out, OntologyOut, StateOut};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use vlmfuse_fusion::Engine;
use vlmfuse_store::{Identity, Store};
use writer::{Cmd, Shared};

/// Hooks that only tests set: they let a test make a request slow deterministically (to fill the
/// concurrency limit, to pass a timeout) without a knob in the production configuration. Behind
/// the `test-hooks` feature, which only this crate's tests enable; without it the hooks are a
/// zero-sized type whose delays are always zero, and [`Service`] has no way to set them.
#[cfg(feature = "test-hooks")]
#[derive(Default)]
pub struct TestHooks {
    fuse_delay_ms: AtomicU64,
    fuse_hold_ms: AtomicU64,
    after_queue_ms: AtomicU64,
}

#[cfg(feature = "test-hooks")]
impl TestHooks {
    /// Every `/v1/fuse` sleeps this long before it starts.
    pub fn set_fuse_delay(&self, d: Duration) {
        self.fuse_delay_ms
            .store(d.as_millis() as u64, Ordering::Relaxed);
    }

    fn fuse_delay(&self) -> Duration {
        Duration::from_millis(self.fuse_delay_ms.load(Ordering::Relaxed))
    }

    /// Every `/v1/fuse` holds the engine's read lock this much longer (a long batch).
    pub fn set_fuse_hold(&self, d: Duration) {
        self.fuse_hold_ms
            .store(d.as_millis() as u64, Ordering::Relaxed);
    }

    /// Every round-storing request waits this long after its rounds are queued for the writer
    /// (so that a request timeout lands after the commit was decided).
    pub fn set_after_queue_delay(&self, d: Duration) {
        self.after_queue_ms
            .store(d.as_millis() as u64, Ordering::Relaxed);
    }

    fn after_queue_delay(&self) -> Duration {
        Duration::from_millis(self.after_queue_ms.load(Ordering::Relaxed))
    }

    fn fuse_hold(&self) -> Duration {
        Duration::from_millis(self.fuse_hold_ms.load(Ordering::Relaxed))
    }
}

/// Without `test-hooks`: no state, every delay zero (the checks compile away).
#[cfg(not(feature = "test-hooks"))]
#[derive(Default)]
struct TestHooks;

#[cfg(not(feature = "test-hooks"))]
impl TestHooks {
    fn fuse_delay(&self) -> Duration {
        Duration::ZERO
    }

    fn after_queue_delay(&self) -> Duration {
        Duration::ZERO
    }

    fn fuse_hold(&self) -> Duration {
        Duration::ZERO
    }
}

pub struct Service {
    shared: Arc<Shared>,
    tx: mpsc::Sender<Cmd>,
    cfg: Arc<Config>,
    pipeline: Arc<Pipeline>,
    metrics: Metrics,
    hooks: TestHooks,
    health: Arc<readiness::Health>,
    /// The operator page's read-only connection to the store, opened on first use.
    reader: Arc<Mutex<Option<Store>>>,
    /// Aborts the reporter probes when the service is dropped.
    _probes: Option<readiness::ProbeTask>,
    /// Which store this replica writes, and on PostgreSQL the lease it holds (for `/readyz`).
    store_info: StoreInfo,
    /// On PostgreSQL, when another replica held the writer lease at the start: the follower
    /// state (`replica`); it forwards writes until this replica takes the lease.
    follower: Option<Arc<replica::Follower>>,
}

/// What `/readyz` says of the store beside its health.
#[derive(Debug, Clone)]
pub struct StoreInfo {
    /// `sqlite` or `postgres`.
    pub backend: &'static str,
    /// The SQLite file, or the PostgreSQL URL without its password.
    pub location: String,
    pub lease: Option<vlmfuse_store::pg::LeaseHeld>,
}

/// The prefix of every spooled upload; only such files are ever removed from the spool.
pub const SPOOL_PREFIX: &str = "vlmfuse-clip-";

/// This process's prefix for spooled uploads: `vlmfuse-clip-<pid>-`. The pid tells the start-up
/// cleaning of another instance that shares `media.temp_dir` whether the upload's owner still
/// runs, so it never deletes an upload in flight.
pub fn spool_prefix() -> String {
    format!("{SPOOL_PREFIX}{}-", std::process::id())
}

/// Whether process `pid` exists (signal 0 probes without sending anything; EPERM means it
/// exists under another user).
fn process_alive(pid: i32) -> bool {
    // SAFETY: kill with signal 0 has no effect besides the permission/existence check.
    let r = unsafe { libc::kill(pid, 0) };
    r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// Creates the spool directory and removes the uploads a killed run left in it (a clean
/// shutdown leaves none: each upload is deleted when its request ends). An upload whose name
/// carries the pid of a process that still runs belongs to another instance sharing the
/// directory and is left alone; names without a pid (written by older versions) are stale.
/// Returns how many were removed.
fn clear_spool(dir: &std::path::Path) -> std::io::Result<usize> {
    std::fs::create_dir_all(dir)?;
    let me = std::process::id() as i32;
    let mut removed = 0;
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(rest) = name.strip_prefix(SPOOL_PREFIX) else {
            continue;
        };
        let owner = rest
            .split_once('-')
            .and_then(|(pid, _)| pid.parse::<i32>().ok())
            .filter(|&p| p > 0);
        if owner.is_some_and(|p| p != me && process_alive(p)) {
            continue;
        }
        if entry.file_type()?.is_file() {
            std::fs::remove_file(entry.path())?;
            removed += 1;
        }
    }
    Ok(removed)
}

/// How long a starting service waits for another holder of the data directory's lock.
const STORE_LOCK_WAIT: Duration = Duration::from_secs(5);

impl Service {
    /// Opens the store, rebuilds the engine from it, loads the clip pipeline and starts the
    /// writer. The writer thread ends once every handle to the service is dropped, after
    /// committing what is queued; join the returned handle to wait for that.
    pub async fn start(
        cfg: Arc<Config>,
        metrics: Metrics,
    ) -> anyhow::Result<(Service, JoinHandle<()>)> {
        use anyhow::Context;
        let start = Instant::now();
        let engine = Engine::new(
            cfg.fusion.clone(),
            cfg.ontology.clone(),
            cfg.reporters.clone(),
        )
        .context("fusion engine")?;
        // The data directory's lock: a second server on it is refused here, naming the
        // holder's pid, instead of colliding on round numbers later. The wait covers a restart
        // that overlaps the previous process's last commit.
        //
        // On PostgreSQL this also takes the writer lease, waiting as `[store]` says (a standby:
        // until the writer's session ends); a replica that does not get it follows the one that
        // holds it (`replica`). Every store call of the start runs off the async threads: a standby waits here for
        // the lease, and the PostgreSQL client blocks on a runtime of its own.
        let cfg_b = cfg.clone();
        let (store, engine, loaded, dash, following) = tokio::task::spawn_blocking(move || {
            let cfg = cfg_b;
            let mut engine = engine;
            let location = cfg.store.location(&cfg.server.data_dir);
            let (mut store, following) = match Store::open_at(&location, STORE_LOCK_WAIT) {
                Ok(s) => (s, false),
                Err(vlmfuse_store::StoreError::Leased { holder, .. }) if !cfg.store.standby => {
                    tracing::info!(writer = %holder, "another replica holds the writer lease: following it");
                    (Store::open_read_only_at(&location)?, true)
                }
                Err(e) => return Err(e.into()),
            };
            let spool = cfg.spool_dir();
            let stale = clear_spool(&spool)
                .with_context(|| format!("upload spool directory {}", spool.display()))?;
            if stale > 0 {
                tracing::info!(files = stale, dir = %spool.display(), "removed uploads a previous run left behind");
            }
            store.check_identity(&Identity {
                reporters: cfg.reporters.clone(),
                labels: cfg.ontology.ids().map(str::to_string).collect(),
            })?;
            let loaded = store
                .load_engine(&mut engine)
                .with_context(|| format!("rebuilding the engine from {}", store.path().display()))?;
            if let Some(from) = &loaded.migrated_from {
                tracing::warn!(
                    from = %from,
                    to = engine.method().name(),
                    "the data directory was written under another fusion method: every round was \
                     inferred again and every credit recomputed under the configured one"
                );
            }
            if let Some(u) = &loaded.snapshot {
                tracing::info!(
                    path = %u.path.display(),
                    rounds = u.anchor.rounds,
                    labelled = u.anchor.labelled,
                    tail_rounds = u.tail_rounds,
                    tail_feedback = u.tail_feedback,
                    "engine loaded from a snapshot; replayed only the events after it"
                );
            }
            tracing::info!(
                method = engine.method().name(),
                rounds = loaded.rounds,
                labelled = loaded.labelled,
                secs = start.elapsed().as_secs_f64(),
                db = %store.path().display(),
                "state rebuilt from the database"
            );
            let mut dash = dashboard::Dashboard::new(
                cfg.ui.clone(),
                engine.reporters().len(),
                engine.ontology().labels().len(),
            );
            // The page's numbers are an aid: a store that cannot give them leaves the page empty
            // until new events arrive, never stops the start.
            let seed_start = Instant::now();
            if let Err(e) = dash.seed(&store, loaded.labelled) {
                tracing::warn!(error = %e, "operator page: could not read the latest events");
            }
            tracing::debug!(
                secs = seed_start.elapsed().as_secs_f64(),
                "operator page seeded from the store"
            );
            anyhow::Ok((store, engine, loaded, dash, following))
        })
        .await
        .context("opening the store")??;
        metrics.scope(|| writer::publish_gauges(&engine));
        let shared = Arc::new(Shared {
            reporter_names: engine.reporters().to_vec(),
            engine: tokio::sync::RwLock::new(engine),
            rounds: AtomicU64::new(loaded.next_seq),
            broken: AtomicBool::new(false),
            broken_reason: Mutex::new(None),
            dashboard: Mutex::new(dash),
            address: std::sync::OnceLock::new(),
        });

        let start = Instant::now();
        let pipeline = Pipeline::load(&cfg).await;
        tracing::info!(
            embedder = pipeline.embedder.is_some(),
            reporters = pipeline.reporters.len(),
            labeler = %pipeline.labeler_name,
            secs = start.elapsed().as_secs_f64(),
            "clip pipeline loaded"
        );
        // A configured embedder's output dimension is the context dimension: fixed now, so a
        // `/v1/fuse` round of another dimension is refused (422) rather than fixing it for
        // good, and a data directory written under another dimension is refused here. Without
        // an embedder the first stored round fixes it.
        if let Some(emb) = &pipeline.embedder {
            let d = emb.dim();
            let mut eng = shared.engine.write().await;
            match eng.dim() {
                Some(stored) if stored != d => anyhow::bail!(
                    "the data directory {} holds rounds with {stored}-dimensional contexts, but \
                     the configured embedder ({}) produces {d}-dimensional ones; use another \
                     data directory (server.data_dir) or the embedder the rounds were written with",
                    cfg.server.data_dir.display(),
                    cfg.embedder
                        .as_ref()
                        .map(|e| e.weights.describe())
                        .unwrap_or_default()
                ),
                Some(_) => {}
                None => eng
                    .fix_dim(d)
                    .context("fixing the context dimension to the embedder's")?,
            }
        }
        let store_info = StoreInfo {
            backend: if store.is_postgres() {
                "postgres"
            } else {
                "sqlite"
            },
            location: store.path().display().to_string(),
            lease: store.lease().cloned(),
        };
        if let Some(l) = &store_info.lease {
            metrics.scope(|| {
                metrics::gauge!("vlmfuse_store_lease_held").set(1.0);
                metrics::gauge!("vlmfuse_store_lease_since_seconds")
                    .set(l.since_ms as f64 / 1000.0);
            });
        }
        let snapshots = writer::SnapshotPolicy {
            every: cfg.server.snapshot_every,
            loaded: loaded
                .snapshot
                .as_ref()
                .map_or((0, 0), |u| (u.anchor.rounds, u.anchor.labelled)),
            interval: (cfg.server.snapshot_interval_s > 0.0)
                .then(|| Duration::from_secs_f64(cfg.server.snapshot_interval_s)),
            keep: cfg.server.snapshot_keep,
        };
        let key_ttl = Duration::from_secs_f64(cfg.limits.idempotency_ttl_s);
        let (tx, writer, follower) = if following {
            let follower = Arc::new(replica::Follower::new(
                vlmfuse_store::Position {
                    rounds: loaded.next_seq,
                    labelled: loaded.labelled,
                },
                cfg.server.api_key.clone().filter(|k| !k.is_empty()),
                Duration::from_secs_f64(cfg.limits.request_timeout_s),
            ));
            let (tx, rx) = std::sync::mpsc::channel();
            let handle = replica::spawn(
                store,
                follower.clone(),
                shared.clone(),
                rx,
                replica::Promotion {
                    location: cfg.store.location(&cfg.server.data_dir),
                    metrics: metrics.clone(),
                    key_ttl,
                    snapshots,
                },
            )
            .context("follow thread")?;
            (tx, handle, Some(follower))
        } else {
            let (tx, handle) =
                writer::spawn(store, shared.clone(), metrics.clone(), key_ttl, snapshots)
                    .context("writer thread")?;
            (tx, handle, None)
        };
        let pipeline = Arc::new(pipeline);
        let (health, probes) = readiness::start_probes(
            &pipeline,
            Duration::from_secs_f64(cfg.server.probe_interval_s),
        );
        Ok((
            Service {
                shared,
                tx,
                cfg,
                pipeline,
                metrics,
                hooks: TestHooks::default(),
                health,
                reader: Arc::new(Mutex::new(None)),
                _probes: probes,
                store_info,
                follower,
            },
            writer,
        ))
    }

    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// The follower state while this replica forwards its writes (`None` once it writes).
    pub(crate) fn following(&self) -> Option<&Arc<replica::Follower>> {
        self.follower.as_ref().filter(|f| f.following())
    }

    /// On PostgreSQL, at each scrape of `/metrics`: `vlmfuse_replica_role{role}` (1 for this
    /// replica's), `vlmfuse_replica_lag_seconds` (a follower: since its engine last read the
    /// committed events; 0 on the writer) and `vlmfuse_store_lease_age_seconds` (the writer).
    pub fn publish_replica_gauges(&self) {
        if self.store_info.backend != "postgres" {
            return;
        }
        let following = self.following();
        let role = if following.is_some() {
            "follower"
        } else {
            "writer"
        };
        let lag = following.map_or(0.0, |f| f.synced_age_s());
        self.metrics.scope(|| {
            for r in ["writer", "follower"] {
                metrics::gauge!("vlmfuse_replica_role", "role" => r)
                    .set(f64::from(u8::from(r == role)));
            }
            metrics::gauge!("vlmfuse_replica_lag_seconds").set(lag);
            if let Some(l) = &self.store_info.lease {
                metrics::gauge!("vlmfuse_store_lease_age_seconds")
                    .set((vlmfuse_store::timestamp_ms() - l.since_ms).max(0) as f64 / 1000.0);
            }
        });
    }

    /// Where this service takes requests, once it listens: a writer on PostgreSQL names it
    /// in the lease row (`[store] advertise_url` overrides it).
    pub fn set_address(&self, listening: std::net::SocketAddr) {
        let url = match &self.cfg.store.advertise_url {
            Some(u) if !u.is_empty() => u.clone(),
            // A wildcard address is no address to send to: the host's name instead.
            _ if listening.ip().is_unspecified() => {
                let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
                    .map(|h| h.trim().to_string())
                    .unwrap_or_else(|_| "localhost".into());
                format!("http://{host}:{}", listening.port())
            }
            _ => format!("http://{listening}"),
        };
        let _ = self.shared.address.set(url);
    }

    /// Where the engine stands in the stored history (`rounds`, `labelled`): what a writer's
    /// answer to a write says in `x-vlmfuse-position`, and what a follower waits for.
    pub async fn position(&self) -> vlmfuse_store::Position {
        let labelled = self.shared.engine.read().await.labelled();
        vlmfuse_store::Position {
            rounds: self.shared.rounds.load(Ordering::SeqCst),
            labelled,
        }
    }

    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// Test-only hooks (see [`TestHooks`]; feature `test-hooks`).
    #[cfg(feature = "test-hooks")]
    pub fn test_hooks(&self) -> &TestHooks {
        &self.hooks
    }

    fn send(&self, cmd: Cmd) -> Result<(), ServiceError> {
        if self.shared.broken.load(Ordering::SeqCst) {
            return Err(ServiceError::NotReady {
                message: "the service refuses writes; see /readyz".into(),
                not_ready: self.not_ready(),
            });
        }
        self.tx.send(cmd).map_err(|_| ServiceError::NotReady {
            message: "the writer has stopped".into(),
            not_ready: vec!["store: writer stopped".into()],
        })
    }

    /// `GET /v1/state`.
    pub async fn state(&self) -> StateOut {
        let eng = self.shared.engine.read().await;
        let mut out = state_out(&eng, self.shared.rounds.load(Ordering::SeqCst));
        out.replica = match &self.follower {
            Some(f) if f.following() => Some(crate::wire::ReplicaOut {
                role: "follower",
                writer: f.writer().map(|(name, _)| name),
                synced_age_s: f.synced_age_s(),
            }),
            Some(_) => Some(crate::wire::ReplicaOut {
                role: "writer",
                writer: None,
                synced_age_s: 0.0,
            }),
            None if self.store_info.backend == "postgres" => Some(crate::wire::ReplicaOut {
                role: "writer",
                writer: None,
                synced_age_s: 0.0,
            }),
            None => None,
        };
        out
    }

    /// `GET /v1/ontology`.
    pub async fn ontology(&self) -> OntologyOut {
        let eng = self.shared.engine.read().await;
        OntologyOut {
            labels: eng.ontology().labels().to_vec(),
        }
    }
}
