//! The single writer: one OS thread owns the SQLite write connection and is the only code that
//! changes the engine. Commands arrive on a channel in arrival order, so feedback is applied one
//! at a time in that order and the service's results equal a sequential replay.
//!
//! Rounds from `/v1/fuse` that are queued together are stored in one transaction (group commit):
//! with `synchronous=FULL` every commit is an fsync, and sharing it is what lets fuse throughput
//! exceed the disk's sync rate. Each feedback commits on its own, because its credit depends on the
//! reputations that the previous feedback left.
//!
//! A feedback holds the engine's write lock only for `apply` (microseconds); the credit is computed
//! under a read lock and the commit under no lock, so fuse requests keep running meanwhile.

use super::ServiceError;
use crate::telemetry::Metrics;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::Instant;
use tokio::sync::oneshot;
use tokio::sync::RwLock;
use vlmfuse_fusion::{Engine, FusionError, LabelledRound, Round};
use vlmfuse_store::{parse_round_id, IdempotencyRecord, NewRound, Store, StoredFeedback};

/// Most commands taken off the queue into one group.
const MAX_GROUP: usize = 256;

pub enum Cmd {
    /// Store rounds; replies with the first `seq` (the rest follow consecutively), or, for a
    /// request whose idempotency key is already stored, with the stored answer.
    Insert {
        rounds: Vec<NewRound>,
        idem: Option<Idem>,
        reply: oneshot::Sender<Result<Inserted, ServiceError>>,
    },
    /// The stored record of an idempotency key (not expired), if any.
    LookupKey {
        key: String,
        reply: oneshot::Sender<Result<Option<IdempotencyRecord>, ServiceError>>,
    },
    /// Label a round; `truth` is already validated against the ontology (0/1 per label it
    /// gives, [`vlmfuse_fusion::UNKNOWN`] for the others), `source` checked.
    Feedback {
        round_id: String,
        truth: Vec<u8>,
        source: String,
        /// A parsed signal track to derive `truth` from (it is empty then), with `[annotate]`:
        /// derived here, where the round's clip (its duration) is known.
        derive: Option<Derive>,
        reply: oneshot::Sender<Result<FeedbackDone, ServiceError>>,
    },
}

/// A signal track and the `[annotate]` section it is read under.
pub type Derive = Box<(vlmfuse_annotate::Track, crate::config::AnnotateSection)>;

/// The idempotency key of an insert, and how to write the answer it is stored with.
pub struct Idem {
    pub key: String,
    pub route: &'static str,
    pub fingerprint: String,
    /// The request's answer, given the first `seq` of its rounds: stored with the key in the
    /// rounds' own transaction, so even a request that timed out after it was queued leaves
    /// its answer for the retry.
    pub render: Box<dyn FnOnce(u64) -> serde_json::Value + Send>,
}

/// What an insert did.
pub enum Inserted {
    /// Stored from this `seq` on; `body` is the rendered answer of a keyed request.
    Fresh {
        first: u64,
        body: Option<serde_json::Value>,
    },
    /// The key was stored already, for the same request: its answer, and nothing stored.
    Replay(serde_json::Value),
}

/// The error for a key reused on another request.
pub fn key_reused(key: &str, route: &str, stored_route: &str) -> ServiceError {
    let what = if route == stored_route {
        "a request with a different body".to_string()
    } else {
        format!("a request to {stored_route}")
    };
    ServiceError::IdempotencyKeyReused(format!(
        "idempotency key {key:?} was already used for {what}; a retry must repeat the request \
         exactly, and a new request needs a new key"
    ))
}

/// An acknowledged feedback (committed), new or repeated.
pub struct FeedbackDone {
    pub round_id: String,
    /// The event this feedback stored, or (a repeat) the round's latest one.
    pub feedback: StoredFeedback,
    /// The round's coalition (reporter indices).
    pub coalition: Vec<usize>,
    /// True when this feedback taught nothing new: every label it gives was already known
    /// with that value (or a person's label stands against it). Nothing was stored.
    pub repeated: bool,
    /// The round's truth after this feedback, every event merged: 0/1, or `UNKNOWN`.
    pub merged: Vec<u8>,
    /// Per label, who gave the truth in force (`None`: unknown).
    pub sources: Vec<Option<String>>,
    /// What this feedback taught: 0/1 where it gave a new label or overrode one.
    pub learned: Vec<u8>,
    /// Labels this feedback gave that were not taken, with why (a person's label stands).
    pub ignored: Vec<(usize, String)>,
    /// The annotation the labels were derived from (a `signals` feedback).
    pub derived: Option<vlmfuse_annotate::Annotation>,
}

