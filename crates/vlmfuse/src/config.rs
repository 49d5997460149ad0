//! The service's configuration: one TOML file (`config/default.toml` documents every field),
//! then environment variables, then flags, each layer over the one before.
//!
//! Built-in defaults equal `config/default.toml` (a test holds them together), so running with no
//! file and running with the shipped file behave the same. Later issues add sections (`[media]`,
//! `[embedder]`, `[[reporter]]`, `[labeler]`) as new fields of [`Config`].

use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use vlmfuse_fusion::{FusionConfig, Ontology};

/// Flags of `vlmfuse serve`. Each also reads an environment variable; a flag or variable that is
/// set wins over the config file.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct ServeArgs {
    /// TOML configuration file (see config/default.toml); built-in defaults without it.
    #[arg(long, env = "VLMFUSE_CONFIG")]
    pub config: Option<PathBuf>,
    /// Address to listen on [default: 127.0.0.1:8080].
    #[arg(long, env = "VLMFUSE_LISTEN")]
    pub listen: Option<String>,
    /// Directory of the embedded database [default: ./data].
    #[arg(long, env = "VLMFUSE_DATA_DIR")]
    pub data_dir: Option<PathBuf>,
    /// Bearer token required on the writing routes (/v1/fuse, /v1/infer, /v1/feedback).
    #[arg(long, env = "VLMFUSE_API_KEY", hide_env_values = true)]
    pub api_key: Option<String>,
    /// Largest request body in bytes (413 above).
    #[arg(long, env = "VLMFUSE_MAX_BODY_BYTES")]
    pub max_body_bytes: Option<usize>,
    /// Requests in flight on the /v1 routes before new ones get 429.
    #[arg(long, env = "VLMFUSE_CONCURRENCY_LIMIT")]
    pub concurrency_limit: Option<usize>,
    /// Seconds before a request is answered 503 (timeout).
    #[arg(long, env = "VLMFUSE_REQUEST_TIMEOUT_S")]
    pub request_timeout_s: Option<f64>,
    /// Most rounds in one `{"rounds": [...]}` request to /v1/fuse.
    #[arg(long, env = "VLMFUSE_MAX_BATCH_ROUNDS")]
    pub max_batch_rounds: Option<usize>,
    /// Comma-separated reporter names, replacing the config's list.
    #[arg(long, env = "VLMFUSE_REPORTERS", value_delimiter = ',')]
    pub reporters: Option<Vec<String>>,
}

/// The whole configuration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// Reporter names; a report from any other name is refused.
    pub reporters: Vec<String>,
    pub server: ServerConfig,
    pub limits: Limits,
    pub fusion: FusionConfig,
    pub ontology: Ontology,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    pub listen: String,
    pub data_dir: PathBuf,
    /// Bearer token for the writing routes; `None` leaves them open (a loopback default).
    pub api_key: Option<String>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    pub max_body_bytes: usize,
    pub concurrency_limit: usize,
    pub request_timeout_s: f64,
    pub max_batch_rounds: usize,
    /// Test-only: milliseconds every /v1/fuse request sleeps before answering, so that tests can
    /// fill the concurrency limit deterministically. 0 (the default) in any real deployment; not
    /// in config/default.toml on purpose.
    #[serde(skip_serializing_if = "is_zero")]
    pub debug_fuse_delay_ms: u64,
}

fn is_zero(v: &u64) -> bool {
    *v == 0
}

pub const DEFAULT_LISTEN: &str = "127.0.0.1:8080";
pub const DEFAULT_DATA_DIR: &str = "./data";
const DEFAULT_REPORTERS: [&str; 3] = ["vlaad", "videollama2", "videollava"];

impl Default for Config {
    fn default() -> Self {
        Self {
            reporters: DEFAULT_REPORTERS.map(String::from).to_vec(),
            server: ServerConfig::default(),
            limits: Limits::default(),
            fusion: FusionConfig::default(),
            ontology: Ontology::paper(),
        }
    }
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            listen: DEFAULT_LISTEN.into(),
            data_dir: DEFAULT_DATA_DIR.into(),
            api_key: None,
        }
    }
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_body_bytes: 8 * 1024 * 1024,
            concurrency_limit: 512,
            request_timeout_s: 30.0,
            max_batch_rounds: 1024,
            debug_fuse_delay_ms: 0,
        }
    }
}

impl Config {
    /// Parses a TOML document and checks it.
    pub fn from_toml(text: &str) -> Result<Self, String> {
        let cfg: Config = toml::from_str(text).map_err(|e| e.to_string())?;
        cfg.validate()?;
        Ok(cfg)
    }

