//! Replicas on PostgreSQL (docs/ARCHITECTURE.md, "Replicas").
//!
//! A replica that does not hold the writer lease is a *follower*. It decodes, embeds, asks the
//! reporters and labels on its own (`/v1/infer`'s CPU work is what needs many machines), but it
//! never writes: the fuse step and feedback go to the writer's own `/v1/fuse` and `/v1/feedback`
//! (the address the writer put in the lease row, the service's bearer token), so every event is
//! ordered, inferred and committed by the one writer, exactly as on a single server, and the
//! writer's answer is passed on as it came. Reads (`/v1/state`, the operator page) are served from
//! the follower's own copy of the engine, which a thread keeps current from the database every
//! [`FOLLOW_EVERY`] by replaying the committed events as a restart does (bit for bit the writer's
//! engine); `/v1/state` says how far behind it is. After a forwarded write the follower waits
//! (at most [`CATCH_UP_WAIT`]) until its copy holds that write, so a client that reads back what
//! it wrote through the same replica sees it.
//!
//! The same thread asks for the lease every [`LEASE_EVERY`]; when the writer's session ends
//! (failover), the first follower to get it catches up to the last committed event and becomes
//! the writer in place: its queue of commands, its engine and its port stay, so a load balancer
//! notices nothing but a short pause.

