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
    /// Clip ingestion for /v1/infer.
    pub media: MediaConfig,
    /// The context embedder; absent: /v1/infer answers 503 (a context is never invented).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub embedder: Option<EmbedderConfig>,
    /// The reporters /v1/infer runs; each `name` must be one of `reporters`.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub reporter: Vec<ReporterEntry>,
    /// Text -> labels for /v1/infer.
    pub labeler: LabelerConfig,
}

/// `[media]`: what an upload may be and how it is sampled.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MediaConfig {
    /// Frames sampled uniformly per clip.
    pub frames: usize,
    /// Frames are scaled so their shorter side is this many pixels (0: the clip's own size).
    pub frame_short_side: u32,
    /// Most `video` parts in one request.
    pub max_clips: usize,
    /// Bytes per clip, enforced while streaming the upload (413 above).
    pub max_bytes: u64,
    pub max_duration_s: f64,
    pub max_width: u32,
    pub max_height: u32,
    /// Seconds one /v1/infer request may take (replaces limits.request_timeout_s there).
    pub request_timeout_s: f64,
    /// Where uploads are spooled; unset: the system temporary directory.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub temp_dir: Option<PathBuf>,
}

impl Default for MediaConfig {
    fn default() -> Self {
        let l = vlmfuse_media::MediaLimits::default();
        Self {
            frames: 8,
            frame_short_side: 448,
            max_clips: 4,
            max_bytes: l.max_bytes,
            max_duration_s: l.max_duration_s,
            max_width: l.max_width,
            max_height: l.max_height,
            request_timeout_s: 300.0,
            temp_dir: None,
        }
    }
}

impl MediaConfig {
    pub fn limits(&self) -> vlmfuse_media::MediaLimits {
        vlmfuse_media::MediaLimits {
            max_bytes: self.max_bytes,
            max_duration_s: self.max_duration_s,
            max_width: self.max_width,
            max_height: self.max_height,
            // max_frames_decoded and decode_threads: the media crate's defaults until the
            // service config grows fields for them (issue 10, phase 2).
            ..vlmfuse_media::MediaLimits::default()
        }
    }

    pub fn sample_options(&self) -> vlmfuse_media::SampleOptions {
        vlmfuse_media::SampleOptions {
            frames: self.frames,
            size: if self.frame_short_side == 0 {
                vlmfuse_media::FrameSize::Native
            } else {
                vlmfuse_media::FrameSize::ShortSide(self.frame_short_side)
            },
        }
    }
}

/// `[embedder]`: a CLIP image tower.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EmbedderConfig {
    /// `{ path = "/models/clip" }` or `{ hub = "openai/clip-vit-base-patch32", revision = "main" }`.
    pub weights: vlmfuse_models::WeightSource,
    /// `"cpu"`, `"cuda"` or `"cuda:N"` (CUDA needs the `cuda` build feature).
    #[serde(default = "cpu")]
    pub device: String,
}

fn cpu() -> String {
    "cpu".into()
}

/// One `[[reporter]]`: a backend (`kind`) plus the round's timeout for it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReporterEntry {
    /// Seconds this reporter may take in a round (retries included) before it is left out.
    #[serde(default = "default_reporter_timeout")]
    pub round_timeout_s: f64,
    #[serde(flatten)]
    pub backend: ReporterBackend,
}

fn default_reporter_timeout() -> f64 {
    120.0
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum ReporterBackend {
    /// Any OpenAI-compatible chat-completions server (vLLM, SGLang, llama.cpp, ...).
    Openai(vlmfuse_models::OpenAiReporterConfig),
    /// In-process Qwen3-VL on candle.
    Candle(vlmfuse_models::CandleVlmConfig),
}

impl ReporterEntry {
    pub fn name(&self) -> String {
        match &self.backend {
            ReporterBackend::Openai(c) => c.name.clone().unwrap_or_else(|| c.model.clone()),
            ReporterBackend::Candle(c) => c.name.clone(),
        }
    }
}

/// `[labeler]`: which backend maps reporter text to ontology labels.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LabelerConfig {
    /// `"embedding"` (offline default, all-MiniLM-L6-v2), `"openai"` or `"gguf"`.
    pub kind: LabelerKind,
    /// embedding: the MiniLM directory; unset: `$VLMFUSE_ASSETS/minilm` (scripts/fetch-assets.sh).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_dir: Option<PathBuf>,
    /// gguf: the model file; unset: the fetched gemma-3-270m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_path: Option<PathBuf>,
    /// embedding/gguf: decision threshold; unset: the backend's tuned default.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub threshold: Option<f32>,
    /// openai: server base URL and model.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub base_url: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    /// openai: name of the environment variable holding the API key.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub api_key_env: Option<String>,
    /// openai: ask for `response_format: json_object`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub json_mode: Option<bool>,
    /// openai: seconds per request.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub timeout_s: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LabelerKind {
    #[default]
    Embedding,
    Openai,
    Gguf,
}

