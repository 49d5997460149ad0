//! The service's configuration: one TOML file (`config/default.toml` documents every field),
//! then environment variables, then flags, each layer over the one before.
//!
//! Each section is one struct that is both the TOML table (serde) and its flags (clap): a field's
//! flag and environment variable are declared next to it, and clap reads both, so there is one
//! way to read the environment. clap parses `vlmfuse serve`'s command line once into
//! [`ServeArgs`]; [`Config::load`] reads the file (or the built-in defaults) and then applies
//! only the flags and variables that were actually given
//! (`FromArgMatches::update_from_arg_matches`), so a flag never resets a file value to a default.
//! Sections whose shape depends on a `kind` (`[[reporter]]`, `[labeler]`), the ontology and the
//! fusion parameters are file-only.
//!
//! Built-in defaults equal `config/default.toml` (a test holds them together), so running with no
//! file and running with the shipped file behave the same.

mod annotate;
mod detect;
mod embedder;
mod labeler;
mod media;
mod reporter;
mod server;
mod store;
mod ui;

pub use annotate::AnnotateSection;
pub use detect::DetectSection;
pub use embedder::{EmbedderBackend, EmbedderConfig};
pub use labeler::{
    EmbeddingLabelerConfig, EncoderEngine, GgufLabelerConfig, LabelerConfig, OpenAiLabelerConfig,
};
pub use media::MediaConfig;
pub use reporter::{ReporterBackend, ReporterEntry};
pub use server::{Limits, ServerConfig, DEFAULT_DATA_DIR, DEFAULT_LISTEN};
pub use store::StoreSection;
pub use ui::UiSection;

use anyhow::{bail, ensure, Context};
use clap::{ArgMatches, Args, FromArgMatches};
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use vlmfuse_fusion::{FusionConfig, Ontology};

/// The whole configuration file.
#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// Comma-separated reporter names, replacing the config's list; a report from any other
    /// name is refused.
    #[arg(
        long,
        env = "VLMFUSE_REPORTERS",
        value_delimiter = ',',
        value_parser = trimmed,
        required = false
    )]
    pub reporters: Vec<String>,
    /// Where scripts/fetch-assets.sh caches the labelers' model files; unset:
    /// `$HOME/.cache/vlmfuse-assets`.
    #[arg(long, env = "VLMFUSE_ASSETS", required = false)]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub assets_dir: Option<PathBuf>,
    #[command(flatten)]
    pub server: ServerConfig,
    /// Where the fusion state lives (SQLite under `server.data_dir`, or PostgreSQL).
    #[command(flatten)]
    pub store: StoreSection,
    #[command(flatten)]
    pub limits: Limits,
    #[arg(skip)]
    pub fusion: FusionConfig,
    #[arg(skip)]
    pub ontology: Ontology,
    /// Clip ingestion for /v1/infer.
    #[command(flatten)]
    pub media: MediaConfig,
    /// The context embedder; absent: /v1/infer answers 503 (a context is never invented). Its
    /// flags apply when the file configures one.
    #[arg(skip)]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub embedder: Option<EmbedderConfig>,
    /// The reporters /v1/infer runs; each `name` must be one of `reporters`.
    #[arg(skip)]
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub reporter: Vec<ReporterEntry>,
    /// Text -> labels for /v1/infer.
    #[arg(skip)]
    pub labeler: LabelerConfig,
    /// Labels derived from the vehicle's signals (`signals` tracks).
    #[command(flatten)]
    pub annotate: AnnotateSection,
    /// Labels derived from an object detector's tracks (off without `model`).
    #[command(flatten)]
    pub detect: DetectSection,
    /// The operator page (`/ui`).
    #[command(flatten)]
    pub ui: UiSection,
}

fn trimmed(s: &str) -> Result<String, std::convert::Infallible> {
    Ok(s.trim().to_string())
}

const DEFAULT_REPORTERS: [&str; 3] = ["vlaad", "videollama2", "videollava"];

impl Default for Config {
    fn default() -> Self {
        Self {
            reporters: DEFAULT_REPORTERS.map(String::from).to_vec(),
            assets_dir: None,
            server: ServerConfig::default(),
            store: StoreSection::default(),
            limits: Limits::default(),
            fusion: FusionConfig::default(),
            // The paper's labels with the glosses the labelers are evaluated with.
            ontology: Ontology::default_driving(),
            media: MediaConfig::default(),
            embedder: None,
            reporter: Vec::new(),
            labeler: LabelerConfig::default(),
            annotate: AnnotateSection::default(),
            detect: DetectSection::default(),
            ui: UiSection::default(),
        }
    }
}

