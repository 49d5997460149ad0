//! PostgreSQL: the store shared by replicas, and the writer lease.
//!
//! The tables are SQLite's ([`crate::SCHEMA`]) with PostgreSQL's types ([`SCHEMA`]); the
//! statements are the same text ([`crate::db`]). What is PostgreSQL's own is the lease:
//!
//! * **One writer.** The writer holds a session-level advisory lock ([`LEASE_KEY`]) on the very
//!   connection it writes through. The server releases it when that session ends, however it
//!   ends: the process killed (its socket closes at once), the host gone or the network cut (the
//!   server's keepalives and `tcp_user_timeout`), or the process hung (`idle_session_timeout`:
//!   a healthy writer touches its session every second, a hung one stops). A write commits only
//!   on that session, so a writer that lost its lease cannot commit anything after it: the
//!   lock fences it without a token of ours. The connection is never re-opened behind the
//!   writer's back; a broken one ends the writer.
//! * **Failover.** A standby polls for the lock ([`PgOptions::lease_wait`]) and, once it holds
//!   it, loads the engine from its own snapshot (if the database's history still matches it)
//!   and the events after it, as any start does. The time to take over is the time the server
//!   needs to notice the old session is gone ([`PgOptions::lease_timeout`], 8 s by default)
//!   plus one poll (0.2 s) plus the load.
//!
//! `postgres` (the synchronous client of `tokio-postgres`) because the store is synchronous by
//! design: one writer thread owns the session that holds the lease, and a pool would hand writes
//! to sessions that do not. TLS through rustls (`tokio-postgres-rustls`, the ring provider the
//! workspace already builds) when the URL's `sslmode` asks for it; readers open their own
//! sessions ([`open_reader`]), marked read-only.

use crate::db::{Db, P};
use crate::{StoreError, SCHEMA_VERSION};
use std::path::PathBuf;
use std::str::FromStr;
use std::time::{Duration, Instant};

/// The advisory lock that is the writer lease: one vlmfuse state per database ("vlmfuse" in
/// ASCII, then 1).
pub const LEASE_KEY: i64 = 0x766c_6d66_7573_6501;

/// How often a waiting standby asks for the lease.
const LEASE_POLL: Duration = Duration::from_millis(200);