/// The source whose labels override every other's.
pub const HUMAN: &str = "human";

/// The round's truth as its stored events leave it: per label the value and who gave it, the
/// later event winning (an override comes after what it overrides).
pub(crate) fn merged_truth(l: usize, events: &[StoredFeedback]) -> (Vec<u8>, Vec<Option<String>>) {
    let mut y = vec![vlmfuse_fusion::UNKNOWN; l];
    let mut src: Vec<Option<String>> = vec![None; l];
    for ev in events {
        for (k, &v) in ev.truth.iter().enumerate().take(l) {
            if v <= 1 {
                y[k] = v;
                src[k] = Some(ev.source.clone());
            }
        }
    }
    (y, src)
}

/// What a feedback teaches (0/1 per label it learns, `UNKNOWN` elsewhere) and the labels it
/// gave that were not taken, with why.
pub type Merged = (Vec<u8>, Vec<(usize, String)>);

/// What a new feedback teaches against the round's merged truth (docs/METHOD.md, "Partial
/// feedback"): a label not known yet is learned; the same value again is nothing new; another
/// value is learned when a person overrides a derived source, ignored when a derived source
/// contradicts a person, and refused (409, nothing stored) between two sources of the same rank.
pub fn merge_feedback(
    ontology: &vlmfuse_fusion::Ontology,
    merged: &[u8],
    sources: &[Option<String>],
    truth: &[u8],
    source: &str,
) -> Result<Merged, ServiceError> {
    let mut learned = vec![vlmfuse_fusion::UNKNOWN; truth.len()];
    let mut ignored = Vec::new();
    let mut conflicts = Vec::new();
    let name = |k: usize| ontology.labels()[k].id.clone();
    let said = |v: u8| if v == 1 { "present" } else { "absent" };
    for (k, &v) in truth.iter().enumerate() {
        if v > 1 {
            continue;
        }
        let cur = merged[k];
        if cur > 1 {
            learned[k] = v;
            continue;
        }
        if cur == v {
            continue;
        }
        let by = sources[k].as_deref().unwrap_or(HUMAN);
        match (source == HUMAN, by == HUMAN) {
            (true, false) => learned[k] = v,
            (false, true) => ignored.push((
                k,
                format!("a person said {:?} is {}; that stands", name(k), said(cur)),
            )),
            _ => conflicts.push(format!("{:?} ({} by {by:?})", name(k), said(cur))),
        }
    }
    if !conflicts.is_empty() {
        return Err(ServiceError::Conflict(format!(
            "this feedback ({source:?}) contradicts what the round already holds: {}; a label \
             is final once given, except that a person's (source \"human\") overrides a \
             derived one",
            conflicts.join(", ")
        )));
    }
    Ok((learned, ignored))
}

/// What the handlers share with the writer.
pub struct Shared {
    /// tokio's lock, not std's: a batch fuse holds the read side for its whole inference and a
    /// feedback then waits for the write side; with std's (writer-preferring) lock every later
    /// `read()` blocked the runtime thread that called it, and two of them froze a 2-worker
    /// runtime, `/healthz` included. Async paths `.read().await` (the task waits, the thread
    /// does not); the writer thread and the blocking pool use `blocking_read`/`blocking_write`.
    /// It is also fair (FIFO), so a stream of fuse requests cannot starve a feedback.
    pub engine: RwLock<Engine>,
    /// Rounds stored so far (the next `seq`).
    pub rounds: AtomicU64,
    /// Set when the writer stopped or left the engine behind the database; the service then
    /// refuses writes and `/readyz` says why.
    pub broken: AtomicBool,
    pub broken_reason: Mutex<Option<String>>,
    /// The operator page's aggregates, updated here after each commit (std's lock: held for
    /// microseconds, never across an await).
    pub dashboard: Mutex<super::dashboard::Dashboard>,
    /// Reporter names in configured order (the dashboard's indices).
    pub reporter_names: Vec<String>,
    /// Where this service takes requests (`http://host:port`), once it listens: what a writer
    /// on PostgreSQL puts in the lease row for the followers.
    pub address: std::sync::OnceLock<String>,
}

impl Shared {
    /// One reporter's run on a clip: its latency (ms) or a failure, for the page and
    /// `vlmfuse_reporter_latency_seconds`.
    pub fn record_reporter(&self, name: &str, result: Result<f64, ()>) {
        if let Ok(ms) = result {
            metrics::histogram!("vlmfuse_reporter_latency_seconds", "reporter" => name.to_string())
                .record(ms / 1e3);
        }
        if let Some(i) = self.reporter_names.iter().position(|n| n == name) {
            if let Ok(mut d) = self.dashboard.lock() {
                d.on_reporter(i, result);
            }
        }
    }

