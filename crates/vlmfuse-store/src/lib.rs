//! Durable state of the service: every round it fused, every feedback it acknowledged, and enough
//! to rebuild the fusion engine exactly on start.
//!
//! SQLite in WAL mode with `synchronous=FULL` because it needs no server, survives `kill -9` and
//! power loss once a transaction commits, and lets readers run beside the one writer.
//!
//! The engine is not serialised with each event. It is a pure function of the events (rounds in
//! order, feedback in labelling order with their outcomes), so the store keeps exactly those and
//! replays them on start ([`Store::load_engine`]); that keeps each feedback's transaction small
//! (one row, not a snapshot of the bank) and makes a restart equal, bit for bit, to never having
//! stopped. So that a long history does not make a long start, the writer also keeps
//! [`snapshot`]s of the engine now and then: a start loads the newest usable one and replays
//! only the events after it, which gives the same engine, bit for bit.

use db::{Db, Get, P};
use rusqlite::{Connection, OpenFlags};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{Read, Write};
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use vlmfuse_fusion::replay::{FeedbackEvent, Replay, ReplayError, RoundEvent, StoredLabel};
#[cfg(test)]
use vlmfuse_fusion::LabelledRound;
use vlmfuse_fusion::{Engine, FeedbackOutcome, FusionError, Inference, Round};

/// Bumped when the schema changes incompatibly; an old database is then refused, not misread.
pub const SCHEMA_VERSION: i64 = 2;

/// The file under the data directory.
pub const DB_FILE: &str = "vlmfuse.db";

/// The lock file under the data directory: held (`flock`, exclusive) by the one process whose
/// [`Store`] writes there, and holding that process's pid for the error a second one gets.
pub const LOCK_FILE: &str = "LOCK";

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("database error: {0}")]
    Sqlite(#[from] rusqlite::Error),
    /// PostgreSQL refused or failed a statement, or the connection broke: the server's message.
    #[error("PostgreSQL: {0}")]
    Postgres(String),
    /// The PostgreSQL server could not be reached or refused the session.
    #[error("cannot connect to PostgreSQL at {url}: {why}")]
    Connect { url: String, why: String },
    /// Another vlmfuse holds the database's writer lease (its session-level advisory lock) and
    /// kept it for as long as this one waited.
    #[error(
        "the PostgreSQL database {url} is written by another vlmfuse ({holder}); this one waits          for the lease only as long as [store] lease_wait_s says"
    )]
    Leased { url: String, holder: String },
    /// SQLite refused to open or set up the database file (read-only, not a database, full):
    /// the path says which file, which a bare SQLite message does not.
    #[error("cannot open the database {path}: {source}")]
    Open {
        path: PathBuf,
        source: rusqlite::Error,
    },
    #[error("cannot create data directory {path}: {source}")]
    DataDir {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("stored value has the wrong type: {0}")]
    Type(#[from] rusqlite::types::FromSqlError),
    #[error("stored JSON is unreadable: {0}")]
    Json(#[from] serde_json::Error),
    /// The database was written under another reporter list, ontology or schema; reading it
    /// with this configuration would silently mix up indices.
    #[error("database does not match this configuration: {0}")]
    Mismatch(String),
    #[error("database is inconsistent: {0}")]
    Corrupt(String),
    /// Writing an engine snapshot failed (reading one never fails a start: an unusable
    /// snapshot is skipped with a warning).
    #[error("snapshot: {0}")]
    Snapshot(String),
    #[error("rebuilding the engine failed: {0}")]
    Fusion(#[from] FusionError),
    /// Another [`Store`] (another server, or another open in this process) holds the data
    /// directory's [`LOCK_FILE`]. Two writers would hand out the same round numbers, so the
    /// second is refused at open instead of failing every write later.
    #[error(
        "the data directory {} is in use by another vlmfuse store ({}); stop that server or \
         give this one another server.data_dir",
        .dir.display(),
        holder(*.pid)
    )]
    Locked { dir: PathBuf, pid: Option<u32> },
    /// The lock file could not be created, read or locked (permissions, a file system
    /// without `flock`).
    #[error("cannot lock the data directory through {path}: {source}")]
    Lock {
        path: PathBuf,
        source: std::io::Error,
    },
}

fn holder(pid: Option<u32>) -> String {
    match pid {
        Some(pid) if pid == std::process::id() => format!("pid {pid}, this process"),
        Some(pid) => format!("pid {pid}"),
        None => "pid unknown".into(),
    }
}

/// The exclusive lock on a data directory, held for as long as its [`Store`] lives.
///
/// `flock(2)` rather than the lock file's mere existence: the kernel drops the lock when the
/// holder exits however it exits (`kill -9` included), so a crash never leaves a stale lock
/// behind, and two opens in one process conflict too (each open file is its own lock owner).
/// The file is never deleted: unlinking a lock file while another process waits on it lets two
/// processes hold "the" lock on two different inodes.
#[derive(Debug)]
struct DirLock {
    _file: File,
}

impl DirLock {
    /// Takes the lock of `dir`, retrying for up to `wait` while another holder has it.
    fn acquire(dir: &Path, wait: Duration) -> Result<Self, StoreError> {
        let path = dir.join(LOCK_FILE);
        let lock_err = |source| StoreError::Lock {
            path: path.clone(),
            source,
        };
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(lock_err)?;
        let deadline = Instant::now() + wait;
        loop {
            // SAFETY: flock on a file descriptor this function owns; no memory is involved.
            if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } == 0 {
                break;
            }
            let err = std::io::Error::last_os_error();
            match err.kind() {
                std::io::ErrorKind::Interrupted => continue,
                std::io::ErrorKind::WouldBlock if Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_millis(50));
                }
                std::io::ErrorKind::WouldBlock => {
                    let mut text = String::new();
                    // The holder may be between truncating and writing: then the pid is unknown.
                    let pid = file
                        .read_to_string(&mut text)
                        .ok()
                        .and_then(|_| text.trim().parse().ok());
                    return Err(StoreError::Locked {
                        dir: dir.to_path_buf(),
                        pid,
                    });
                }
                _ => return Err(lock_err(err)),
            }
        }
        file.set_len(0).map_err(lock_err)?;
        // The cursor is still at 0: nothing was read on the way to taking the lock.
        file.write_all(format!("{}\n", std::process::id()).as_bytes())
            .map_err(lock_err)?;
        Ok(DirLock { _file: file })
    }
}

impl From<ReplayError> for StoreError {
    fn from(e: ReplayError) -> Self {
        match e {
            ReplayError::Fusion(e) => StoreError::Fusion(e),
            ReplayError::Inconsistent(m) => StoreError::Corrupt(m),
        }
    }
}

/// The part of the service's configuration that fixes what indices in the database mean.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Identity {
    pub reporters: Vec<String>,
    /// Label ids in ontology order.
    pub labels: Vec<String>,
}

/// A round to store, as inference produced it.
#[derive(Debug, Clone)]
pub struct NewRound {
    pub round: Round,
    pub inference: Inference,
    /// The request as received (client id, reports by name) and, for later issues, raw texts
    /// and clip metadata. Stored verbatim; never read back by the engine.
    pub request: serde_json::Value,
    pub created_ms: i64,
    /// Frame thumbnails for the operator page (none for `/v1/fuse` rounds).
    pub thumbnails: Vec<browse::Thumbnail>,
}

/// A stored round, read back for feedback.
#[derive(Debug, Clone)]
pub struct StoredRound {
    pub seq: u64,
    pub round_id: String,
    pub round: Round,
    pub inference: Inference,
}

/// An acknowledged feedback.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredFeedback {
    pub seq: u64,
    /// 0-based position in labelling order.
    pub labelled_order: u64,
    /// Rounds stored when the feedback was applied: where it falls among the rounds' own
    /// events, which the `adaptive` method also learns from (`Engine::observe`). A rebuild
    /// replays both kinds of event in this order. Databases written before the column existed
    /// read `seq + 1` (the earliest it can have been).
    pub rounds_before: u64,
    /// Per label: 0 or 1 where this event gave (and the engine learned) the truth,
    /// [`vlmfuse_fusion::UNKNOWN`] elsewhere.
    pub truth: Vec<u8>,
    /// Who gave it (`human`, `kinematics`, `detector` or a caller's name).
    pub source: String,
    pub outcome: FeedbackOutcome,
}