impl Default for LabelerConfig {
    fn default() -> Self {
        Self {
            kind: LabelerKind::Embedding,
            model_dir: None,
            model_path: None,
            threshold: None,
            base_url: None,
            model: None,
            api_key_env: None,
            json_mode: None,
            timeout_s: None,
        }
    }
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
            media: MediaConfig::default(),
            embedder: None,
            reporter: Vec::new(),
            labeler: LabelerConfig::default(),
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
        cfg.apply_env(|k| std::env::var(k).ok())?;
        if let Ok(v) = std::env::var("VLMFUSE_DEBUG_FUSE_DELAY_MS") {
            cfg.limits.debug_fuse_delay_ms = v
                .parse()
                .map_err(|_| format!("VLMFUSE_DEBUG_FUSE_DELAY_MS={v:?} is not a number"))?;
        }
        cfg.validate()?;
        Ok(cfg)
    }

    /// Scalar fields of the clip pipeline from the environment (`VLMFUSE_MEDIA_FRAMES`, ...).
    fn apply_env(&mut self, get: impl Fn(&str) -> Option<String>) -> Result<(), String> {
        fn num<T: std::str::FromStr>(k: &str, v: &str) -> Result<T, String> {
            v.trim()
                .parse()
                .map_err(|_| format!("{k}={v:?} is not a valid number"))
        }
        let m = &mut self.media;
        let get = |k: &str| get(k).filter(|v| !v.is_empty()).map(|v| (k.to_string(), v));
        if let Some((k, v)) = get("VLMFUSE_MEDIA_FRAMES") {
            m.frames = num(&k, &v)?;
        }
        if let Some((k, v)) = get("VLMFUSE_MEDIA_MAX_CLIPS") {
            m.max_clips = num(&k, &v)?;
        }
        if let Some((k, v)) = get("VLMFUSE_MEDIA_MAX_BYTES") {
            m.max_bytes = num(&k, &v)?;
        }
        if let Some((k, v)) = get("VLMFUSE_MEDIA_MAX_DURATION_S") {
            m.max_duration_s = num(&k, &v)?;
        }
        if let Some((k, v)) = get("VLMFUSE_MEDIA_REQUEST_TIMEOUT_S") {
            m.request_timeout_s = num(&k, &v)?;
        }
        if let Some((_, v)) = get("VLMFUSE_MEDIA_TEMP_DIR") {
            m.temp_dir = Some(v.into());
        }
        if let Some((_, v)) = get("VLMFUSE_EMBEDDER_DEVICE") {
            if let Some(e) = &mut self.embedder {
                e.device = v;
            }
        }
        if let Some((k, v)) = get("VLMFUSE_LABELER_KIND") {
            self.labeler.kind = serde_json::from_value(serde_json::Value::String(v.clone()))
                .map_err(|_| format!("{k}={v:?}: expected embedding, openai or gguf"))?;
        }
        if let Some((_, v)) = get("VLMFUSE_LABELER_MODEL_DIR") {
            self.labeler.model_dir = Some(v.into());
        }
        Ok(())
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
        let m = &self.media;
        if m.frames == 0 || m.frames > vlmfuse_media::MAX_SAMPLE_FRAMES {
            return Err(format!(
                "media.frames must be 1..={}",
                vlmfuse_media::MAX_SAMPLE_FRAMES
            ));
        }
        if m.max_clips == 0 || m.max_bytes == 0 {
            return Err("media.max_clips and media.max_bytes must be at least 1".into());
        }
        if !(m.request_timeout_s.is_finite() && m.request_timeout_s > 0.0) {
            return Err("media.request_timeout_s must be a positive number".into());
        }
        let mut seen = std::collections::BTreeSet::new();
        for r in &self.reporter {
            let name = r.name();
            if !self.reporters.contains(&name) {
                return Err(format!(
                    "[[reporter]] {name:?} is not in `reporters` ({:?})",
                    self.reporters
                ));
            }
            if !seen.insert(name.clone()) {
                return Err(format!("[[reporter]] {name:?} is configured twice"));
            }
            if !(r.round_timeout_s.is_finite() && r.round_timeout_s > 0.0) {
                return Err(format!(
                    "[[reporter]] {name:?}: round_timeout_s must be a positive number"
                ));
            }
        }
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

    /// The commented examples of config/default.toml, uncommented, are a valid config.
    #[test]
    fn the_commented_pipeline_examples_parse() {
        let mut text = String::new();
        let mut on = false;
        for line in SHIPPED.lines() {
            if line.starts_with("# [embedder]") {
                on = true;
            }
            if line.starts_with("# Text -> labels") {
                on = false;
            }
            if on {
                if let Some(rest) = line.strip_prefix("# ") {
                    let toml_line = rest.starts_with('[') || rest.contains(" = ");
                    if toml_line && !rest.starts_with('#') {
                        text.push_str(rest);
                        text.push('\n');
                    }
                }
            }
        }
        let text = format!("reporters = [\"vlaad\", \"videollama2\"]\n{text}");
        let cfg = Config::from_toml(&text).unwrap_or_else(|e| panic!("{e}\n{text}"));
        assert_eq!(cfg.reporter.len(), 2);
        assert_eq!(cfg.reporter[0].name(), "videollama2");
        assert_eq!(cfg.reporter[0].round_timeout_s, 180.0);
        match &cfg.reporter[1].backend {
            ReporterBackend::Candle(c) => {
                assert_eq!(c.device, "cuda:1");
                assert!(c.adapter.is_some());
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(cfg.embedder.unwrap().device, "cpu");
        // A reporter whose name is not in `reporters` is refused.
        let bad = text.replace("name = \"vlaad\"", "name = \"nobody\"");
        assert!(Config::from_toml(&bad).is_err());
    }
}