    /// The rounds just committed, for the page's windows and the per-predictor and agreement
    /// metrics.
    fn dashboard_rounds(&self, rounds: &[NewRound]) {
        let Ok(mut d) = self.dashboard.lock() else {
            return;
        };
        for r in rounds {
            let decision = r.request.get("decision").and_then(|v| v.as_str());
            metrics::counter!("vlmfuse_decisions_total", "predictor" => decision.unwrap_or("unknown").to_string())
                .increment(1);
            d.on_round(&r.round, &r.inference, decision);
        }
        for (name, a) in self.reporter_names.iter().zip(d.agreement()) {
            if let Some(a) = a {
                metrics::gauge!("vlmfuse_reporter_agreement", "reporter" => name.clone()).set(a);
            }
        }
    }

    /// Why writes are refused (empty while they are not).
    pub fn broken_reason(&self) -> String {
        self.broken_reason
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
            .unwrap_or_default()
    }

    pub fn mark_broken(&self, why: String) {
        tracing::error!("writer broken: {why}");
        *self.broken_reason.lock().unwrap_or_else(|e| e.into_inner()) = Some(why);
        self.broken.store(true, Ordering::SeqCst);
    }
}

/// Publishes the engine's gauges (reputations, labelled rounds, threshold).
pub fn publish_gauges(engine: &Engine) {
    for (name, w) in engine.reporters().iter().zip(engine.reputations()) {
        metrics::gauge!("vlmfuse_reputation", "reporter" => name.clone()).set(*w);
    }
    metrics::gauge!("vlmfuse_labelled_rounds").set(engine.labelled() as f64);
    metrics::gauge!("vlmfuse_threshold").set(engine.threshold().scalar());
    if let Some((labelled, unlabelled)) = engine.pool_sizes() {
        metrics::gauge!("vlmfuse_pool_entries", "kind" => "labelled").set(labelled as f64);
        metrics::gauge!("vlmfuse_pool_entries", "kind" => "unlabelled").set(unlabelled as f64);
    }
    // Which predictor serves (1, the others 0) and, under `adaptive`, the scores that decide it.
    let now = crate::wire::serving_predictor(engine);
    for p in vlmfuse_fusion::Predictor::ALL {
        metrics::gauge!("vlmfuse_serving", "predictor" => p.name())
            .set(f64::from(u8::from(p.name() == now)));
    }
    for s in engine.candidate_scores().unwrap_or_default() {
        let p = s.predictor.name();
        metrics::gauge!("vlmfuse_predictor_errors", "predictor" => p).set(s.errors);
        metrics::gauge!("vlmfuse_predictor_loss", "predictor" => p).set(s.loss);
        metrics::gauge!("vlmfuse_predictor_micro_f1", "predictor" => p).set(s.micro_f1);
    }
}

/// How long idempotency keys are kept, and when they were last pruned.
struct Keys {
    ttl_ms: i64,
    last_prune: Option<Instant>,
}

impl Keys {
    /// Keys created before this have expired.
    fn not_before(&self) -> i64 {
        vlmfuse_store::timestamp_ms().saturating_sub(self.ttl_ms)
    }

    /// Prunes expired keys at most every ten minutes (and at the first group).
    fn maybe_prune(&mut self, store: &mut Store) {
        if self
            .last_prune
            .is_some_and(|t| t.elapsed() < std::time::Duration::from_secs(600))
        {
            return;
        }
        self.last_prune = Some(Instant::now());
        match store.prune_idempotency(self.not_before()) {
            Ok(0) => {}
            Ok(n) => tracing::info!(keys = n, "expired idempotency keys removed"),
            Err(e) => tracing::warn!("pruning idempotency keys failed: {e}"),
        }
    }
}

/// When the writer snapshots the engine (`[server] snapshot_*`).
#[derive(Debug, Clone, Copy)]
pub struct SnapshotPolicy {
    /// Events after which a snapshot is due; 0: never by count.
    pub every: u64,
    /// `(rounds, labelled)` of the snapshot the start loaded, `(0, 0)` without one: the
    /// events replayed at the start count toward the next snapshot, so a long replay is the last.
    pub loaded: (u64, u64),
    /// Time after which newer events are snapshotted anyway; `None`: never by time.
    pub interval: Option<std::time::Duration>,
    pub keep: usize,
}

/// The writer's snapshot schedule: where it stands, and the one write that may be in flight.
struct Snapshots {
    policy: SnapshotPolicy,
    /// The service's recorder, put in force on the snapshot thread too (it is thread-local).
    metrics: Metrics,
    /// `(rounds, labelled)` of the last snapshot (or of the start: the loaded state).
    last: (u64, u64),
    last_at: Instant,
    in_flight: Option<std::thread::JoinHandle<()>>,
}