/// A stored idempotency key: which request it was used for and what that request answered.
#[derive(Debug, Clone, PartialEq)]
pub struct IdempotencyRecord {
    pub key: String,
    /// The route, e.g. `/v1/fuse`: one key names one request on one route.
    pub route: String,
    /// A hash of the request, to tell a retry from another request under the same key.
    pub fingerprint: String,
    pub response: serde_json::Value,
    pub created_ms: i64,
}

/// Where an engine stands in the stored history: the rounds (by `seq`) and feedbacks (by
/// labelling order) it holds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Position {
    pub rounds: u64,
    pub labelled: u64,
}

/// What [`Store::load_engine`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadReport {
    pub rounds: u64,
    pub labelled: u64,
    /// The `seq` the next stored round gets.
    pub next_seq: u64,
    /// The fusion method the database was written under before this start, when it differs
    /// from the engine's: every outcome was then recomputed under the engine's method.
    pub migrated_from: Option<String>,
    /// The snapshot the engine was loaded from (then only the events after it were replayed);
    /// `None`: every event was replayed.
    pub snapshot: Option<snapshot::Used>,
    /// Snapshots found but not used, with the reason (each also logged as a warning).
    pub skipped_snapshots: Vec<(PathBuf, String)>,
}

/// The public id of a round: its creation order, zero-padded so ids sort like rounds.
pub fn round_id(seq: u64) -> String {
    format!("r-{seq:08}")
}

/// Parses a public round id back into its `seq`; `None` for anything [`round_id`] never
/// produces, so that `r-42` and `r-00000042` cannot both name one round.
pub fn parse_round_id(id: &str) -> Option<u64> {
    let digits = id.strip_prefix("r-")?;
    if !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let seq: u64 = digits.parse().ok()?;
    (round_id(seq) == id).then_some(seq)
}

fn f64s_to_blob(v: &[f64]) -> Vec<u8> {
    let mut out = Vec::with_capacity(v.len() * 8);
    for x in v {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out
}

fn blob_to_f64s(b: &[u8]) -> Result<Vec<f64>, StoreError> {
    let chunks = b.chunks_exact(8);
    if !chunks.remainder().is_empty() {
        return Err(StoreError::Corrupt(format!(
            "f64 blob of {} bytes is not a multiple of 8",
            b.len()
        )));
    }
    Ok(chunks
        .map(|c| f64::from_le_bytes(c.try_into().expect("chunk of 8")))
        .collect())
}

fn bools_to_blob(v: &[bool]) -> Vec<u8> {
    v.iter().map(|&b| b as u8).collect()
}

/// A round from the `context`, `present` and `reports` columns of a row, from column `at`.
fn round_from(row: &(impl Get + ?Sized), at: usize) -> Result<Round, StoreError> {
    Ok(Round {
        context: blob_to_f64s(row.blob(at)?)?,
        present: row.blob(at + 1)?.iter().map(|&b| b != 0).collect(),
        reports: row.blob(at + 2)?.to_vec(),
    })
}

/// A feedback row of round `seq` from the columns `labelled_order, truth, outcome,
/// rounds_before, source`, from column `at`. A row written before `rounds_before` was kept
/// falls right after its round.
fn feedback_from(
    row: &(impl Get + ?Sized),
    seq: u64,
    at: usize,
) -> Result<StoredFeedback, StoreError> {
    let before = row.opt_i64(at + 3)?;
    Ok(StoredFeedback {
        seq,
        labelled_order: row.u64(at)?,
        rounds_before: before.map_or(seq + 1, |b| b as u64),
        truth: row.blob(at + 1)?.to_vec(),
        outcome: serde_json::from_str(row.str(at + 2)?)?,
        source: row.str(at + 4)?.to_string(),
    })
}

/// What a replay recomputed (under another method), and how many feedbacks it applied.
#[derive(Default)]
struct Replayed {
    labelled: u64,
    /// Rounds the replay fed to the engine.
    rounds_fed: u64,
    inferences: Vec<(u64, Inference)>,
    /// By labelling order (a round may have several).
    outcomes: Vec<(u64, FeedbackOutcome)>,
}

/// A replay's rounds from `?1`, a page of `?2`: what the engine learns from each (its
/// context, reporters and reports), the inference it was served, and whether feedback followed.
const REPLAY_ROUNDS: &str = "SELECT r.seq, r.context, r.present, r.reports, d.inference,
        EXISTS (SELECT 1 FROM feedback f WHERE f.seq = r.seq)
 FROM rounds r JOIN round_detail d ON d.seq = r.seq
 WHERE r.seq >= ?1 ORDER BY r.seq LIMIT ?2";

/// A replay's feedback from labelling order `?1`, a page of `?2`, with its round, the
/// posteriors served, the stored outcome, its place among the rounds, and whether a later
/// feedback on the same round follows.
const REPLAY_FEEDBACK: &str = "SELECT r.seq, r.context, r.present, r.reports, r.q, f.truth,
        f.outcome, f.rounds_before, f.labelled_order,
        EXISTS (SELECT 1 FROM feedback g
                WHERE g.seq = f.seq AND g.labelled_order > f.labelled_order)
 FROM feedback f JOIN rounds r ON r.seq = f.seq
 WHERE f.labelled_order >= ?1 ORDER BY f.labelled_order LIMIT ?2";

/// Rows of a big table read a page at a time in key order, each decoded in place by `decode`:
/// `sql` takes the first key as `?1` and the page size as `?2`, orders by the key, and `key`
/// gives a decoded row's. Bounded memory at any table size, and no cursor held open across the
/// caller's other queries.
struct Pager<'s, T, F> {
    db: &'s Db,
    sql: &'static str,
    decode: F,
    key: fn(&T) -> u64,
    next_key: u64,
    done: bool,
    page: std::vec::IntoIter<T>,
}

/// Rows per page of a replay: a few megabytes of contexts at most.
const PAGE_ROWS: i64 = 512;

impl<'s, T, F: FnMut(&dyn Get) -> Result<T, StoreError>> Pager<'s, T, F> {
    fn new(db: &'s Db, sql: &'static str, from: u64, key: fn(&T) -> u64, decode: F) -> Self {
        Pager {
            db,
            sql,
            decode,
            key,
            next_key: from,
            done: false,
            page: Vec::new().into_iter(),
        }
    }

    fn next(&mut self) -> Result<Option<T>, StoreError> {
        loop {
            if let Some(r) = self.page.next() {
                return Ok(Some(r));
            }
            if self.done {
                return Ok(None);
            }
            let rows = self.db.query_with(
                self.sql,
                &[P::I(self.next_key as i64), P::I(PAGE_ROWS)],
                &mut self.decode,
            )?;
            self.done = (rows.len() as i64) < PAGE_ROWS;
            if let Some(last) = rows.last() {
                self.next_key = (self.key)(last) + 1;
            }
            self.page = rows.into_iter();
        }
    }
}

/// A round of a replay, decoded.
struct RoundItem {
    seq: u64,
    round: Round,
    /// The inference it was served (unread when the replay infers afresh).
    served: Option<Inference>,
    /// Feedback followed it.
    labelled: bool,
}

/// A feedback of a replay, decoded.
struct FeedbackItem {
    seq: u64,
    order: u64,
    /// Rounds stored when it was applied.
    before: u64,
    truth: Vec<u8>,
    /// What it was credited with (unread when the replay credits afresh).
    stored: Option<StoredLabel>,
    /// A later feedback on the same round follows.
    more: bool,
}

fn round_item(row: &dyn Get, fresh: bool) -> Result<RoundItem, StoreError> {
    Ok(RoundItem {
        seq: row.u64(0)?,
        round: round_from(row, 1)?,
        served: if fresh {
            None
        } else {
            Some(serde_json::from_str(row.str(4)?)?)
        },
        labelled: row.bool(5)?,
    })
}