    pub fn from_file(path: &Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read config {}: {e}", path.display()))?;
        Self::from_toml(&text).map_err(|e| format!("config {}: {e}", path.display()))
    }

    /// File (or defaults), then flags and environment (clap has already merged those two).
    pub fn load(args: &ServeArgs) -> Result<Self, String> {
        let mut cfg = match &args.config {
            Some(p) => Self::from_file(p)?,
            None => Self::default(),
        };
        if let Some(v) = &args.listen {
            cfg.server.listen = v.clone();
        }
        if let Some(v) = &args.data_dir {
            cfg.server.data_dir = v.clone();
        }
        // An empty variable (compose's `${VLMFUSE_API_KEY:-}`) means "no key", not "empty key".
        if let Some(v) = args.api_key.as_ref().filter(|v| !v.is_empty()) {
            cfg.server.api_key = Some(v.clone());
        }
        if let Some(v) = args.max_body_bytes {
            cfg.limits.max_body_bytes = v;
        }
        if let Some(v) = args.concurrency_limit {
            cfg.limits.concurrency_limit = v;
        }
        if let Some(v) = args.request_timeout_s {
            cfg.limits.request_timeout_s = v;
        }
        if let Some(v) = args.max_batch_rounds {
            cfg.limits.max_batch_rounds = v;
        }
        if let Some(v) = &args.reporters {
            cfg.reporters = v.iter().map(|s| s.trim().to_string()).collect();
        }
        if let Ok(v) = std::env::var("VLMFUSE_DEBUG_FUSE_DELAY_MS") {
            cfg.limits.debug_fuse_delay_ms = v
                .parse()
                .map_err(|_| format!("VLMFUSE_DEBUG_FUSE_DELAY_MS={v:?} is not a number"))?;
        }
        cfg.validate()?;
        Ok(cfg)
    }

    /// Refuses what would only fail later, at the first request.
    pub fn validate(&self) -> Result<(), String> {
        self.listen_addr()?;
        if let Some(k) = &self.server.api_key {
            if k.is_empty() {
                return Err("api_key is empty; leave it out to disable authentication".into());
            }
        }
        let l = &self.limits;
        if l.max_body_bytes == 0 || l.concurrency_limit == 0 || l.max_batch_rounds == 0 {
            return Err("limits must be at least 1".into());
        }
        if !(l.request_timeout_s.is_finite() && l.request_timeout_s > 0.0) {
            return Err("limits.request_timeout_s must be a positive number".into());
        }
        self.fusion.validate()?;
        Ontology::new(self.ontology.labels().to_vec())?;
        Ok(())
    }

    pub fn listen_addr(&self) -> Result<SocketAddr, String> {
        self.server
            .listen
            .parse()
            .map_err(|_| format!("listen address {:?} is not host:port", self.server.listen))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SHIPPED: &str = include_str!("../../../config/default.toml");

    #[test]
    fn the_shipped_file_equals_the_builtin_defaults() {
        let file = Config::from_toml(SHIPPED).unwrap();
        assert_eq!(file, Config::default());
    }

    #[test]
    fn the_shipped_file_sets_every_field() {
        // Every key the defaults serialise must appear in the file, so the file documents all.
        let defaults = toml::Value::try_from(Config::default()).unwrap();
        let file: toml::Value = toml::from_str(SHIPPED).unwrap();
        fn keys(v: &toml::Value, prefix: &str, out: &mut Vec<String>) {
            if let toml::Value::Table(t) = v {
                for (k, v) in t {
                    let p = format!("{prefix}{k}");
                    out.push(p.clone());
                    keys(v, &format!("{p}."), out);
                }
            }
        }
        let (mut a, mut b) = (Vec::new(), Vec::new());
        keys(&defaults, "", &mut a);
        keys(&file, "", &mut b);
        for k in a {
            assert!(b.contains(&k), "config/default.toml does not set {k}");
        }
    }

    #[test]
    fn flags_override_the_file_and_typos_are_refused() {
        let args = ServeArgs {
            listen: Some("127.0.0.1:9".into()),
            reporters: Some(vec!["a".into(), " b".into()]),
            ..Default::default()
        };
        let cfg = Config::load(&args).unwrap();
        assert_eq!(cfg.server.listen, "127.0.0.1:9");
        assert_eq!(cfg.reporters, vec!["a", "b"]);
        assert!(Config::from_toml("reporter = [\"a\"]").is_err());
        assert!(Config::from_toml("[fusion]\nkk = 3").is_err());
        assert!(Config::from_toml("[server]\nlisten = \"nowhere\"").is_err());
    }
}