impl Snapshots {
    fn new(policy: SnapshotPolicy, metrics: Metrics) -> Self {
        Self {
            policy,
            metrics,
            last: policy.loaded,
            last_at: Instant::now(),
            in_flight: None,
        }
    }

    /// Events since the last snapshot.
    fn pending(&self, rounds: u64, labelled: u64) -> u64 {
        (rounds - self.last.0.min(rounds)) + (labelled - self.last.1.min(labelled))
    }

    /// Between groups: starts a snapshot in the background when one is due (or, with
    /// `finish`, at shutdown: writes one for any new events and waits for it).
    fn maybe(&mut self, store: &Store, shared: &Shared, finish: bool) {
        if self.in_flight.as_ref().is_some_and(|h| !h.is_finished()) && !finish {
            return;
        }
        if let Some(h) = self.in_flight.take() {
            let _ = h.join();
        }
        if shared.broken.load(Ordering::SeqCst) {
            return;
        }
        let rounds = shared.rounds.load(Ordering::SeqCst);
        let engine = shared.engine.blocking_read();
        let pending = self.pending(rounds, engine.labelled());
        let by_count = self.policy.every > 0 && pending >= self.policy.every;
        let by_time = pending > 0
            && (finish
                || self
                    .policy
                    .interval
                    .is_some_and(|t| self.last_at.elapsed() >= t));
        if !(by_count || by_time)
            || (finish && self.policy.every == 0 && self.policy.interval.is_none())
        {
            return;
        }
        let anchor = match store.anchor() {
            Ok(a) if a.rounds == rounds && a.labelled == engine.labelled() => a,
            Ok(a) => {
                tracing::warn!(
                    "snapshot skipped: the database is at {} rounds / {} feedbacks but the \
                     engine at {rounds} / {}",
                    a.rounds,
                    a.labelled,
                    engine.labelled()
                );
                return;
            }
            Err(e) => {
                tracing::warn!("snapshot skipped: {e}");
                return;
            }
        };
        // A copy under the read lock (fuse requests go on meanwhile); serialising and syncing
        // it happen on another thread, so the writer does not stall on the disk.
        let copy = engine.clone();
        drop(engine);
        self.last = (anchor.rounds, anchor.labelled);
        self.last_at = Instant::now();
        let dir = vlmfuse_store::snapshot::dir_of(store.dir());
        let keep = self.policy.keep;
        let job = move || {
            let t = Instant::now();
            match vlmfuse_store::snapshot::write(&dir, &copy, &anchor, keep) {
                Ok(w) => {
                    metrics::counter!("vlmfuse_snapshots_total").increment(1);
                    metrics::gauge!("vlmfuse_snapshot_bytes").set(w.bytes as f64);
                    tracing::info!(
                        rounds = anchor.rounds,
                        labelled = anchor.labelled,
                        bytes = w.bytes,
                        secs = t.elapsed().as_secs_f64(),
                        path = %w.path.display(),
                        "engine snapshot written"
                    );
                }
                Err(e) => {
                    metrics::counter!("vlmfuse_snapshot_failures_total").increment(1);
                    tracing::warn!("engine snapshot failed (the next restart replays more): {e}");
                }
            }
        };
        if finish {
            job();
            return;
        }
        let metrics = self.metrics.clone();
        match std::thread::Builder::new()
            .name("vlmfuse-snapshot".into())
            .spawn(move || metrics.scope(job))
        {
            Ok(h) => self.in_flight = Some(h),
            Err(e) => tracing::warn!("cannot start the snapshot thread: {e}"),
        }
    }
}

pub fn spawn(
    store: Store,
    shared: Arc<Shared>,
    metrics: Metrics,
    key_ttl: std::time::Duration,
    snapshots: SnapshotPolicy,
) -> std::io::Result<(mpsc::Sender<Cmd>, std::thread::JoinHandle<()>)> {
    let (tx, rx) = mpsc::channel::<Cmd>();
    let handle = std::thread::Builder::new()
        .name("vlmfuse-writer".into())
        .spawn(move || serve_writes(store, shared, metrics, key_ttl, snapshots, rx))?;
    Ok((tx, handle))
}