fn feedback_item(row: &dyn Get, fresh: bool) -> Result<FeedbackItem, StoreError> {
    let seq = row.u64(0)?;
    Ok(FeedbackItem {
        seq,
        order: row.u64(8)?,
        before: row.opt_i64(7)?.map_or(seq + 1, |b| b as u64),
        truth: row.blob(5)?.to_vec(),
        stored: if fresh {
            None
        } else {
            Some(StoredLabel {
                round: round_from(row, 1)?,
                q: blob_to_f64s(row.blob(4)?)?,
                outcome: serde_json::from_str(row.str(6)?)?,
            })
        },
        more: row.bool(9)?,
    })
}

/// The `rounds` rows, fed to a replay up to a point in event order.
struct RoundFeed<'s, F> {
    /// `None` when the replay needs no rounds (a method that learns only from feedback).
    rows: Option<Pager<'s, RoundItem, F>>,
    /// Rounds before this `seq` have been fed.
    fed: u64,
    /// Infer each round again instead of reading its stored inference.
    fresh: bool,
}

impl<F: FnMut(&dyn Get) -> Result<RoundItem, StoreError>> RoundFeed<'_, F> {
    /// Feeds the rounds stored before the `upto`-th.
    fn feed(
        &mut self,
        upto: u64,
        replay: &mut Replay,
        out: &mut Replayed,
    ) -> Result<(), StoreError> {
        let Some(rows) = self.rows.as_mut() else {
            return Ok(());
        };
        while self.fed < upto {
            let Some(item) = rows.next()? else {
                self.fed = upto;
                break;
            };
            let seq = item.seq;
            let inf = replay.round(RoundEvent {
                seq,
                round: item.round,
                served: item.served,
                sims: None,
                observe: true,
                credit_later: self.fresh && item.labelled,
            })?;
            if self.fresh {
                out.inferences.push((seq, inf));
            }
            out.rounds_fed += 1;
            self.fed = seq + 1;
        }
        Ok(())
    }
}

fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