/// `vlmfuse serve`'s command line: `--config FILE` plus every flag of [`Config`]. It keeps clap's
/// matches so that [`Config::load`] can apply the flags and variables that were given on top of
/// the file.
#[derive(Debug, Clone, Default)]
pub struct ServeArgs {
    /// TOML configuration file (see config/default.toml); built-in defaults without it.
    pub config: Option<PathBuf>,
    matches: ArgMatches,
}

impl ServeArgs {
    /// Parses a `serve` command line (`argv[0]` first), for tests and embedding.
    pub fn try_parse_from<I, T>(args: I) -> Result<Self, clap::Error>
    where
        I: IntoIterator<Item = T>,
        T: Into<std::ffi::OsString> + Clone,
    {
        let cmd = Self::augment_args(clap::Command::new("serve"));
        Self::from_arg_matches(&cmd.try_get_matches_from(args)?)
    }
}

impl FromArgMatches for ServeArgs {
    fn from_arg_matches(m: &ArgMatches) -> Result<Self, clap::Error> {
        Ok(Self {
            config: m.get_one::<PathBuf>("config").cloned(),
            matches: m.clone(),
        })
    }

    fn update_from_arg_matches(&mut self, m: &ArgMatches) -> Result<(), clap::Error> {
        *self = Self::from_arg_matches(m)?;
        Ok(())
    }
}

impl Args for ServeArgs {
    fn augment_args(cmd: clap::Command) -> clap::Command {
        let cmd = cmd.arg(
            clap::Arg::new("config")
                .long("config")
                .env("VLMFUSE_CONFIG")
                .value_name("FILE")
                .value_parser(clap::value_parser!(PathBuf))
                .help("TOML configuration file (see config/default.toml); built-in defaults without it"),
        );
        EmbedderConfig::augment_args(Config::augment_args(cmd))
    }

    fn augment_args_for_update(cmd: clap::Command) -> clap::Command {
        Self::augment_args(cmd)
    }
}

impl Config {
    /// Parses a TOML document and checks it.
    pub fn from_toml(text: &str) -> anyhow::Result<Self> {
        let cfg: Config = toml::from_str(text)?;
        cfg.validate()?;
        Ok(cfg)
    }

    pub fn from_file(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read config {}", path.display()))?;
        Self::from_toml(&text).with_context(|| format!("config {}", path.display()))
    }

    /// File (or defaults), then the flags and environment variables that were given.
    pub fn load(args: &ServeArgs) -> anyhow::Result<Self> {
        let mut cfg = match &args.config {
            Some(p) => Self::from_file(p)?,
            None => Self::default(),
        };
        cfg.update_from_arg_matches(&args.matches)?;
        if let Some(e) = &mut cfg.embedder {
            e.update_from_arg_matches(&args.matches)?;
        }
        // An empty variable (compose's `${VLMFUSE_API_KEY:-}`) means "no key", not "empty key";
        // the file itself may not say `api_key = ""` (refused when it was parsed).
        if cfg.server.api_key.as_deref().is_some_and(str::is_empty) {
            cfg.server.api_key = None;
        }
        cfg.validate()?;
        Ok(cfg)
    }