/// The writer loop on the current thread until the queue closes (every handle to the service
/// dropped), then a last snapshot. [`spawn`]'s thread runs it, and a follower's thread once it
/// takes the writer lease (`replica`).
pub fn serve_writes(
    mut store: Store,
    shared: Arc<Shared>,
    metrics: Metrics,
    key_ttl: std::time::Duration,
    snapshots: SnapshotPolicy,
    rx: mpsc::Receiver<Cmd>,
) {
    let res = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let mut keys = Keys {
            ttl_ms: i64::try_from(key_ttl.as_millis()).unwrap_or(i64::MAX),
            last_prune: None,
        };
        metrics.scope(|| {
            let mut snaps = Snapshots::new(snapshots, metrics.clone());
            run(&mut store, &shared, &mut keys, &mut snaps, rx);
            // The queue is drained: a snapshot of the final state makes the next start
            // replay nothing.
            snaps.maybe(&store, &shared, true);
        })
    }));
    match res {
        Ok(()) => tracing::info!("writer stopped: every queued write is committed"),
        Err(_) => shared.mark_broken("the writer thread panicked".into()),
    }
}

fn run(
    store: &mut Store,
    shared: &Arc<Shared>,
    keys: &mut Keys,
    snaps: &mut Snapshots,
    rx: mpsc::Receiver<Cmd>,
) {
    let mut dim = shared.engine.blocking_read().dim();
    let mut lease = Lease::new(store, shared);
    loop {
        // Wake at least once a second while idle, so a snapshot due by time is written even
        // when no request comes, and the writer lease's session sees a sign of life.
        // A writer on PostgreSQL that has not yet named its address in the lease row looks
        // again soon: followers forward nothing until it has.
        let wait = if lease.pending() { 50 } else { 1000 };
        let first = match rx.recv_timeout(std::time::Duration::from_millis(wait)) {
            Ok(c) => c,
            Err(mpsc::RecvTimeoutError::Timeout) => {
                lease.check(store, shared);
                snaps.maybe(store, shared, false);
                continue;
            }
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        };
        let mut group = vec![first];
        while group.len() < MAX_GROUP {
            match rx.try_recv() {
                Ok(c) => group.push(c),
                Err(_) => break,
            }
        }
        keys.maybe_prune(store);
        let mut inserts = Vec::new();
        for cmd in group {
            match cmd {
                Cmd::Insert {
                    rounds,
                    idem,
                    reply,
                } => inserts.push((rounds, idem, reply)),
                Cmd::LookupKey { key, reply } => {
                    // Rounds queued before this lookup are committed first: arrival order.
                    flush_inserts(store, shared, keys, &mut dim, std::mem::take(&mut inserts));
                    let _ = reply.send(
                        store
                            .idempotency(&key, keys.not_before())
                            .map_err(ServiceError::from),
                    );
                }
                Cmd::Feedback {
                    round_id,
                    truth,
                    source,
                    derive,
                    reply,
                } => {
                    // Rounds queued before this feedback are committed first: arrival order.
                    flush_inserts(store, shared, keys, &mut dim, std::mem::take(&mut inserts));
                    let res = if shared.broken.load(Ordering::SeqCst) {
                        Err(broken_error(shared))
                    } else {
                        feedback(store, shared, &round_id, truth, source, derive)
                    };
                    let _ = reply.send(res);
                }
            }
        }
        flush_inserts(store, shared, keys, &mut dim, inserts);
        lease.check(store, shared);
        snaps.maybe(store, shared, false);
    }
}

/// The PostgreSQL writer lease, seen from the writer: its session must show a sign of life at
/// least every `lease_timeout` (or the server ends it, `idle_session_timeout`), and once it has
/// ended this process may no longer write, for another replica may already be writing.
struct Lease {
    on: bool,
    last: Instant,
    advertised: bool,
    /// When the lease's session last answered (ms since the epoch), for the watchdog.
    answered_ms: Arc<std::sync::atomic::AtomicI64>,
    /// Set when the writer loop ends: the watchdog stops (a clean shutdown's last snapshot
    /// may take longer than the lease's timeout).
    done: Arc<AtomicBool>,
}

impl Drop for Lease {
    fn drop(&mut self) {
        self.done.store(true, Ordering::SeqCst);
    }
}

/// The exit status of a writer that lost its lease (EX_TEMPFAIL): its supervisor restarts it,
/// and it comes back as a follower.
pub const LEASE_LOST_EXIT: i32 = 75;