/// Milliseconds since the Unix epoch, for `created_ms`.
pub fn timestamp_ms() -> i64 {
    now_ms()
}

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
-- What the engine needs on start, kept narrow so that a scan of 100k rows stays fast.
CREATE TABLE IF NOT EXISTS rounds (
    seq        INTEGER PRIMARY KEY,
    round_id   TEXT NOT NULL UNIQUE,
    created_ms INTEGER NOT NULL,
    context    BLOB NOT NULL,   -- unit-norm context, f64 little-endian
    present    BLOB NOT NULL,   -- one byte per configured reporter
    reports    BLOB NOT NULL,   -- n * L bytes, 0/1
    q          BLOB NOT NULL,   -- posteriors at inference, f64 LE (the threshold fit needs them)
    threshold  REAL NOT NULL    -- threshold in force at inference: the threshold history
);
-- What feedback and audits need: the frozen signals, w used, the request and its raw texts.
CREATE TABLE IF NOT EXISTS round_detail (
    seq       INTEGER PRIMARY KEY REFERENCES rounds(seq),
    inference TEXT NOT NULL,    -- vlmfuse_fusion::Inference as JSON (signals, q, w_used, ...)
    request   TEXT NOT NULL     -- the request as received, plus later raw texts/metadata
);
-- One row per feedback event, in labelling order. A round may have several (partial
-- feedback: labels from the vehicle's signals, later a person's); each row holds what that
-- event taught, and the round's truth is their merge.
CREATE TABLE IF NOT EXISTS feedback (
    labelled_order INTEGER PRIMARY KEY,
    seq            INTEGER NOT NULL REFERENCES rounds(seq),
    rounds_before  INTEGER,         -- rounds stored when it was applied (event order)
    created_ms     INTEGER NOT NULL,
    truth          BLOB NOT NULL,   -- L bytes: 0/1 learned from this event, 2 not in it
    source         TEXT NOT NULL DEFAULT 'human',  -- who said it: human, kinematics, ...
    outcome        TEXT NOT NULL    -- vlmfuse_fusion::FeedbackOutcome as JSON
);
CREATE INDEX IF NOT EXISTS feedback_seq ON feedback (seq);
-- Small JPEG thumbnails of a /v1/infer round's frames, for the operator page (/ui); never read by
-- the engine. Added beside schema 2 (a database without it gains it on open).
CREATE TABLE IF NOT EXISTS thumbnails (
    seq  INTEGER NOT NULL REFERENCES rounds(seq),
    idx  INTEGER NOT NULL,
    t_s  REAL NOT NULL,
    jpeg BLOB NOT NULL,
    PRIMARY KEY (seq, idx)
);
-- Idempotency keys of /v1/fuse and /v1/infer: the answer a retry with the same key gets.
-- Written in the transaction that stores the rounds, so a request that timed out after it was
-- queued still leaves its answer for the retry; rows older than the configured TTL are pruned.
CREATE TABLE IF NOT EXISTS idempotency (
    key         TEXT PRIMARY KEY,
    route       TEXT NOT NULL,
    fingerprint TEXT NOT NULL,   -- hash of the request (body without the key), hex
    response    TEXT NOT NULL,   -- the JSON answer
    created_ms  INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS idempotency_created ON idempotency (created_ms);
-- One row: the reputations after the last feedback, to check the rebuild against.
CREATE TABLE IF NOT EXISTS state (
    id          INTEGER PRIMARY KEY CHECK (id = 1),
    reputations TEXT NOT NULL,
    labelled    INTEGER NOT NULL
);
";

/// What [`Store::open`] found of a write-ahead log that looks damaged.
#[derive(Debug, Clone, PartialEq, Eq)]
struct WalReport {
    wal_bytes: u64,
    /// Frames the file's size holds room for (some may be stale leftovers of an earlier log).
    frames_in_file: u64,
    /// Frames SQLite found valid and replayed.
    frames_recovered: u64,
    rounds: u64,
    feedback: u64,
}

/// Replays the write-ahead log (SQLite does on the first read) and checkpoints it, as the
/// first automatic checkpoint would: the number of valid frames it held.
fn checkpoint(conn: &Connection) -> Result<u64, StoreError> {
    let (_busy, log, _done): (i64, i64, i64) =
        conn.query_row("PRAGMA wal_checkpoint(PASSIVE)", [], |r| {
            Ok((r.get(0)?, r.get(1)?, r.get(2)?))
        })?;
    Ok(log.max(0) as u64)
}

/// After an open that found a non-empty write-ahead log of `wal_bytes` and replayed
/// `frames_recovered` of its frames: the counts, when they suggest the log was damaged
/// (SQLite recovered none of its frames, or fewer than the file holds and the database
/// holds no round). SQLite silently cuts a log at its first bad checksum, so this is the only
/// trace such a loss leaves.
fn judge_wal(
    conn: &Connection,
    wal_bytes: u64,
    frames_recovered: u64,
) -> Result<Option<WalReport>, StoreError> {
    let count = |sql: &str| -> Result<u64, StoreError> {
        Ok(conn.query_row(sql, [], |r| r.get::<_, i64>(0))? as u64)
    };
    let rounds = count("SELECT COUNT(*) FROM rounds")?;
    let feedback = count("SELECT COUNT(*) FROM feedback")?;
    let page = count("PRAGMA page_size")?;
    // A WAL is a 32-byte header and frames of a 24-byte header plus one page.
    let frames_in_file = wal_bytes.saturating_sub(32) / (page.max(512) + 24);
    // No round is suspicious only when frames were lost too: a server killed before its
    // first round leaves a log of nothing but the schema, all of it recovered.
    let damaged = frames_recovered == 0 || (rounds == 0 && frames_recovered < frames_in_file);
    Ok(damaged.then_some(WalReport {
        wal_bytes,
        frames_in_file,
        frames_recovered,
        rounds,
        feedback,
    }))
}

/// Sets the `method` meta key (both engines read `ON CONFLICT ... excluded` alike).
const SET_METHOD: &str = "INSERT INTO meta (key, value) VALUES ('method', ?1)
     ON CONFLICT(key) DO UPDATE SET value = excluded.value";

fn wal_path(db: &Path) -> PathBuf {
    let mut p = db.as_os_str().to_owned();
    p.push("-wal");
    PathBuf::from(p)
}

/// The database. One `Store` is the service's single writer, and holds the data directory's
/// lock ([`LOCK_FILE`]) for as long as it lives (on PostgreSQL also the database's writer
/// lease, [`pg`]); [`Store::open_read_only`] opens another for reads beside it.
pub struct Store {
    db: Db,
    /// SQLite: the database file; PostgreSQL: its URL without the password (for messages).
    path: PathBuf,
    /// The data directory: the snapshots' parent (on PostgreSQL each replica keeps its own).
    dir: PathBuf,
    /// What [`Store::open`] found of a damaged write-ahead log (logged as a warning).
    damaged_wal: Option<WalReport>,
    /// On PostgreSQL, the writer lease this store holds.
    lease: Option<pg::LeaseHeld>,
    /// Dropped after `db` (fields drop in order), so the lock outlives the last write.
    _lock: Option<DirLock>,
}

/// Where the state lives: the embedded SQLite file under the data directory, or a PostgreSQL
/// database that replicas share (the data directory then keeps only this replica's snapshots).
#[derive(Debug, Clone, PartialEq)]
pub enum Location {
    Sqlite { dir: PathBuf },
    Postgres(pg::PgOptions),
}

impl Location {
    /// The data directory (the SQLite file's, or a PostgreSQL replica's snapshots').
    pub fn dir(&self) -> &Path {
        match self {
            Location::Sqlite { dir } => dir,
            Location::Postgres(o) => &o.data_dir,
        }
    }
}

impl Store {
    /// Opens (creating if needed) the database under `dir`, taking the directory's lock:
    /// [`StoreError::Locked`] at once when another store holds it, in this process or another.
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        Self::open_waiting(dir, Duration::ZERO)
    }

    /// Opens the store at `at` as its writer: [`Store::open_waiting`] for SQLite, and for
    /// PostgreSQL the connection that holds the writer lease ([`pg::open_writer`]), waiting for
    /// it as the options say.
    pub fn open_at(at: &Location, wait: Duration) -> Result<Self, StoreError> {
        match at {
            Location::Sqlite { dir } => Self::open_waiting(dir, wait),
            Location::Postgres(o) => {
                std::fs::create_dir_all(&o.data_dir).map_err(|source| StoreError::DataDir {
                    path: o.data_dir.clone(),
                    source,
                })?;
                let lock = DirLock::acquire(&o.data_dir, wait)?;
                let (db, held) = pg::open_writer(o)?;
                Ok(Self {
                    db,
                    path: PathBuf::from(o.redacted()),
                    dir: o.data_dir.clone(),
                    damaged_wal: None,
                    lease: Some(held),
                    _lock: Some(lock),
                })
            }
        }
    }

    /// A reader of the store at `at`, beside its writer ([`Store::open_read_only`]).
    pub fn open_read_only_at(at: &Location) -> Result<Self, StoreError> {
        match at {
            Location::Sqlite { dir } => Self::open_read_only(dir),
            Location::Postgres(o) => Ok(Self {
                db: pg::open_reader(o)?,
                path: PathBuf::from(o.redacted()),
                dir: o.data_dir.clone(),
                damaged_wal: None,
                lease: None,
                _lock: None,
            }),
        }
    }

    /// [`Store::open`] that waits up to `wait` for another holder to let go of the lock before
    /// refusing: for a restart that may overlap the previous process's last commit.
    pub fn open_waiting(dir: &Path, wait: Duration) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir).map_err(|source| StoreError::DataDir {
            path: dir.to_path_buf(),
            source,
        })?;
        let lock = DirLock::acquire(dir, wait)?;
        let path = dir.join(DB_FILE);
        // Read before SQLite opens the log: after open it is either replayed or gone.
        let wal_bytes = std::fs::metadata(wal_path(&path))
            .map(|m| m.len())
            .unwrap_or(0);
        let at = |source: rusqlite::Error| StoreError::Open {
            path: path.clone(),
            source,
        };
        let conn = Connection::open(&path).map_err(at)?;
        // WAL lets a reader see the last commit while the writer works; FULL syncs the WAL on
        // every commit, which is what "acknowledged only after it commits" needs.
        conn.pragma_update(None, "journal_mode", "WAL")
            .map_err(at)?;
        conn.pragma_update(None, "synchronous", "FULL")
            .map_err(at)?;
        conn.pragma_update(None, "foreign_keys", "ON").map_err(at)?;
        conn.busy_timeout(std::time::Duration::from_secs(10))
            .map_err(at)?;
        // Before this open writes anything, or the count would include its own frames.
        let recovered = if wal_bytes > 0 {
            Some(checkpoint(&conn)?)
        } else {
            None
        };
        conn.execute_batch(SCHEMA).map_err(at)?;
        let version: Option<String> = {
            let mut st = conn.prepare("SELECT value FROM meta WHERE key = 'schema_version'")?;
            let mut rows = st.query([])?;
            match rows.next()? {
                Some(r) => Some(r.get(0)?),
                None => None,
            }
        };
        match version {
            None => {
                conn.execute(
                    "INSERT INTO meta (key, value) VALUES ('schema_version', ?1)",
                    [SCHEMA_VERSION.to_string()],
                )?;
            }
            Some(v) if v == SCHEMA_VERSION.to_string() => {}
            Some(v) if v == "1" => {
                // Databases from before the event order was recorded gain the column (NULL
                // rows read as `seq + 1`); adding a nullable column rewrites nothing.
                let has_order: bool = conn
                    .prepare(
                        "SELECT 1 FROM pragma_table_info('feedback') WHERE name = 'rounds_before'",
                    )?
                    .exists([])?;
                if !has_order {
                    conn.execute("ALTER TABLE feedback ADD COLUMN rounds_before INTEGER", [])?;
                }
                migrate_v1_feedback(&conn)?;
                tracing::info!(db = %path.display(), "database schema upgraded from 1 to 2");
            }
            Some(v) => {
                return Err(StoreError::Mismatch(format!(
                    "schema version {v}, this build reads {SCHEMA_VERSION}"
                )))
            }
        }
        let damaged_wal = match recovered {
            Some(frames_recovered) => judge_wal(&conn, wal_bytes, frames_recovered)?,
            None => None,
        };
        let store = Self {
            db: Db::Lite(conn),
            path,
            dir: dir.to_path_buf(),
            damaged_wal,
            lease: None,
            _lock: Some(lock),
        };
        if let Some(w) = &store.damaged_wal {
            tracing::warn!(
                db = %store.path.display(),
                wal_bytes = w.wal_bytes,
                wal_frames_in_file = w.frames_in_file,
                wal_frames_recovered = w.frames_recovered,
                rounds = w.rounds,
                feedback = w.feedback,
                "the database's write-ahead log was not empty at open, but SQLite recovered {} \
                 of its ~{} frames and the database holds {} rounds: if rounds were stored \
                 before, the log was damaged and they are lost",
                w.frames_recovered,
                w.frames_in_file,
                w.rounds
            );
        }
        Ok(store)
    }

    /// Opens the database under `dir` for reading only, without the directory's lock: for
    /// tools and tests that look at a data directory a running server holds. Writes through it
    /// fail.
    pub fn open_read_only(dir: &Path) -> Result<Self, StoreError> {
        let path = dir.join(DB_FILE);
        let conn = Connection::open_with_flags(
            &path,
            OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )?;
        conn.busy_timeout(std::time::Duration::from_secs(10))?;
        Ok(Self {
            db: Db::Lite(conn),
            path,
            dir: dir.to_path_buf(),
            damaged_wal: None,
            lease: None,
            _lock: None,
        })
    }

    /// SQLite: the database file; PostgreSQL: its URL without the password.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether this store writes (it holds the data directory's lock and, on PostgreSQL, the
    /// writer lease), rather than reading beside a writer.
    pub fn writes(&self) -> bool {
        self._lock.is_some()
    }

    /// On PostgreSQL, the writer lease this store holds (`None` for a reader and on SQLite).
    pub fn lease(&self) -> Option<&pg::LeaseHeld> {
        self.lease.as_ref()
    }

    /// The writer, on PostgreSQL: records where it takes writes (its HTTP address), for the
    /// replicas that forward to it.
    pub fn advertise(&self, address: &str) -> Result<(), StoreError> {
        if self.lease.is_some() {
            self.db.exec(
                "UPDATE lease SET address = ?1 WHERE id = 1",
                &[P::T(address)],
            )?;
        }
        Ok(())
    }

    /// On PostgreSQL, the lease row: who writes and where (`None` before any writer).
    pub fn lease_row(&self) -> Result<Option<pg::LeaseRow>, StoreError> {
        if !self.db.is_pg() {
            return Ok(None);
        }
        self.db
            .query_opt(
                "SELECT holder, since_ms, address FROM lease WHERE id = 1",
                &[],
            )?
            .map(|r| {
                Ok(pg::LeaseRow {
                    holder: r.string(0)?,
                    since_ms: r.i64(1)?,
                    address: r.string(2)?,
                })
            })
            .transpose()
    }

    /// Brings a replica's engine from `at` (the rounds and feedbacks it holds) to the latest
    /// committed events, as a restart's tail replay does (the stored inferences and outcomes,
    /// so the engine equals the writer's bit for bit), reading one consistent view of the
    /// database. Returns where the engine then stands.
    pub fn follow(&self, engine: &mut Engine, at: Position) -> Result<Position, StoreError> {
        self.db.batch(if self.db.is_pg() {
            "BEGIN ISOLATION LEVEL REPEATABLE READ READ ONLY"
        } else {
            "BEGIN"
        })?;
        let res = (|| {
            let anchor = snapshot::Anchor {
                rounds: at.rounds,
                labelled: at.labelled,
                last_round: None,
                last_feedback: None,
            };
            let r = self.replay_into(engine, false, Some(&anchor))?;
            let next = self
                .db
                .query_one("SELECT COALESCE(MAX(seq) + 1, 0) FROM rounds", &[])?
                .u64(0)?;
            Ok(Position {
                rounds: next.max(at.rounds),
                labelled: r.labelled,
            })
        })();
        let _ = self.db.batch("COMMIT");
        res
    }

    /// Whether this store is on PostgreSQL.
    pub fn is_postgres(&self) -> bool {
        self.db.is_pg()
    }

    /// On PostgreSQL, whether the writer's session (and with it the lease) is still alive: a
    /// cheap round trip. Always `true` on SQLite.
    pub fn alive(&self) -> bool {
        match &self.db {
            Db::Lite(_) => true,
            Db::Pg(_) => self.db.query("SELECT 1", &[]).is_ok(),
        }
    }

    fn meta(&self, key: &str) -> Result<Option<String>, StoreError> {
        self.db
            .query_opt("SELECT value FROM meta WHERE key = ?1", &[P::T(key)])?
            .map(|r| r.string(0))
            .transpose()
    }

    /// Records the identity on first use and refuses a database written under another one.
    pub fn check_identity(&mut self, id: &Identity) -> Result<(), StoreError> {
        let want = serde_json::to_string(id)?;
        match self.meta("identity")? {
            // A reader has nothing to check yet: the writer records it.
            None if !self.writes() => Ok(()),
            None => {
                self.db.exec(
                    "INSERT INTO meta (key, value) VALUES ('identity', ?1)",
                    &[P::T(&want)],
                )?;
                Ok(())
            }
            Some(have) => {
                let have_id: Identity = serde_json::from_str(&have)?;
                if &have_id == id {
                    Ok(())
                } else {
                    Err(StoreError::Mismatch(format!(
                        "it was written with reporters {:?} and labels {:?}, but the \
                         configuration names reporters {:?} and labels {:?}; use another \
                         data directory or the old configuration",
                        have_id.reporters, have_id.labels, id.reporters, id.labels
                    )))
                }
            }
        }
    }

    /// The context dimension fixed by the first stored round, if any.
    pub fn dim(&self) -> Result<Option<usize>, StoreError> {
        match self.meta("dim")? {
            None => Ok(None),
            Some(v) => v
                .parse()
                .map(Some)
                .map_err(|_| StoreError::Corrupt(format!("dim {v:?} is not a number"))),
        }
    }

    /// The fusion method the stored outcomes were computed under: the `method` meta key,
    /// else `paper` for a database that already holds feedback (written before the key
    /// existed, when `paper` was the only method), else none yet.
    pub fn method(&self) -> Result<Option<String>, StoreError> {
        if let Some(m) = self.meta("method")? {
            return Ok(Some(m));
        }
        let (_, labelled) = self.counts()?;
        Ok((labelled > 0).then(|| "paper".to_string()))
    }

    fn set_method(&self, method: &str) -> Result<(), StoreError> {
        self.db.exec(SET_METHOD, &[P::T(method)])?;
        Ok(())
    }

    /// Rebuilds a freshly built engine (same reporters, ontology and config as the database)
    /// by replaying the stored events ([`vlmfuse_fusion::replay::Replay`]) in the order the
    /// writer saw them: every round as it was stored (which the `adaptive` method learns from,
    /// `Engine::observe`) and every feedback in labelling order, at the point among the rounds
    /// where it was applied.
    ///
    /// Under the method the database was written with, each round comes with the inference it
    /// was served and each feedback with its stored outcome, which is what makes a restart
    /// exact: the replay makes the very floating-point operations the live service did, in the
    /// same order. Under another method (the configuration changed `[fusion] method`) the rounds
    /// are the state: the replay infers each round again and recomputes each credit, and the
    /// outcomes, the rounds' stored inferences and the state row are rewritten in one
    /// transaction, so the database then reads as if it had been written under the new method.
    ///
    /// The latest usable snapshot ([`snapshot`]) stands in for the events it covers, so only
    /// the tail is replayed; an unusable one is skipped with a warning, and if the engine the
    /// tail leads to disagrees with the state row, the full replay runs after all.
    pub fn load_engine(&mut self, engine: &mut Engine) -> Result<LoadReport, StoreError> {
        self.load_engine_from(engine, true)
    }

    /// [`Store::load_engine`] without snapshots: every event is replayed.
    pub fn load_engine_full(&mut self, engine: &mut Engine) -> Result<LoadReport, StoreError> {
        self.load_engine_from(engine, false)
    }

    fn load_engine_from(
        &mut self,
        engine: &mut Engine,
        snapshots: bool,
    ) -> Result<LoadReport, StoreError> {
        if engine.labelled() != 0 {
            return Err(StoreError::Corrupt(
                "load_engine needs a fresh engine".into(),
            ));
        }
        if let Some(d) = self.dim()? {
            engine.fix_dim(d)?;
        }
        let method = engine.method().name().to_string();
        let stored = self.method()?;
        let migrate = stored.as_deref().is_some_and(|m| m != method);
        let row = self
            .db
            .query_one("SELECT COUNT(*), MAX(seq) FROM rounds", &[])?;
        let (rounds, max_seq) = (row.i64(0)?, row.opt_i64(1)?);
        let next_seq = max_seq.map(|m| m as u64 + 1).unwrap_or(0);
        let mut skipped = Vec::new();
        if snapshots && !migrate {
            let fresh = engine.clone();
            if let Some((snap, anchor, path)) =
                self.usable_snapshot(&fresh, next_seq, &mut skipped)?
            {
                *engine = snap;
                let tail = self
                    .replay_into(engine, false, Some(&anchor))
                    .and_then(|r| self.check_state(engine, r.labelled).map(|()| r));
                match tail {
                    Ok(r) => {
                        if stored.is_none() && self.writes() {
                            self.set_method(&method)?;
                        }
                        return Ok(LoadReport {
                            rounds: rounds as u64,
                            labelled: r.labelled,
                            next_seq,
                            migrated_from: None,
                            snapshot: Some(snapshot::Used {
                                path,
                                tail_rounds: r.rounds_fed,
                                tail_feedback: r.labelled - anchor.labelled,
                                anchor,
                            }),
                            skipped_snapshots: skipped,
                        });
                    }
                    Err(e) => {
                        let why =
                            format!("the events after it do not lead to the stored state ({e})");
                        tracing::warn!(path = %path.display(), "snapshot not used: {why}; replaying every event");
                        skipped.push((path, why));
                        *engine = fresh;
                    }
                }
            }
        }
        if migrate && !self.writes() {
            return Err(StoreError::Mismatch(format!(
                "the database was written under method {:?} and this replica runs {method:?}; \
                 only the writer rewrites it (start the writer with this configuration first)",
                stored.as_deref().unwrap_or_default()
            )));
        }
        let replayed = self.replay_into(engine, migrate, None)?;
        if migrate {
            self.rewrite(&method, engine, &replayed)?;
        } else {
            self.check_state(engine, replayed.labelled)?;
            if stored.is_none() && self.writes() {
                self.set_method(&method)?;
            }
        }
        Ok(LoadReport {
            rounds: rounds as u64,
            labelled: replayed.labelled,
            next_seq,
            migrated_from: if migrate { stored } else { None },
            snapshot: None,
            skipped_snapshots: skipped,
        })
    }

    /// The data directory (the snapshots' parent, and on SQLite the database's).
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Where the engine stands in the stored history now: after every stored round and
    /// feedback (the single writer calls this between events, where that is the engine's
    /// state), with the anchors a later [`Store::load_engine`] checks a snapshot against.
    pub fn anchor(&self) -> Result<snapshot::Anchor, StoreError> {
        let last_round = self
            .db
            .query_opt(
                "SELECT seq, created_ms FROM rounds ORDER BY seq DESC LIMIT 1",
                &[],
            )?
            .map(|r| Ok::<_, StoreError>((r.i64(0)?, r.i64(1)?)))
            .transpose()?;
        let last_feedback = self
            .db
            .query_opt(
                "SELECT labelled_order, seq, created_ms FROM feedback
                 ORDER BY labelled_order DESC LIMIT 1",
                &[],
            )?
            .map(|r| Ok::<_, StoreError>((r.i64(0)?, r.i64(1)?, r.i64(2)?)))
            .transpose()?;
        Ok(snapshot::Anchor {
            rounds: last_round.map_or(0, |(s, _)| s as u64 + 1),
            labelled: last_feedback.map_or(0, |(o, _, _)| o as u64 + 1),
            last_round: last_round.map(|(s, ms)| (s as u64, ms)),
            last_feedback: last_feedback.map(|(_, s, ms)| (s as u64, ms)),
        })
    }

    /// Why the snapshot's anchor does not describe a point of this database's history, if it
    /// does not.
    fn anchor_mismatch(
        &self,
        a: &snapshot::Anchor,
        next_seq: u64,
    ) -> Result<Option<String>, StoreError> {
        if a.rounds > next_seq {
            return Ok(Some(format!(
                "it covers {} rounds but the database holds {next_seq}",
                a.rounds
            )));
        }
        let round_at = |seq: u64| -> Result<Option<i64>, StoreError> {
            self.db
                .query_opt(
                    "SELECT created_ms FROM rounds WHERE seq = ?1",
                    &[P::I(seq as i64)],
                )?
                .map(|r| r.i64(0))
                .transpose()
        };
        match (a.rounds, a.last_round) {
            (0, None) => {}
            (r, Some((seq, ms))) if seq + 1 == r => {
                if round_at(seq)? != Some(ms) {
                    return Ok(Some(format!(
                        "its last round {seq} is not this database's (another history)"
                    )));
                }
            }
            _ => return Ok(Some("its round anchor is malformed".into())),
        }
        let fb_at = |order: u64| -> Result<Option<(i64, i64)>, StoreError> {
            self.db
                .query_opt(
                    "SELECT seq, created_ms FROM feedback WHERE labelled_order = ?1",
                    &[P::I(order as i64)],
                )?
                .map(|r| Ok((r.i64(0)?, r.i64(1)?)))
                .transpose()
        };
        match (a.labelled, a.last_feedback) {
            (0, None) => {}
            (f, Some((seq, ms))) if f > 0 => match fb_at(f - 1)? {
                Some((s, m)) if s as u64 == seq && m == ms => {}
                Some(_) => {
                    return Ok(Some(format!(
                        "its feedback {f} is not this database's (another history)"
                    )))
                }
                None => {
                    return Ok(Some(format!(
                        "it covers {f} feedbacks but the database holds fewer"
                    )))
                }
            },
            _ => return Ok(Some("its feedback anchor is malformed".into())),
        }
        Ok(None)
    }

    /// The snapshot at `path` as an engine built like `fresh` (fixed to the database's
    /// dimension) with its anchor and path, or why it cannot stand in for its events. The
    /// header's checks (method, anchors) come before the engine is decoded.
    #[allow(clippy::type_complexity)]
    fn snapshot_usable(
        &self,
        path: &Path,
        fresh: &Engine,
        next_seq: u64,
    ) -> Result<Result<(Engine, snapshot::Anchor, PathBuf), String>, StoreError> {
        let opened = match snapshot::open(path) {
            Ok(o) => o,
            Err(why) => return Ok(Err(why)),
        };
        let h = &opened.header;
        if h.method != fresh.method().name() {
            return Ok(Err(format!(
                "written under method {:?}, the engine runs {:?}",
                h.method,
                fresh.method().name()
            )));
        }
        if let Some(why) = self.anchor_mismatch(&h.anchor, next_seq)? {
            return Ok(Err(why));
        }
        let mut snap = match opened.engine() {
            Ok(e) => e,
            Err(why) => return Ok(Err(why)),
        };
        if !snap.same_setup(fresh) {
            return Ok(Err(
                "written under another [fusion] configuration, ontology or reporter list".into(),
            ));
        }
        match (fresh.dim(), snap.dim()) {
            (Some(d), Some(e)) if d != e => {
                return Ok(Err("written for another context dimension".into()))
            }
            (Some(d), None) => snap.fix_dim(d)?,
            _ => {}
        }
        Ok(Ok((snap, opened.header.anchor.clone(), path.to_path_buf())))
    }

    /// The newest snapshot that can stand in for its events, as an engine built like `fresh`
    /// (fixed to the database's dimension), with its anchor and path. Unusable ones go to
    /// `skipped` with the reason and a warning.
    fn usable_snapshot(
        &self,
        fresh: &Engine,
        next_seq: u64,
        skipped: &mut Vec<(PathBuf, String)>,
    ) -> Result<Option<(Engine, snapshot::Anchor, PathBuf)>, StoreError> {
        let dir = snapshot::dir_of(self.dir());
        snapshot::remove_leftovers(&dir);
        for path in snapshot::list(&dir) {
            let why = match self.snapshot_usable(&path, fresh, next_seq)? {
                Ok(found) => return Ok(Some(found)),
                Err(why) => why,
            };
            tracing::warn!(path = %path.display(), "snapshot not used: {why}");
            skipped.push((path, why));
        }
        Ok(None)
    }

    /// Reads the stored events in the writer's order and feeds them to `engine`. With `fresh`
    /// the stored inferences and outcomes are left unread (the replay computes new ones, which
    /// are returned); without it, the rounds are read only if the engine learns from them.
    ///
    /// With `from` (a snapshot's anchor, the engine already holding its events) only the
    /// events after it are read: rounds from `from.rounds`, feedback from `from.labelled`.
    fn replay_into(
        &self,
        engine: &mut Engine,
        fresh: bool,
        from: Option<&snapshot::Anchor>,
    ) -> Result<Replayed, StoreError> {
        let (first_round, first_fb) = from.map_or((0, 0), |a| (a.rounds, a.labelled));
        let mut out = Replayed {
            labelled: first_fb,
            ..Replayed::default()
        };
        let mut rounds = RoundFeed {
            rows: if fresh || engine.observes() {
                Some(Pager::new(
                    &self.db,
                    REPLAY_ROUNDS,
                    first_round,
                    |r: &RoundItem| r.seq,
                    move |row: &dyn Get| round_item(row, fresh),
                ))
            } else {
                None
            },
            fed: first_round,
            fresh,
        };
        let mut fb_rows = Pager::new(
            &self.db,
            REPLAY_FEEDBACK,
            first_fb,
            |f: &FeedbackItem| f.order,
            move |row: &dyn Get| feedback_item(row, fresh),
        );
        let mut replay = Replay::new(engine);
        while let Some(fb) = fb_rows.next()? {
            rounds.feed(fb.before, &mut replay, &mut out)?;
            let outcome = replay.feedback(FeedbackEvent {
                seq: fb.seq,
                truth: fb.truth,
                stored: fb.stored,
                more: fb.more,
            })?;
            if fresh {
                out.outcomes.push((fb.order, outcome));
            }
            out.labelled += 1;
        }
        rounds.feed(u64::MAX, &mut replay, &mut out)?;
        Ok(out)
    }

    /// After a replay under another method: the recomputed outcomes and inferences, the state
    /// row and the method, in one transaction.
    fn rewrite(
        &mut self,
        method: &str,
        engine: &Engine,
        replayed: &Replayed,
    ) -> Result<(), StoreError> {
        self.db.tx(|tx| {
            for (order, o) in &replayed.outcomes {
                tx.exec(
                    "UPDATE feedback SET outcome = ?2 WHERE labelled_order = ?1",
                    &[P::I(*order as i64), P::T(&serde_json::to_string(o)?)],
                )?;
            }
            for (seq, inf) in &replayed.inferences {
                tx.exec(
                    "UPDATE round_detail SET inference = ?2 WHERE seq = ?1",
                    &[P::I(*seq as i64), P::T(&serde_json::to_string(inf)?)],
                )?;
                tx.exec(
                    "UPDATE rounds SET q = ?2, threshold = ?3 WHERE seq = ?1",
                    &[
                        P::I(*seq as i64),
                        P::B(&f64s_to_blob(&inf.q)),
                        P::F(inf.thresholds.first().copied().unwrap_or(f64::NAN)),
                    ],
                )?;
            }
            if replayed.labelled > 0 {
                tx.exec(
                    "UPDATE state SET reputations = ?1, labelled = ?2 WHERE id = 1",
                    &[
                        P::T(&serde_json::to_string(engine.reputations())?),
                        P::I(replayed.labelled as i64),
                    ],
                )?;
            }
            tx.exec(SET_METHOD, &[P::T(method)])?;
            Ok(())
        })
    }

    /// The state row is written in the same transaction as each feedback: a rebuild that
    /// disagrees with it means the tables were edited or damaged, and serving would be wrong.
    fn check_state(&self, engine: &Engine, labelled: u64) -> Result<(), StoreError> {
        let state = self
            .db
            .query_opt("SELECT reputations, labelled FROM state WHERE id = 1", &[])?
            .map(|r| Ok::<_, StoreError>((r.string(0)?, r.i64(1)?)))
            .transpose()?;
        match state {
            Some((w, lab)) => {
                let w: Vec<f64> = serde_json::from_str(&w)?;
                if lab as u64 != labelled || w.as_slice() != engine.reputations() {
                    return Err(StoreError::Corrupt(format!(
                        "the rebuilt state ({labelled} labelled, reputations {:?}) differs from \
                         the stored one ({lab} labelled, reputations {w:?})",
                        engine.reputations()
                    )));
                }
                Ok(())
            }
            None if labelled != 0 => {
                Err(StoreError::Corrupt("feedback without a state row".into()))
            }
            None => Ok(()),
        }
    }

    /// Stores rounds in one transaction (group commit), numbered from `first_seq`. The first
    /// round ever stored fixes the context dimension in the same transaction.
    pub fn insert_rounds(&mut self, first_seq: u64, rounds: &[NewRound]) -> Result<(), StoreError> {
        self.insert_rounds_keyed(first_seq, rounds, &[])
    }

    /// [`insert_rounds`](Self::insert_rounds) plus the idempotency keys of the requests those
    /// rounds answer, in the same transaction: the rounds and their keys commit together or
    /// not at all.
    pub fn insert_rounds_keyed(
        &mut self,
        first_seq: u64,
        rounds: &[NewRound],
        keys: &[IdempotencyRecord],
    ) -> Result<(), StoreError> {
        self.db.tx(|tx| write_rounds(tx, first_seq, rounds, keys))
    }

    /// Rounds and the feedback that follows them, in one transaction: a bulk import's chunk.
    /// Each feedback's `rounds_before` places it among the rounds in event order, as
    /// [`Store::load_engine`] replays them.
    pub fn insert_batch(
        &mut self,
        first_seq: u64,
        rounds: &[NewRound],
        fbs: &[StoredFeedback],
    ) -> Result<(), StoreError> {
        self.db.tx(|tx| {
            write_rounds(tx, first_seq, rounds, &[])?;
            write_feedback(tx, fbs)
        })
    }

    /// Undoes everything stored after `to` (a point [`Store::anchor`] gave): the rounds from
    /// `to.rounds`, the feedback from `to.labelled`, and the state row back to `reputations`
    /// (the engine's at that point). For a bulk import that failed half-way, so that a file
    /// that fails stores nothing.
    pub fn roll_back_to(
        &mut self,
        to: &snapshot::Anchor,
        reputations: &[f64],
    ) -> Result<(), StoreError> {
        self.db.tx(|tx| {
            // Feedback on a round after `to` came after `to` too: the labelling order covers it.
            let (r, l) = (P::I(to.rounds as i64), P::I(to.labelled as i64));
            tx.exec("DELETE FROM feedback WHERE labelled_order >= ?1", &[l])?;
            tx.exec("DELETE FROM round_detail WHERE seq >= ?1", &[r])?;
            tx.exec("DELETE FROM thumbnails WHERE seq >= ?1", &[r])?;
            tx.exec("DELETE FROM rounds WHERE seq >= ?1", &[r])?;
            if to.labelled == 0 {
                tx.exec("DELETE FROM state", &[])?;
            } else {
                tx.exec(
                    "UPDATE state SET reputations = ?1, labelled = ?2 WHERE id = 1",
                    &[P::T(&serde_json::to_string(reputations)?), l],
                )?;
            }
            if to.rounds == 0 {
                tx.exec("DELETE FROM meta WHERE key = 'dim'", &[])?;
            }
            Ok(())
        })
    }
}