    /// Refuses what would only fail later, at the first request.
    pub fn validate(&self) -> anyhow::Result<()> {
        self.listen_addr()?;
        self.annotate.validate()?;
        self.detect.validate()?;
        if self.detect.model.is_some() {
            for r in &self.detect.rules.labels {
                ensure!(
                    self.ontology.lookup(&r.label).is_some(),
                    "detect.rules: label {:?} is not in the ontology",
                    r.label
                );
            }
        }
        self.ui.validate()?;
        if self.server.api_key.as_deref().is_some_and(str::is_empty) {
            bail!("api_key is empty; leave it out to disable authentication");
        }
        let l = &self.limits;
        ensure!(
            l.max_body_bytes > 0
                && l.concurrency_limit > 0
                && l.max_batch_rounds > 0
                && l.max_label_texts > 0
                && l.max_context_dim > 0,
            "limits must be at least 1"
        );
        seconds("limits.request_timeout_s", l.request_timeout_s)?;
        seconds("server.probe_interval_s", self.server.probe_interval_s)?;
        seconds(
            "server.header_read_timeout_s",
            self.server.header_read_timeout_s,
        )?;
        seconds("server.idle_timeout_s", self.server.idle_timeout_s)?;
        seconds("server.shutdown_timeout_s", self.server.shutdown_timeout_s)?;
        ensure!(
            self.server.snapshot_interval_s == 0.0
                || (self.server.snapshot_interval_s.is_finite()
                    && self.server.snapshot_interval_s > 0.0
                    && self.server.snapshot_interval_s <= MAX_SECONDS),
            "server.snapshot_interval_s must be 0 (off) or a number of seconds in (0, {MAX_SECONDS}], got {}",
            self.server.snapshot_interval_s
        );
        ensure!(
            self.server.snapshot_keep >= 1,
            "server.snapshot_keep must be at least 1"
        );
        seconds("media.upload_grace_s", self.media.upload_grace_s)?;
        ensure!(
            self.server.max_connections > 0
                && self.server.max_connections <= tokio::sync::Semaphore::MAX_PERMITS.min(1 << 24),
            "server.max_connections must be 1..={}, got {}",
            1 << 24,
            self.server.max_connections
        );
        ensure!(
            l.idempotency_ttl_s.is_finite()
                && l.idempotency_ttl_s > 0.0
                && l.idempotency_ttl_s <= 30.0 * MAX_SECONDS,
            "limits.idempotency_ttl_s must be a number of seconds in (0, {}], got {}",
            30.0 * MAX_SECONDS,
            l.idempotency_ttl_s
        );
        self.fusion.validate().map_err(anyhow::Error::msg)?;
        let m = &self.media;
        ensure!(
            m.frames > 0 && m.frames <= vlmfuse_media::MAX_SAMPLE_FRAMES,
            "media.frames must be 1..={}",
            vlmfuse_media::MAX_SAMPLE_FRAMES
        );
        ensure!(
            m.max_clips > 0 && m.max_bytes > 0,
            "media.max_clips and media.max_bytes must be at least 1"
        );
        seconds("media.request_timeout_s", m.request_timeout_s)?;
        ensure!(
            m.max_duration_s.is_finite() && m.max_duration_s > 0.0,
            "media.max_duration_s must be a positive number of seconds, got {}",
            m.max_duration_s
        );
        let mut seen = std::collections::BTreeSet::new();
        for r in &self.reporter {
            let name = r.name();
            ensure!(
                self.reporters.contains(&name),
                "[[reporter]] {name:?} is not in `reporters` ({:?})",
                self.reporters
            );
            ensure!(
                seen.insert(name.clone()),
                "[[reporter]] {name:?} is configured twice"
            );
            seconds(
                &format!("[[reporter]] {name:?}: round_timeout_s"),
                r.round_timeout_s,
            )?;
        }
        if let LabelerConfig::Openai(o) = &self.labeler {
            if let Some(t) = o.timeout_s {
                seconds("labeler.timeout_s", t)?;
            }
        }
        Ok(())
    }

    /// The socket edge's limits ([`crate::conn`]); validated durations.
    pub fn conn_limits(&self) -> crate::conn::ConnLimits {
        let s = &self.server;
        crate::conn::ConnLimits {
            header_read_timeout: std::time::Duration::from_secs_f64(s.header_read_timeout_s),
            idle_timeout: std::time::Duration::from_secs_f64(s.idle_timeout_s),
            max_connections: s.max_connections,
            shutdown_timeout: std::time::Duration::from_secs_f64(s.shutdown_timeout_s),
        }
    }

    pub fn listen_addr(&self) -> anyhow::Result<SocketAddr> {
        self.server
            .listen
            .parse()
            .with_context(|| format!("listen address {:?} is not host:port", self.server.listen))
    }

    /// Where `/v1/infer` spools uploads: `media.temp_dir`, else `spool/` under the data
    /// directory. Per data directory (one server each), so the server may clear it at startup
    /// of what a killed run left behind without touching another instance's uploads.
    pub fn spool_dir(&self) -> std::path::PathBuf {
        self.media
            .temp_dir
            .clone()
            .unwrap_or_else(|| self.server.data_dir.join("spool"))
    }

    /// Where the fetched labeler models live.
    pub fn assets(&self) -> vlmfuse_labeler::assets::AssetPaths {
        match &self.assets_dir {
            Some(root) => vlmfuse_labeler::assets::AssetPaths::under(root),
            None => vlmfuse_labeler::assets::AssetPaths::default_cache(),
        }
    }
}

/// A duration field: positive, finite and at most a day, so that every later
/// `Duration::from_secs_f64` holds it (`1e20` would panic on every request, `NaN` would switch
/// the check it feeds off). Named in the error.
fn seconds(field: &str, v: f64) -> anyhow::Result<()> {
    ensure!(
        v.is_finite() && v > 0.0 && v <= MAX_SECONDS,
        "{field} must be a number of seconds in (0, {MAX_SECONDS}], got {v}"
    );
    Ok(())
}

/// The longest timeout a config may set: one day.
const MAX_SECONDS: f64 = 86_400.0;

#[cfg(test)]
mod tests;