impl Lease {
    /// With a lease, also starts its watchdog: a session that stops answering (a partition that
    /// drops packets without a reset, where the client's own keepalives are answered by a
    /// middlebox) would leave this thread blocked in its round trip; past the lease's timeout
    /// without an answer the server has ended the session anyway, so the watchdog refuses
    /// writes and exits as a lost lease does.
    fn new(store: &Store, shared: &Arc<Shared>) -> Self {
        let answered_ms = Arc::new(std::sync::atomic::AtomicI64::new(
            vlmfuse_store::timestamp_ms(),
        ));
        let done = Arc::new(AtomicBool::new(false));
        if let Some(held) = store.lease() {
            let (answered, shared, stop) = (answered_ms.clone(), shared.clone(), done.clone());
            let timeout_ms = held.timeout.as_millis() as i64;
            let place = store.path().display().to_string();
            let spawned = std::thread::Builder::new()
                .name("vlmfuse-lease".into())
                .spawn(move || loop {
                    std::thread::sleep(std::time::Duration::from_millis(250));
                    if stop.load(Ordering::SeqCst) {
                        return;
                    }
                    let silent = vlmfuse_store::timestamp_ms() - answered.load(Ordering::SeqCst);
                    if silent > timeout_ms {
                        shared.mark_broken(format!(
                            "lost the writer lease on {place}: its database session has not \
                             answered for {:.1} s (past [store] lease_timeout_s, the server has \
                             ended it); exiting with status {LEASE_LOST_EXIT} to restart as a \
                             follower",
                            silent as f64 / 1000.0
                        ));
                        std::process::exit(LEASE_LOST_EXIT);
                    }
                });
            if let Err(e) = spawned {
                tracing::warn!("cannot start the lease watchdog: {e}");
            }
        }
        Lease {
            on: store.is_postgres(),
            last: Instant::now(),
            advertised: false,
            answered_ms,
            done,
        }
    }

    /// Whether the lease row does not name this writer's address yet.
    fn pending(&self) -> bool {
        self.on && !self.advertised
    }

    /// At most once a second: a round trip on the lease's session. When it fails the writes
    /// are refused and the process exits ([`LEASE_LOST_EXIT`]): nothing it acknowledged is
    /// lost (each acknowledgement followed its commit), and it cannot commit anything more.
    fn check(&mut self, store: &Store, shared: &Shared) {
        if !self.on {
            return;
        }
        // Once the service listens, the lease row says where: the followers forward there.
        if !self.advertised {
            if let Some(addr) = shared.address.get() {
                match store.advertise(addr) {
                    Ok(()) => {
                        tracing::info!(address = %addr, "the lease row names this writer's address");
                        self.advertised = true;
                    }
                    Err(e) => tracing::warn!(error = %e, "cannot write this writer's address"),
                }
            }
        }
        if self.last.elapsed() < std::time::Duration::from_secs(1) {
            return;
        }
        self.last = Instant::now();
        if store.alive() {
            self.answered_ms
                .store(vlmfuse_store::timestamp_ms(), Ordering::SeqCst);
            metrics::gauge!("vlmfuse_store_lease_held").set(1.0);
            return;
        }
        metrics::gauge!("vlmfuse_store_lease_held").set(0.0);
        shared.mark_broken(format!(
            "lost the writer lease on {}: its database session ended (another replica may \
             be writing now); exiting with status {LEASE_LOST_EXIT} to restart as a follower",
            store.path().display()
        ));
        std::process::exit(LEASE_LOST_EXIT);
    }
}

fn broken_error(shared: &Shared) -> ServiceError {
    let why = shared.broken_reason();
    ServiceError::NotReady {
        message: format!("the service refuses writes: {why}"),
        not_ready: vec![format!("store: {why}")],
    }
}

type InsertCmd = (
    Vec<NewRound>,
    Option<Idem>,
    oneshot::Sender<Result<Inserted, ServiceError>>,
);