/// The rows of `rounds` from `first_seq`, and their idempotency keys, inside `tx`. The first
/// round ever stored fixes the context dimension.
fn write_rounds(
    tx: &Db,
    first_seq: u64,
    rounds: &[NewRound],
    keys: &[IdempotencyRecord],
) -> Result<(), StoreError> {
    if let Some(first) = rounds.first() {
        let d = first.round.context.len();
        let have = tx
            .query_opt("SELECT value FROM meta WHERE key = 'dim'", &[])?
            .map(|r| r.string(0))
            .transpose()?;
        match have {
            None => {
                tx.exec(
                    "INSERT INTO meta (key, value) VALUES ('dim', ?1)",
                    &[P::T(&d.to_string())],
                )?;
            }
            Some(v) if v == d.to_string() => {}
            Some(v) => {
                return Err(StoreError::Mismatch(format!(
                    "context dimension {d}, but the database holds dimension {v}"
                )))
            }
        }
    }
    for (i, r) in rounds.iter().enumerate() {
        let seq = first_seq + i as u64;
        let threshold = r.inference.thresholds.first().copied().unwrap_or(f64::NAN);
        tx.exec(
            "INSERT INTO rounds (seq, round_id, created_ms, context, present, reports, q, threshold)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
            &[
                P::I(seq as i64),
                P::T(&round_id(seq)),
                P::I(r.created_ms),
                P::B(&f64s_to_blob(&r.round.context)),
                P::B(&bools_to_blob(&r.round.present)),
                P::B(&r.round.reports),
                P::B(&f64s_to_blob(&r.inference.q)),
                P::F(threshold),
            ],
        )?;
        tx.exec(
            "INSERT INTO round_detail (seq, inference, request) VALUES (?1, ?2, ?3)",
            &[
                P::I(seq as i64),
                P::T(&serde_json::to_string(&r.inference)?),
                P::T(&serde_json::to_string(&r.request)?),
            ],
        )?;
    }
    browse::write_thumbnails(tx, first_seq, rounds)?;
    for k in keys {
        tx.exec(
            "INSERT INTO idempotency (key, route, fingerprint, response, created_ms)
             VALUES (?1, ?2, ?3, ?4, ?5)
             ON CONFLICT(key) DO UPDATE SET route = excluded.route,
               fingerprint = excluded.fingerprint, response = excluded.response,
               created_ms = excluded.created_ms",
            &[
                P::T(&k.key),
                P::T(&k.route),
                P::T(&k.fingerprint),
                P::T(&serde_json::to_string(&k.response)?),
                P::I(k.created_ms),
            ],
        )?;
    }
    Ok(())
}