use super::writer::{self, Cmd, Shared, SnapshotPolicy};
use super::ServiceError;
use crate::telemetry::Metrics;
use serde_json::Value;
use std::sync::atomic::{AtomicBool, AtomicI64, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::watch;
use vlmfuse_store::{Location, Position, Store, StoreError};

/// How often a follower reads the events committed since it last looked.
pub const FOLLOW_EVERY: Duration = Duration::from_millis(50);
/// How often a follower asks for the writer lease.
pub const LEASE_EVERY: Duration = Duration::from_millis(500);
/// How long an answer to a forwarded write waits for this replica's engine to hold it.
pub const CATCH_UP_WAIT: Duration = Duration::from_secs(2);

/// The response header in which a writer says where its engine stands after a write
/// (`rounds,labelled`), for the follower that forwarded it.
pub const POSITION_HEADER: &str = "x-vlmfuse-position";

/// A follower's view of the writer and of its own engine.
pub struct Follower {
    /// The writer's address (`http://host:port`) and name, from the lease row.
    writer: Mutex<Option<(String, String)>>,
    /// Where this replica's engine stands; forwarded writes wait on it.
    position: watch::Sender<Position>,
    /// When the engine last caught up (ms since the epoch).
    synced_ms: AtomicI64,
    /// Set once this replica holds the lease and writes itself.
    promoted: AtomicBool,
    client: reqwest::Client,
    api_key: Option<String>,
    /// Set by a forwarded write the writer acknowledged: the follow thread reads the database at
    /// once instead of at its next period, so the write's answer does not wait for a poll.
    wake: (std::sync::Mutex<bool>, std::sync::Condvar),
}

/// What the writer answered to a forwarded request.
pub struct Forwarded {
    pub body: Value,
    /// `idempotent-replayed: true` (a `/v1/fuse` answered from its key).
    pub replayed: bool,
    /// `x-vlmfuse-repeated: true` (a feedback that taught nothing new).
    pub repeated: bool,
}

impl Follower {
    pub fn new(at: Position, api_key: Option<String>, timeout: Duration) -> Self {
        Follower {
            writer: Mutex::new(None),
            position: watch::Sender::new(at),
            synced_ms: AtomicI64::new(vlmfuse_store::timestamp_ms()),
            promoted: AtomicBool::new(false),
            client: reqwest::Client::builder()
                .no_proxy()
                .timeout(timeout)
                .build()
                .unwrap_or_default(),
            api_key,
            wake: (std::sync::Mutex::new(false), std::sync::Condvar::new()),
        }
    }

    /// Whether this replica still forwards (it has not taken the lease).
    pub fn following(&self) -> bool {
        !self.promoted.load(Ordering::SeqCst)
    }

    pub fn position(&self) -> Position {
        *self.position.borrow()
    }

    /// Seconds since the engine last caught up with the database.
    pub fn synced_age_s(&self) -> f64 {
        (vlmfuse_store::timestamp_ms() - self.synced_ms.load(Ordering::SeqCst)).max(0) as f64
            / 1000.0
    }

    /// The writer's name and address, as the lease row said last.
    pub fn writer(&self) -> Option<(String, String)> {
        self.writer
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// POSTs `body` to the writer's `path`, then waits until this replica's engine holds what
    /// the writer says the write left (read-your-writes). An error answer comes back as the
    /// writer gave it ([`ServiceError::Forwarded`]).
    pub async fn forward(
        &self,
        path: &str,
        body: &Value,
        idempotency_key: Option<&str>,
    ) -> Result<Forwarded, ServiceError> {
        let not_ready = |why: String| ServiceError::NotReady {
            message: format!("this replica forwards writes to the writer, and {why}"),
            not_ready: vec![format!("store: {why}")],
        };
        let Some((name, addr)) = self.writer().filter(|(_, a)| !a.is_empty()) else {
            return Err(not_ready(
                "no writer has said where it listens yet (lease row without an address)".into(),
            ));
        };
        let mut req = self
            .client
            .post(format!("{}{path}", addr.trim_end_matches('/')))
            .json(body);
        if let Some(k) = &self.api_key {
            req = req.bearer_auth(k);
        }
        if let Some(k) = idempotency_key {
            req = req.header("idempotency-key", k);
        }
        let resp = req
            .send()
            .await
            .map_err(|e| not_ready(format!("the writer {name} at {addr} did not answer: {e}")))?;
        let status = resp.status().as_u16();
        let flag = |h: &str| {
            resp.headers()
                .get(h)
                .and_then(|v| v.to_str().ok())
                .is_some_and(|v| v == "true")
        };
        let (replayed, repeated) = (flag("idempotent-replayed"), flag("x-vlmfuse-repeated"));
        let position = resp
            .headers()
            .get(POSITION_HEADER)
            .and_then(|v| v.to_str().ok())
            .and_then(parse_position);
        let body: Value = resp.json().await.map_err(|e| {
            not_ready(format!(
                "the writer {name} at {addr} sent an unreadable answer: {e}"
            ))
        })?;
        if status >= 400 {
            return Err(ServiceError::Forwarded { status, body });
        }
        if let Some(p) = position.filter(|p| {
            let at = self.position();
            at.rounds < p.rounds || at.labelled < p.labelled
        }) {
            let mut rx = self.position.subscribe();
            self.wake_up();
            let caught_up = tokio::time::timeout(
                CATCH_UP_WAIT,
                rx.wait_for(|at| at.rounds >= p.rounds && at.labelled >= p.labelled),
            )
            .await;
            if caught_up.is_err() {
                tracing::warn!(
                    "this replica did not see its forwarded write within {CATCH_UP_WAIT:?}; \
                     answering anyway (reads here may lag)"
                );
            }
        }
        Ok(Forwarded {
            body,
            replayed,
            repeated,
        })
    }
}

impl Follower {
    fn wake_up(&self) {
        let (flag, cv) = &self.wake;
        *flag.lock().unwrap_or_else(|e| e.into_inner()) = true;
        cv.notify_one();
    }

    /// Waits until woken or `period` passed.
    fn sleep(&self, period: Duration) {
        let (flag, cv) = &self.wake;
        let guard = flag.lock().unwrap_or_else(|e| e.into_inner());
        let (mut guard, _) = cv
            .wait_timeout_while(guard, period, |woken| !*woken)
            .unwrap_or_else(|e| e.into_inner());
        *guard = false;
    }
}

/// `rounds,labelled`.
pub fn parse_position(s: &str) -> Option<Position> {
    let (r, l) = s.split_once(',')?;
    Some(Position {
        rounds: r.trim().parse().ok()?,
        labelled: l.trim().parse().ok()?,
    })
}

/// What the follow thread needs to become the writer.
pub struct Promotion {
    pub location: Location,
    pub metrics: Metrics,
    pub key_ttl: Duration,
    pub snapshots: SnapshotPolicy,
}

/// Starts the follow thread: it keeps the engine current from `reader`, watches the lease row,
/// asks for the lease, and once it holds it runs the writer loop on `rx` (so the returned handle
/// is the writer's, as [`writer::spawn`]'s is).
pub fn spawn(
    reader: Store,
    follower: Arc<Follower>,
    shared: Arc<Shared>,
    rx: mpsc::Receiver<Cmd>,
    promotion: Promotion,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    std::thread::Builder::new()
        .name("vlmfuse-follow".into())
        .spawn(move || {
            let metrics = promotion.metrics.clone();
            metrics.scope(|| follow(reader, follower, shared, rx, promotion))
        })
}

fn follow(
    reader: Store,
    follower: Arc<Follower>,
    shared: Arc<Shared>,
    rx: mpsc::Receiver<Cmd>,
    promotion: Promotion,
) {
    let mut reader = Some(reader);
    // The lease row at once: a write may arrive before the first period is over.
    let mut last_lease: Option<Instant> = None;
    loop {
        // Commands only come here once this replica writes (until then every write is
        // forwarded before it reaches the queue); a closed queue means the service is gone.
        follower.sleep(FOLLOW_EVERY);
        if let Err(mpsc::TryRecvError::Disconnected) = rx.try_recv() {
            return;
        }
        if reader.is_none() {
            let o = match &promotion.location {
                Location::Postgres(o) => o,
                Location::Sqlite { .. } => return,
            };
            match Store::open_read_only_at(&Location::Postgres(o.clone())) {
                Ok(r) => reader = Some(r),
                Err(e) => {
                    tracing::warn!(error = %e, "follower: cannot reopen its database session");
                    std::thread::sleep(Duration::from_secs(1));
                    continue;
                }
            }
        }
        let r = reader.as_ref().expect("opened");
        if let Err(e) = catch_up(r, &follower, &shared) {
            tracing::warn!(error = %e, "follower: cannot read new events; retrying");
            if !r.alive() {
                reader = None;
            }
            continue;
        }
        // Until the writer has said where it listens, its row is read at every pass.
        let unknown = follower.writer().is_none_or(|(_, a)| a.is_empty());
        if unknown {
            if let Ok(Some(row)) = r.lease_row() {
                *follower.writer.lock().unwrap_or_else(|e| e.into_inner()) =
                    Some((row.holder, row.address));
            }
        }
        if last_lease.is_none_or(|t| t.elapsed() >= LEASE_EVERY) {
            last_lease = Some(Instant::now());
            match r.lease_row() {
                Ok(Some(row)) => {
                    *follower.writer.lock().unwrap_or_else(|e| e.into_inner()) =
                        Some((row.holder, row.address));
                }
                Ok(None) => {}
                Err(e) => tracing::warn!(error = %e, "follower: cannot read the lease row"),
            }
            let mut location = promotion.location.clone();
            if let Location::Postgres(o) = &mut location {
                o.lease_wait = Duration::ZERO;
            }
            match Store::open_at(&location, Duration::ZERO) {
                Ok(store) => {
                    drop(reader.take());
                    promote(store, follower, shared, rx, promotion);
                    return;
                }
                Err(StoreError::Leased { .. }) => {}
                Err(e) => {
                    tracing::warn!(error = %e, "follower: asking for the writer lease failed")
                }
            }
        }
    }
}

/// Applies the events committed since the engine's position.
fn catch_up(reader: &Store, follower: &Follower, shared: &Shared) -> Result<(), StoreError> {
    let at = follower.position();
    let next = {
        let mut eng = shared.engine.blocking_write();
        reader.follow(&mut eng, at)?
    };
    shared.rounds.store(next.rounds, Ordering::SeqCst);
    follower
        .synced_ms
        .store(vlmfuse_store::timestamp_ms(), Ordering::SeqCst);
    if next != at {
        follower.position.send_replace(next);
        let eng = shared.engine.blocking_read();
        writer::publish_gauges(&eng);
    }
    Ok(())
}

/// This replica holds the lease: the events the old writer committed last, then the writer loop.
fn promote(
    store: Store,
    follower: Arc<Follower>,
    shared: Arc<Shared>,
    rx: mpsc::Receiver<Cmd>,
    promotion: Promotion,
) {
    let t = Instant::now();
    if let Err(e) = catch_up(&store, &follower, &shared) {
        shared.mark_broken(format!(
            "took the writer lease but could not read the events before it: {e}"
        ));
        return;
    }
    follower.promoted.store(true, Ordering::SeqCst);
    let at = follower.position();
    tracing::info!(
        rounds = at.rounds,
        labelled = at.labelled,
        secs = t.elapsed().as_secs_f64(),
        "took the writer lease: this replica writes now"
    );
    metrics::gauge!("vlmfuse_store_lease_held").set(1.0);
    let mut snapshots = promotion.snapshots;
    snapshots.loaded = (at.rounds, at.labelled);
    writer::serve_writes(
        store,
        shared,
        promotion.metrics,
        promotion.key_ttl,
        snapshots,
        rx,
    );
}