fn flush_inserts(
    store: &mut Store,
    shared: &Shared,
    keys: &Keys,
    dim: &mut Option<usize>,
    cmds: Vec<InsertCmd>,
) {
    if cmds.is_empty() {
        return;
    }
    if shared.broken.load(Ordering::SeqCst) {
        for (_, _, reply) in cmds {
            let _ = reply.send(Err(broken_error(shared)));
        }
        return;
    }
    // A request whose contexts disagree with the dimension in force is refused alone; the
    // handler has already checked against the engine, so this only catches two first requests
    // of different dimensions racing each other.
    let before = *dim;
    let not_before = keys.not_before();
    let mut accepted: Vec<InsertCmd> = Vec::with_capacity(cmds.len());
    // A keyed request repeated within this group: answered with the first one's answer once
    // it commits.
    type Follower = (usize, oneshot::Sender<Result<Inserted, ServiceError>>);
    let mut followers: Vec<Follower> = Vec::new();
    for (rounds, idem, reply) in cmds {
        if let Some(i) = &idem {
            let earlier = accepted
                .iter()
                .position(|(_, other, _)| other.as_ref().is_some_and(|o| o.key == i.key));
            if let Some(pos) = earlier {
                let o = accepted[pos].1.as_ref().expect("keyed");
                if o.route == i.route && o.fingerprint == i.fingerprint {
                    followers.push((pos, reply));
                } else {
                    let _ = reply.send(Err(key_reused(&i.key, i.route, o.route)));
                }
                continue;
            }
            match store.idempotency(&i.key, not_before) {
                Ok(Some(rec)) if rec.route == i.route && rec.fingerprint == i.fingerprint => {
                    metrics::counter!("vlmfuse_idempotent_replays_total").increment(1);
                    let _ = reply.send(Ok(Inserted::Replay(rec.response)));
                    continue;
                }
                Ok(Some(rec)) => {
                    let _ = reply.send(Err(key_reused(&i.key, i.route, &rec.route)));
                    continue;
                }
                Ok(None) => {}
                Err(e) => {
                    let _ = reply.send(Err(e.into()));
                    continue;
                }
            }
        }
        // The handler made every round of one request the same dimension.
        let d = rounds.first().map(|r| r.round.context.len()).unwrap_or(0);
        let bad = match *dim {
            Some(e) if e != d => Some(FusionError::Dimension {
                expected: e,
                got: d,
            }),
            Some(_) => None,
            None => {
                *dim = Some(d);
                None
            }
        };
        match bad {
            Some(e) => {
                let _ = reply.send(Err(e.into()));
            }
            None => accepted.push((rounds, idem, reply)),
        }
    }
    let first_seq = shared.rounds.load(Ordering::SeqCst);
    let all: Vec<NewRound> = accepted
        .iter()
        .flat_map(|(r, _, _)| r.iter().cloned())
        .collect();
    if all.is_empty() {
        return;
    }
    // Each keyed request's answer, rendered now so that it commits with its rounds.
    let created_ms = vlmfuse_store::timestamp_ms();
    let mut records = Vec::new();
    let mut bodies: Vec<Option<serde_json::Value>> = Vec::with_capacity(accepted.len());
    let mut replies = Vec::with_capacity(accepted.len());
    let mut seq = first_seq;
    for (rounds, idem, reply) in accepted {
        let body = idem.map(|i| {
            let body = (i.render)(seq);
            records.push(IdempotencyRecord {
                key: i.key,
                route: i.route.to_string(),
                fingerprint: i.fingerprint,
                response: body.clone(),
                created_ms,
            });
            body
        });
        bodies.push(body);
        replies.push((seq, reply));
        seq += rounds.len() as u64;
    }
    match store.insert_rounds_keyed(first_seq, &all, &records) {
        Ok(()) => {
            if before.is_none() {
                if let Some(d) = *dim {
                    let mut eng = shared.engine.blocking_write();
                    if let Err(e) = eng.fix_dim(d) {
                        shared.mark_broken(format!("engine refused the stored dimension: {e}"));
                    }
                }
            }
            // The adaptive method learns from unlabelled rounds: each joins its pool now, in
            // `seq` order, which is the order a rebuild replays them in.
            let observe = shared.engine.blocking_read().method() != vlmfuse_fusion::Method::Paper;
            if observe {
                let mut eng = shared.engine.blocking_write();
                for (i, r) in all.iter().enumerate() {
                    let seq = first_seq + i as u64;
                    if let Err(e) = eng.observe(seq, &r.round, &r.inference) {
                        shared.mark_broken(format!(
                            "round {seq} committed but the engine could not learn from it ({e}); \
                             restart to rebuild"
                        ));
                        break;
                    }
                }
            }
            shared
                .rounds
                .store(first_seq + all.len() as u64, Ordering::SeqCst);
            metrics::counter!("vlmfuse_rounds_stored_total").increment(all.len() as u64);
            shared.dashboard_rounds(&all);
            for (pos, reply) in followers {
                let res = match &bodies[pos] {
                    Some(b) => Ok(Inserted::Replay(b.clone())),
                    None => Err(ServiceError::Internal(
                        "a keyed request lost its answer".into(),
                    )),
                };
                let _ = reply.send(res);
            }
            for ((seq, reply), body) in replies.into_iter().zip(bodies) {
                let _ = reply.send(Ok(Inserted::Fresh { first: seq, body }));
            }
        }
        Err(e) => {
            *dim = before;
            let msg = e.to_string();
            for (_, reply) in replies {
                let _ = reply.send(Err(ServiceError::NotStored(msg.clone())));
            }
            for (_, reply) in followers {
                let _ = reply.send(Err(ServiceError::NotStored(msg.clone())));
            }
        }
    }
}