impl Store {
    /// The record of an idempotency key created at or after `not_before_ms` (older ones have
    /// expired, even before [`prune_idempotency`](Self::prune_idempotency) removes them).
    pub fn idempotency(
        &self,
        key: &str,
        not_before_ms: i64,
    ) -> Result<Option<IdempotencyRecord>, StoreError> {
        let Some(row) = self.db.query_opt(
            "SELECT route, fingerprint, response, created_ms FROM idempotency
             WHERE key = ?1 AND created_ms >= ?2",
            &[P::T(key), P::I(not_before_ms)],
        )?
        else {
            return Ok(None);
        };
        Ok(Some(IdempotencyRecord {
            key: key.to_string(),
            route: row.string(0)?,
            fingerprint: row.string(1)?,
            response: serde_json::from_str(row.str(2)?)?,
            created_ms: row.i64(3)?,
        }))
    }

    /// Removes the idempotency keys created before `before_ms`; returns how many.
    pub fn prune_idempotency(&mut self, before_ms: i64) -> Result<usize, StoreError> {
        Ok(self.db.exec(
            "DELETE FROM idempotency WHERE created_ms < ?1",
            &[P::I(before_ms)],
        )? as usize)
    }

    /// How many idempotency keys are stored.
    pub fn idempotency_keys(&self) -> Result<u64, StoreError> {
        self.db
            .query_one("SELECT COUNT(*) FROM idempotency", &[])?
            .u64(0)
    }

