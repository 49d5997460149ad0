//! `[store]`: where the fusion state lives. The embedded SQLite file under `server.data_dir` by
//! default; with `url`, a PostgreSQL database that any number of replicas share, one of them
//! the writer at a time (docs/ARCHITECTURE.md, "Replicas").

use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::time::Duration;

#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StoreSection {
    /// PostgreSQL URL (`postgres://user:password@host:5432/db?sslmode=require`); unset: the
    /// embedded SQLite database under `server.data_dir`. The data directory then keeps only this
    /// replica's snapshots and lock. Prefer the environment to a file: it may hold a password.
    #[arg(
        long = "store-url",
        id = "store-url",
        env = "VLMFUSE_STORE_URL",
        hide_env_values = true,
        required = false
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub url: Option<String>,
    /// Seconds a starting replica waits for the writer lease before it follows the holder
    /// instead. A standby (`standby = true`) waits as long as it takes.
    #[arg(
        long = "store-lease-wait-s",
        id = "store-lease-wait-s",
        env = "VLMFUSE_STORE_LEASE_WAIT_S",
        required = false
    )]
    pub lease_wait_s: f64,
    /// Wait for the writer lease without limit before serving (active-passive): this replica
    /// opens its port only once it writes. Off (the default), a replica that does not get the
    /// lease follows the writer: it serves, forwards writes to it, and takes over when the
    /// writer's session ends.
    #[arg(
        long = "store-standby",
        id = "store-standby",
        env = "VLMFUSE_STORE_STANDBY",
        action = clap::ArgAction::Set,
        required = false
    )]
    pub standby: bool,
    /// Seconds without a sign of life after which the database server ends the writer's
    /// session and with it the lease (keepalives, TCP user timeout, idle-session timeout): the
    /// bound on failover. The writer touches its session every second.
    #[arg(
        long = "store-lease-timeout-s",
        id = "store-lease-timeout-s",
        env = "VLMFUSE_STORE_LEASE_TIMEOUT_S",
        required = false
    )]
    pub lease_timeout_s: f64,
    /// PEM file of CA certificates to trust for the database's TLS, beside the web's roots.
    #[arg(
        long = "store-ca-file",
        id = "store-ca-file",
        env = "VLMFUSE_STORE_CA_FILE",
        required = false
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ca_file: Option<PathBuf>,
    /// This replica's name in the lease row, `/readyz` and the metrics; empty: host:pid.
    #[arg(
        long = "store-replica-name",
        id = "store-replica-name",
        env = "VLMFUSE_STORE_REPLICA_NAME",
        required = false
    )]
    pub replica_name: String,
    /// The URL the other replicas send this one's writes to while it holds the lease
    /// (`http://vlmfuse-1:8080`); unset: the address it listens on (the host's name for a
    /// wildcard address).
    #[arg(
        long = "store-advertise-url",
        id = "store-advertise-url",
        env = "VLMFUSE_STORE_ADVERTISE_URL",
        required = false
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub advertise_url: Option<String>,
}

impl Default for StoreSection {
    fn default() -> Self {
        Self {
            url: None,
            lease_wait_s: 1.0,
            standby: false,
            lease_timeout_s: 8.0,
            ca_file: None,
            replica_name: String::new(),
            advertise_url: None,
        }
    }
}

impl StoreSection {
    /// Where the state lives, for a replica whose data directory is `data_dir`.
    pub fn location(&self, data_dir: &std::path::Path) -> vlmfuse_store::Location {
        match &self.url {
            None => vlmfuse_store::Location::Sqlite {
                dir: data_dir.to_path_buf(),
            },
            Some(url) => {
                let mut o = vlmfuse_store::pg::PgOptions::new(url.clone(), data_dir);
                o.lease_wait = if self.standby {
                    Duration::MAX
                } else {
                    Duration::from_secs_f64(self.lease_wait_s.max(0.0))
                };
                o.lease_timeout = Duration::from_secs_f64(self.lease_timeout_s.max(3.0));
                o.ca_file = self.ca_file.clone();
                o.name = self.replica_name.clone();
                vlmfuse_store::Location::Postgres(o)
            }
        }
    }
}