fn feedback(
    store: &mut Store,
    shared: &Shared,
    round_id: &str,
    truth: Vec<u8>,
    source: String,
    derive: Option<Derive>,
) -> Result<FeedbackDone, ServiceError> {
    let start = Instant::now();
    let unknown = || ServiceError::UnknownRound(round_id.to_string());
    let seq = parse_round_id(round_id).ok_or_else(unknown)?;
    if seq >= shared.rounds.load(Ordering::SeqCst) {
        return Err(unknown());
    }
    let stored = store.round(seq)?.ok_or_else(unknown)?;
    let (truth, derived) = match derive {
        None => (truth, None),
        Some(d) => {
            let (track, cfg) = *d;
            // The clip's duration, for a round /v1/infer stored (a /v1/fuse round has none).
            let duration = store
                .round_request(seq)?
                .and_then(|r| r["clip"]["duration_s"].as_f64());
            let a = super::annotate::derive(&cfg, &track, duration)?;
            let eng = shared.engine.blocking_read();
            let Some(t) = super::annotate::truth_of(eng.ontology(), &a) else {
                let why: Vec<String> = a
                    .undecided
                    .iter()
                    .map(|u| format!("{}: {}", u.label, u.reason))
                    .collect();
                return Err(ServiceError::Signals {
                    kind: "undecided",
                    message: format!(
                        "signals: the track decides none of the labels ({})",
                        why.join("; ")
                    ),
                });
            };
            (t, Some(a))
        }
    };
    let coalition = stored.round.coalition();
    let l = truth.len();
    let events = store.feedback(seq)?;
    let (merged, sources) = merged_truth(l, &events);
    let (learned, ignored) = {
        let eng = shared.engine.blocking_read();
        merge_feedback(eng.ontology(), &merged, &sources, &truth, &source)?
    };
    if learned.iter().all(|&v| v > 1) {
        let last = events.last().cloned().ok_or_else(|| {
            ServiceError::Internal("a feedback that teaches nothing on an unlabelled round".into())
        })?;
        // The answer the round's latest feedback got (a plain repeat reads as its first answer).
        return Ok(FeedbackDone {
            round_id: round_id.to_string(),
            learned: last.truth.clone(),
            feedback: last,
            coalition,
            repeated: true,
            merged,
            sources,
            ignored,
            derived,
        });
    }
    let (outcome, labelled_order) = {
        let eng = shared.engine.blocking_read();
        let o = eng.credit(
            &stored.inference.signals,
            &stored.inference.w_used,
            &learned,
            seq,
        );
        (o, eng.labelled())
    };
    let fb = StoredFeedback {
        seq,
        labelled_order,
        rounds_before: shared.rounds.load(Ordering::SeqCst),
        truth: learned.clone(),
        source: source.clone(),
        outcome,
    };
    store.insert_feedback(std::slice::from_ref(&fb))?;
    // Committed: from here the database holds the feedback, so the engine must follow.
    let round_for_page = Round {
        context: Vec::new(),
        present: stored.round.present.clone(),
        reports: stored.round.reports.clone(),
    };
    let q_served = stored.inference.q.clone();
    {
        let mut eng = shared.engine.blocking_write();
        let lr = LabelledRound {
            seq,
            round: stored.round,
            truth: fb.truth.clone(),
            q: stored.inference.q,
        };
        if let Err(e) = eng.apply(&lr, Some(&fb.outcome)) {
            shared.mark_broken(format!(
                "feedback for {round_id} committed but could not be applied ({e}); restart to rebuild"
            ));
        }
        publish_gauges(&eng);
    }
    if let Ok(mut d) = shared.dashboard.lock() {
        d.on_feedback(
            fb.labelled_order + 1,
            round_id,
            &round_for_page,
            &fb.truth,
            &q_served,
            &fb.outcome.phi,
            &fb.outcome.w_after,
        );
    }
    metrics::histogram!("vlmfuse_feedback_duration_seconds").record(start.elapsed().as_secs_f64());
    metrics::counter!("vlmfuse_feedback_labels_total", "source" => source_metric(&source))
        .increment(learned.iter().filter(|&&v| v <= 1).count() as u64);
    let mut merged = merged;
    let mut sources = sources;
    for (k, &v) in learned.iter().enumerate() {
        if v <= 1 {
            merged[k] = v;
            sources[k] = Some(source.clone());
        }
    }
    Ok(FeedbackDone {
        round_id: round_id.to_string(),
        feedback: fb,
        coalition,
        repeated: false,
        merged,
        sources,
        learned,
        ignored,
        derived,
    })
}

/// The `source` label of the feedback metrics: the three known sources by name, any other
/// (a caller's own) as `other`, so that callers cannot grow the metric's label set.
fn source_metric(source: &str) -> &'static str {
    match source {
        "human" => "human",
        "kinematics" => "kinematics",
        "detector" => "detector",
        _ => "other",
    }
}