    /// Reads a stored round with its frozen inference.
    pub fn round(&self, seq: u64) -> Result<Option<StoredRound>, StoreError> {
        let Some(row) = self.db.query_opt(
            "SELECT r.context, r.present, r.reports, d.inference
             FROM rounds r JOIN round_detail d ON d.seq = r.seq WHERE r.seq = ?1",
            &[P::I(seq as i64)],
        )?
        else {
            return Ok(None);
        };
        Ok(Some(StoredRound {
            seq,
            round_id: round_id(seq),
            round: round_from(&row, 0)?,
            inference: serde_json::from_str(row.str(3)?)?,
        }))
    }

    /// The request JSON stored with a round.
    pub fn request(&self, seq: u64) -> Result<Option<serde_json::Value>, StoreError> {
        self.round_request(seq)
    }

    /// The request a round was stored with (its reports, and for `/v1/infer` the clip's
    /// metadata), if the round exists.
    pub fn round_request(&self, seq: u64) -> Result<Option<serde_json::Value>, StoreError> {
        self.db
            .query_opt(
                "SELECT request FROM round_detail WHERE seq = ?1",
                &[P::I(seq as i64)],
            )?
            .map(|r| Ok(serde_json::from_str(r.str(0)?)?))
            .transpose()
    }

    /// The feedback events acknowledged for a round, in labelling order (empty: none).
    pub fn feedback(&self, seq: u64) -> Result<Vec<StoredFeedback>, StoreError> {
        self.db
            .query(
                "SELECT labelled_order, truth, outcome, rounds_before, source FROM feedback
                 WHERE seq = ?1 ORDER BY labelled_order",
                &[P::I(seq as i64)],
            )?
            .iter()
            .map(|row| feedback_from(row, seq, 0))
            .collect()
    }