/// The tables of [`crate::SCHEMA`] in PostgreSQL's types (`bigint` for SQLite's 64-bit
/// `INTEGER`, `bytea` for `BLOB`, `double precision` for `REAL`), plus the lease row that says
/// who writes.
pub const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS rounds (
    seq        BIGINT PRIMARY KEY,
    round_id   TEXT NOT NULL UNIQUE,
    created_ms BIGINT NOT NULL,
    context    BYTEA NOT NULL,
    present    BYTEA NOT NULL,
    reports    BYTEA NOT NULL,
    q          BYTEA NOT NULL,
    threshold  DOUBLE PRECISION NOT NULL
);
CREATE TABLE IF NOT EXISTS round_detail (
    seq       BIGINT PRIMARY KEY REFERENCES rounds(seq),
    inference TEXT NOT NULL,
    request   TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS feedback (
    labelled_order BIGINT PRIMARY KEY,
    seq            BIGINT NOT NULL REFERENCES rounds(seq),
    rounds_before  BIGINT,
    created_ms     BIGINT NOT NULL,
    truth          BYTEA NOT NULL,
    source         TEXT NOT NULL DEFAULT 'human',
    outcome        TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS feedback_seq ON feedback (seq);
CREATE TABLE IF NOT EXISTS thumbnails (
    seq  BIGINT NOT NULL REFERENCES rounds(seq),
    idx  BIGINT NOT NULL,
    t_s  DOUBLE PRECISION NOT NULL,
    jpeg BYTEA NOT NULL,
    PRIMARY KEY (seq, idx)
);
CREATE TABLE IF NOT EXISTS idempotency (
    key         TEXT PRIMARY KEY,
    route       TEXT NOT NULL,
    fingerprint TEXT NOT NULL,
    response    TEXT NOT NULL,
    created_ms  BIGINT NOT NULL
);
CREATE INDEX IF NOT EXISTS idempotency_created ON idempotency (created_ms);
CREATE TABLE IF NOT EXISTS state (
    id          BIGINT PRIMARY KEY CHECK (id = 1),
    reputations TEXT NOT NULL,
    labelled    BIGINT NOT NULL
);
-- Who holds the writer lease (the advisory lock is the lease; this row only names its holder
-- for the others' messages and /readyz).
CREATE TABLE IF NOT EXISTS lease (
    id       BIGINT PRIMARY KEY CHECK (id = 1),
    holder   TEXT NOT NULL,
    since_ms BIGINT NOT NULL,
    address  TEXT NOT NULL DEFAULT ''   -- where the other replicas send writes (http://host:port)
);
";

/// How to reach the database, and the lease's timing.
#[derive(Debug, Clone, PartialEq)]
pub struct PgOptions {
    /// `postgres://user:password@host:port/dbname?sslmode=require` (libpq's URL form).
    pub url: String,
    /// This replica's data directory: its snapshots and its lock (two replicas on one machine
    /// need two).
    pub data_dir: PathBuf,
    /// How long a starting writer waits for the lease; a standby waits as long as it takes.
    pub lease_wait: Duration,
    /// After how long without a sign of life the server ends the writer's session, and the
    /// lease with it. Shorter: faster failover; it must stay well above a commit's time.
    pub lease_timeout: Duration,
    /// A PEM file of CA certificates to trust for TLS, beside the web's roots.
    pub ca_file: Option<PathBuf>,
    /// The name this replica gives itself in the lease row (host:pid when empty).
    pub name: String,
}

impl PgOptions {
    pub fn new(url: impl Into<String>, data_dir: impl Into<PathBuf>) -> Self {
        PgOptions {
            url: url.into(),
            data_dir: data_dir.into(),
            lease_wait: Duration::from_secs(5),
            lease_timeout: Duration::from_secs(8),
            ca_file: None,
            name: String::new(),
        }
    }

    /// The URL without its password, for messages and logs.
    pub fn redacted(&self) -> String {
        redact(&self.url)
    }

    fn holder_name(&self) -> String {
        if !self.name.is_empty() {
            return self.name.clone();
        }
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "unknown-host".into());
        format!("{host}:{}", std::process::id())
    }
}

/// `url` with the password between `user:` and `@` replaced by `***`.
pub fn redact(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else {
        return url.to_string();
    };
    let (auth, host) = match rest.rsplit_once('@') {
        Some(x) => x,
        None => return url.to_string(),
    };
    match auth.split_once(':') {
        Some((user, _)) => format!("{scheme}://{user}:***@{host}"),
        None => url.to_string(),
    }
}

fn connect_err(o: &PgOptions, why: impl std::fmt::Display) -> StoreError {
    StoreError::Connect {
        url: o.redacted(),
        why: why.to_string(),
    }
}

/// The rustls client configuration: the web's roots (webpki-roots) plus the CA file's.
fn tls(o: &PgOptions) -> Result<tokio_postgres_rustls::MakeRustlsConnect, StoreError> {
    use rustls::pki_types::{pem::PemObject, CertificateDer};
    let mut roots = rustls::RootCertStore::empty();
    roots.extend(webpki_roots::TLS_SERVER_ROOTS.iter().cloned());
    if let Some(f) = &o.ca_file {
        let certs = CertificateDer::pem_file_iter(f)
            .map_err(|e| connect_err(o, format!("CA file {}: {e}", f.display())))?;
        for c in certs {
            let c = c.map_err(|e| connect_err(o, format!("CA file {}: {e}", f.display())))?;
            roots
                .add(c)
                .map_err(|e| connect_err(o, format!("CA file {}: {e}", f.display())))?;
        }
    }
    let provider = std::sync::Arc::new(rustls::crypto::ring::default_provider());
    let cfg = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| connect_err(o, e))?
        .with_root_certificates(roots)
        .with_no_client_auth();
    Ok(tokio_postgres_rustls::MakeRustlsConnect::new(cfg))
}

/// A session with the keepalives and timeouts that bound how long a dead peer holds it.
fn connect(o: &PgOptions, read_only: bool) -> Result<postgres::Client, StoreError> {
    let mut cfg = postgres::Config::from_str(&o.url).map_err(|e| connect_err(o, e))?;
    let secs = o.lease_timeout.as_secs().max(3);
    // Our side: give up on a server that stopped answering within the lease's timeout, so a
    // partitioned writer errors out instead of hanging past the point where a standby writes.
    cfg.application_name(if read_only {
        "vlmfuse-reader"
    } else {
        "vlmfuse-writer"
    })
    .connect_timeout(Duration::from_secs(secs))
    .keepalives(true)
    .keepalives_idle(Duration::from_secs((secs / 4).max(1)))
    .keepalives_interval(Duration::from_secs((secs / 4).max(1)))
    .keepalives_retries(3)
    .tcp_user_timeout(o.lease_timeout);
    let mut client = match cfg.get_ssl_mode() {
        postgres::config::SslMode::Disable => cfg.connect(postgres::NoTls),
        _ => cfg.connect(tls(o)?),
    }
    .map_err(|e| connect_err(o, e))?;
    // The server's side: end this session when its client has shown no sign of life for
    // `lease_timeout` (dead socket: keepalives and tcp_user_timeout; live socket but hung
    // process: idle_session_timeout, which a writer's heartbeat keeps from firing).
    let q = (secs / 4).max(1);
    let mut set = format!(
        "SET tcp_keepalives_idle = {q}; SET tcp_keepalives_interval = {q}; \
         SET tcp_keepalives_count = 3; SET tcp_user_timeout = {}; \
         SET idle_in_transaction_session_timeout = {};",
        o.lease_timeout.as_millis(),
        o.lease_timeout.as_millis()
    );
    if read_only {
        set.push_str("SET default_transaction_read_only = on;");
    } else {
        set.push_str(&format!(
            "SET idle_session_timeout = {};",
            o.lease_timeout.as_millis()
        ));
    }
    client.batch_execute(&set)?;
    Ok(client)
}

/// Who holds the lease, as its row says (empty before the first writer wrote it).
fn holder(db: &Db) -> String {
    let have = db
        .query_one("SELECT to_regclass('lease') IS NOT NULL", &[])
        .and_then(|r| r.bool(0))
        .unwrap_or(false);
    if !have {
        return "holder unknown".into();
    }
    match db.query_opt("SELECT holder, since_ms FROM lease WHERE id = 1", &[]) {
        Ok(Some(r)) => match (r.str(0), r.i64(1)) {
            (Ok(h), Ok(ms)) => format!(
                "{h}, writing for {:.1} s",
                (crate::timestamp_ms() - ms) as f64 / 1000.0
            ),
            _ => "holder unknown".into(),
        },
        _ => "holder unknown".into(),
    }
}

/// Takes the writer lease on `db`, polling for up to `wait`.
fn take_lease(db: &Db, o: &PgOptions, wait: Duration) -> Result<(), StoreError> {
    // `None`: wait without limit (a standby's `Duration::MAX`).
    let deadline = Instant::now().checked_add(wait);
    let mut logged = false;
    loop {
        let got = db
            .query_one("SELECT pg_try_advisory_lock(?1)", &[P::I(LEASE_KEY)])?
            .bool(0)?;
        if got {
            return Ok(());
        }
        if deadline.is_some_and(|d| Instant::now() >= d) {
            return Err(StoreError::Leased {
                url: o.redacted(),
                holder: holder(db),
            });
        }
        if !logged {
            tracing::info!(db = %o.redacted(), holder = %holder(db), "waiting for the writer lease");
            logged = true;
        }
        std::thread::sleep(LEASE_POLL);
    }
}

/// The writer lease this store holds: who (this replica's name) and since when.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LeaseHeld {
    pub holder: String,
    pub since_ms: i64,
    /// [`PgOptions::lease_timeout`]: past it without an answer from its session, the holder
    /// must assume the lease gone.
    pub timeout: Duration,
}

/// The writer's session: connected, holding the lease, the schema created or checked, the
/// lease row naming this replica.
pub(crate) fn open_writer(o: &PgOptions) -> Result<(Db, LeaseHeld), StoreError> {
    let db = Db::pg(connect(o, false)?);
    take_lease(&db, o, o.lease_wait)?;
    // Only the lease holder creates or migrates tables, so replicas starting together do not
    // race on the DDL.
    db.batch(SCHEMA)?;
    let version = db
        .query_opt("SELECT value FROM meta WHERE key = 'schema_version'", &[])?
        .map(|r| r.string(0))
        .transpose()?;
    match version {
        None => {
            db.exec(
                "INSERT INTO meta (key, value) VALUES ('schema_version', ?1)",
                &[P::T(&SCHEMA_VERSION.to_string())],
            )?;
        }
        Some(v) if v == SCHEMA_VERSION.to_string() => {}
        Some(v) => {
            return Err(StoreError::Mismatch(format!(
                "schema version {v}, this build reads {SCHEMA_VERSION}"
            )))
        }
    }
    let held = LeaseHeld {
        holder: o.holder_name(),
        since_ms: crate::timestamp_ms(),
        timeout: o.lease_timeout,
    };
    db.exec(
        "INSERT INTO lease (id, holder, since_ms, address) VALUES (1, ?1, ?2, '')
         ON CONFLICT(id) DO UPDATE SET holder = excluded.holder, since_ms = excluded.since_ms,
                                       address = ''",
        &[P::T(&held.holder), P::I(held.since_ms)],
    )?;
    tracing::info!(db = %o.redacted(), holder = %held.holder, "holding the writer lease");
    Ok((db, held))
}

/// The lease row as the others read it: who writes, since when, and where it takes writes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LeaseRow {
    pub holder: String,
    pub since_ms: i64,
    /// Empty until the writer listens.
    pub address: String,
}

/// A read-only session beside the writer.
pub(crate) fn open_reader(o: &PgOptions) -> Result<Db, StoreError> {
    Ok(Db::pg(connect(o, true)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn passwords_stay_out_of_messages() {
        assert_eq!(
            redact("postgres://vlm:s3cret@db:5432/state?sslmode=require"),
            "postgres://vlm:***@db:5432/state?sslmode=require"
        );
        assert_eq!(redact("postgres://db/state"), "postgres://db/state");
        assert_eq!(redact("host=db user=vlm"), "host=db user=vlm");
    }
}