    /// Commits feedback, in labelling order, and the reputations the last one leads to, in one
    /// transaction. The caller applies them to the engine only after this returns `Ok`.
    pub fn insert_feedback(&mut self, fbs: &[StoredFeedback]) -> Result<(), StoreError> {
        if fbs.is_empty() {
            return Ok(());
        }
        self.db.tx(|tx| write_feedback(tx, fbs))
    }
}

/// Schema 1 kept one feedback per round (`seq` its key); schema 2 keeps feedback events (partial
/// feedback comes in parts), keyed by labelling order. The rows are copied as they are (each a
/// person's full labelling: source `human`), in one transaction with the version.
fn migrate_v1_feedback(conn: &Connection) -> Result<(), StoreError> {
    conn.execute_batch(
        "BEGIN IMMEDIATE;
         CREATE TABLE feedback_v2 (
             labelled_order INTEGER PRIMARY KEY,
             seq            INTEGER NOT NULL REFERENCES rounds(seq),
             rounds_before  INTEGER,
             created_ms     INTEGER NOT NULL,
             truth          BLOB NOT NULL,
             source         TEXT NOT NULL DEFAULT 'human',
             outcome        TEXT NOT NULL
         );
         INSERT INTO feedback_v2 (labelled_order, seq, rounds_before, created_ms, truth, source,
                                  outcome)
             SELECT labelled_order, seq, rounds_before, created_ms, truth, 'human', outcome
             FROM feedback;
         DROP TABLE feedback;
         ALTER TABLE feedback_v2 RENAME TO feedback;
         CREATE INDEX IF NOT EXISTS feedback_seq ON feedback (seq);
         UPDATE meta SET value = '2' WHERE key = 'schema_version';
         COMMIT;",
    )?;
    Ok(())
}

/// `fbs` in labelling order inside `tx`, and the state row after the last.
fn write_feedback(tx: &Db, fbs: &[StoredFeedback]) -> Result<(), StoreError> {
    let Some(last) = fbs.last() else {
        return Ok(());
    };
    // The next labelling order: the highest stored plus one (an index lookup; a count
    // would scan the table on every feedback).
    let labelled = tx
        .query_one(
            "SELECT COALESCE(MAX(labelled_order) + 1, 0) FROM feedback",
            &[],
        )?
        .u64(0)?;
    let now = now_ms();
    for (i, fb) in fbs.iter().enumerate() {
        if labelled + i as u64 != fb.labelled_order {
            return Err(StoreError::Corrupt(format!(
                "feedback would be number {} in labelling order, but {} precede it",
                fb.labelled_order,
                labelled + i as u64
            )));
        }
        tx.exec(
            "INSERT INTO feedback (seq, labelled_order, created_ms, truth, outcome, rounds_before,
                                   source)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
            &[
                P::I(fb.seq as i64),
                P::I(fb.labelled_order as i64),
                P::I(now),
                P::B(&fb.truth),
                P::T(&serde_json::to_string(&fb.outcome)?),
                P::I(fb.rounds_before as i64),
                P::T(&fb.source),
            ],
        )?;
    }
    tx.exec(
        "INSERT INTO state (id, reputations, labelled) VALUES (1, ?1, ?2)
         ON CONFLICT(id) DO UPDATE SET reputations = excluded.reputations,
                                       labelled = excluded.labelled",
        &[
            P::T(&serde_json::to_string(&last.outcome.w_after)?),
            P::I(last.labelled_order as i64 + 1),
        ],
    )?;
    Ok(())
}

impl Store {
    /// Counts of stored rounds and feedback, for tests and `/v1/state`.
    pub fn counts(&self) -> Result<(u64, u64), StoreError> {
        let r = self.db.query_one("SELECT COUNT(*) FROM rounds", &[])?;
        let f = self.db.query_one("SELECT COUNT(*) FROM feedback", &[])?;
        Ok((r.u64(0)?, f.u64(0)?))
    }
}

pub mod browse;
mod db;
pub mod pg;
pub mod snapshot;

#[cfg(test)]
mod tests;
