//! The clip pipeline's components (embedder, reporters, labeler), loaded once at startup.
//!
//! A component that is configured but fails to load is kept out and named in `/readyz` (503); one
//! that is simply not configured is named too, but only `/v1/infer` refuses (503) because of it:
//! `/v1/fuse` does not need it.

use crate::config::{Config, EmbedderBackend, EncoderEngine, LabelerConfig, ReporterBackend};
use anyhow::{bail, Context};
use std::sync::Arc;
use std::time::Duration;
use vlmfuse_labeler::Labeler;
use vlmfuse_models::{BackendPool, Embedder, PoolConfig, Reporter, RoundReporter};

#[derive(Default)]
pub struct Pipeline {
    pub embedder: Option<Arc<Embedder>>,
    pub reporters: Vec<RoundReporter>,
    pub labeler: Option<Arc<dyn Labeler>>,
    /// The object detector (`[detect] model`), run on the blocking pool; its session runs one
    /// frame at a time.
    pub detector: Option<Arc<vlmfuse_detect::Detector>>,
    /// Name of the labeler, as responses report it.
    pub labeler_name: String,
    /// Configured components that failed to load: `/readyz` answers 503 while any is listed.
    pub failed: Vec<String>,
    /// Components /v1/infer needs but the config leaves out.
    pub not_configured: Vec<String>,
    /// Configured reporters that failed to load (also in `failed`): /v1/infer runs without
    /// them and names them in every response's `failed`.
    pub unloaded_reporters: Vec<(String, String)>,
    /// The loaded remote reporters, which the readiness probe asks `GET /v1/models`.
    pub remote: Vec<(String, Arc<vlmfuse_models::OpenAiReporter>)>,
    /// Without a clip pipeline the labeler is not loaded at startup; `/v1/label` loads it here.
    lazy_labeler: Option<Arc<LazyLabeler>>,
}

/// Everything a labeler is built from: the `[labeler]` table, the ontology (with the configured
/// descriptions, which the LLM labelers' prompt shows) and where the fetched models live.
#[derive(Clone)]
struct LabelerSpec {
    config: LabelerConfig,
    ontology: vlmfuse_labeler::Ontology,
    assets: vlmfuse_labeler::assets::AssetPaths,
}

struct LazyLabeler {
    spec: LabelerSpec,
    /// Set once a load succeeds; a failed load is retried by the next call (after the operator
    /// fetched the model, say), and concurrent first calls wait for one load.
    cell: tokio::sync::OnceCell<Arc<dyn Labeler>>,
}

/// Why the labeler cannot be used.
#[derive(Debug)]
pub struct LabelerUnavailable(pub String);

impl Pipeline {
    /// Why /v1/infer cannot run, or empty when it can. A reporter that failed to load does not
    /// block it while another reporter is loaded: the rounds are fused over those that are.
    pub fn infer_blockers(&self) -> Vec<String> {
        let mut out = self.not_configured.clone();
        out.extend(
            self.failed
                .iter()
                .filter(|f| !f.starts_with("reporter ") || self.reporters.is_empty())
                .cloned(),
        );
        out
    }

    /// The labeler for `POST /v1/label`: the one loaded at startup, or (without a clip
    /// pipeline) the one loaded on first use.
    pub async fn label_route_labeler(&self) -> Result<Arc<dyn Labeler>, LabelerUnavailable> {
        if let Some(l) = &self.labeler {
            return Ok(l.clone());
        }
        let Some(lazy) = &self.lazy_labeler else {
            let why = self
                .failed
                .iter()
                .find(|f| f.starts_with("labeler"))
                .cloned()
                .unwrap_or_else(|| "labeler: not loaded".into());
            return Err(LabelerUnavailable(why));
        };
        if let Some(l) = lazy.cell.get() {
            return Ok(l.clone());
        }
        // The load runs in its own task: a request that times out (a big model loads for longer
        // than a request may take) leaves it running, and the next request finds it done
        // instead of starting it again.
        let lazy = lazy.clone();
        tokio::spawn(async move {
            lazy.cell
                .get_or_try_init(|| async {
                    let spec = lazy.spec.clone();
                    let t0 = std::time::Instant::now();
                    let l = tokio::task::spawn_blocking(move || spec.load())
                        .await
                        .map_err(|e| LabelerUnavailable(format!("labeler: load panicked: {e}")))?
                        .map_err(|e| {
                            let why = one_line(&e);
                            tracing::error!("labeler not loaded: {why}");
                            LabelerUnavailable(format!("labeler: {why}"))
                        })?;
                    tracing::info!(
                        labeler = l.name(),
                        secs = t0.elapsed().as_secs_f64(),
                        "labeler loaded on first use"
                    );
                    Ok(l)
                })
                .await
                .cloned()
        })
        .await
        .map_err(|e| LabelerUnavailable(format!("labeler: load failed: {e}")))?
    }

    /// Loads every configured component; blocking loads run on the blocking pool, in parallel.
    pub async fn load(cfg: &Config) -> Pipeline {
        let mut p = Pipeline::default();

        // Embedder.
        let embedder = cfg.embedder.clone().map(|e| {
            tokio::task::spawn_blocking(move || {
                let model: Arc<dyn vlmfuse_models::ContextEmbedder> = match e.backend {
                    EmbedderBackend::Candle => {
                        let device = vlmfuse_models::parse_device(&e.device)?;
                        Arc::new(
                            vlmfuse_models::ClipEmbedder::load(&e.weights, &device).with_context(
                                || format!("{} ({})", e.weights.describe(), e.device),
                            )?,
                        )
                    }
                    EmbedderBackend::Onnx => {
                        if e.device != "cpu" {
                            anyhow::bail!(
                                "backend = \"onnx\" runs on the CPU; device {:?} needs backend = \"candle\"",
                                e.device
                            );
                        }
                        let oc = vlmfuse_models::OnnxClipConfig {
                            weights: e.weights.clone(),
                            model_file: e.model_file.clone(),
                            session: vlmfuse_ort::SessionOptions {
                                threads: e.threads,
                                library: e.onnx_library.clone(),
                            },
                        };
                        Arc::new(
                            vlmfuse_models::OnnxClipEmbedder::load(&oc).with_context(|| {
                                format!("{} (onnx)", e.weights.describe())
                            })?,
                        )
                    }
                };
                let pool = Embedder::new(model, PoolConfig::default())
                    .context("embedder worker")?;
                anyhow::Ok(Arc::new(pool))
            })
        });

        // Reporters.
        let reporters: Vec<_> = cfg
            .reporter
            .iter()
            .cloned()
            .map(|entry| {
                let name = entry.name();
                let timeout = Duration::from_secs_f64(entry.round_timeout_s);
                let name_for_pool = name.clone();
                type Loaded = (
                    Arc<dyn Reporter>,
                    Option<Arc<vlmfuse_models::OpenAiReporter>>,
                );
                let task = tokio::task::spawn_blocking(move || -> anyhow::Result<Loaded> {
                    Ok(match entry.backend {
                        ReporterBackend::Openai(mut c) => {
                            c.name = Some(entry_name(&c.name, &c.model));
                            let r = Arc::new(vlmfuse_models::OpenAiReporter::new(c)?);
                            (r.clone() as Arc<dyn Reporter>, Some(r))
                        }
                        ReporterBackend::Candle(c) => {
                            let r = vlmfuse_models::CandleVlmReporter::load(c)?;
                            let pool =
                                BackendPool::new(name_for_pool, Arc::new(r), PoolConfig::default())
                                    .context("reporter worker")?;
                            (Arc::new(pool) as Arc<dyn Reporter>, None)
                        }
                    })
                });
                (name, timeout, task)
            })
            .collect();

        // Labeler: loaded at startup only when there is a clip pipeline to serve; a
        // /v1/fuse-only deployment must not load (or be unready for lack of) a model it never
        // uses. There, `POST /v1/label` loads it on first use.
        let wanted = cfg.embedder.is_some() || !cfg.reporter.is_empty();
        let spec = LabelerSpec {
            // The labeler and the engine share one ontology type (with the configured
            // descriptions): no translation.
            ontology: cfg.ontology.clone(),
            assets: cfg.assets(),
            config: cfg.labeler.clone(),
        };
        let labeler = wanted.then(|| {
            let spec = spec.clone();
            tokio::task::spawn_blocking(move || spec.load())
        });

        // Detector.
        let assets = cfg.assets();
        let detector = cfg.detect.detector_config().map(|mut dc| {
            if dc.session.library.is_none() {
                dc.session.library = onnx_library(&assets);
            }
            tokio::task::spawn_blocking(move || {
                vlmfuse_detect::Detector::load(&dc)
                    .map(Arc::new)
                    .with_context(|| format!("detector {}", dc.model.display()))
            })
        });

        match embedder {
            None => p.not_configured.push("embedder: not configured".into()),
            Some(task) => match task.await {
                Ok(Ok(e)) => p.embedder = Some(e),
                Ok(Err(e)) => p.failed.push(format!("embedder: {}", one_line(&e))),
                Err(e) => p.failed.push(format!("embedder: load panicked: {e}")),
            },
        }
        if cfg.reporter.is_empty() {
            p.not_configured
                .push("reporters: no [[reporter]] configured".into());
        }
        for (name, timeout, task) in reporters {
            match task.await {
                Ok(Ok((reporter, remote))) => {
                    if let Some(r) = remote {
                        p.remote.push((name, r));
                    }
                    p.reporters.push(RoundReporter::new(reporter, timeout));
                }
                Ok(Err(e)) => {
                    let why = one_line(&e);
                    p.failed.push(format!("reporter {name}: {why}"));
                    p.unloaded_reporters
                        .push((name, format!("not loaded at startup: {why}")));
                }
                Err(e) => {
                    p.failed
                        .push(format!("reporter {name}: load panicked: {e}"));
                    p.unloaded_reporters
                        .push((name, "not loaded at startup: load panicked".into()));
                }
            }
        }
        match labeler {
            None => {
                p.not_configured.push(
                    "labeler: not loaded: no clip pipeline is configured (POST /v1/label loads \
                     it on first use)"
                        .into(),
                );
                p.lazy_labeler = Some(Arc::new(LazyLabeler {
                    spec,
                    cell: tokio::sync::OnceCell::new(),
                }));
            }
            Some(task) => match task.await {
                Ok(Ok(l)) => {
                    p.labeler_name = l.name().to_string();
                    p.labeler = Some(l);
                }
                Ok(Err(e)) => p.failed.push(format!("labeler: {}", one_line(&e))),
                Err(e) => p.failed.push(format!("labeler: load panicked: {e}")),
            },
        }
        if let Some(task) = detector {
            match task.await {
                Ok(Ok(d)) => p.detector = Some(d),
                Ok(Err(e)) => p.failed.push(format!("detector: {}", one_line(&e))),
                Err(e) => p.failed.push(format!("detector: load panicked: {e}")),
            }
        }
        for f in &p.failed {
            tracing::error!("component not loaded: {f}");
        }
        p
    }
}

/// The configured labeler, built as the service builds it (`vlmfuse label` uses this, so the
/// command line and `/v1/label` cannot disagree). Blocking: model loads take seconds.
pub fn load_labeler(cfg: &Config) -> anyhow::Result<Arc<dyn Labeler>> {
    LabelerSpec {
        ontology: cfg.ontology.clone(),
        assets: cfg.assets(),
        config: cfg.labeler.clone(),
    }
    .load()
}

impl LabelerSpec {
    /// Builds the configured labeler (blocking: model loads take seconds).
    fn load(self) -> anyhow::Result<Arc<dyn Labeler>> {
        let LabelerSpec {
            config,
            ontology,
            assets,
        } = self;
        match config {
            LabelerConfig::Embedding(lc) => {
                let mut ec = vlmfuse_labeler::EmbeddingConfig::new(&assets.minilm_dir);
                if let Some(t) = lc.threshold {
                    ec.threshold = t;
                }
                let l = match lc.encoder {
                    EncoderEngine::Onnx => {
                        let dir = lc
                            .model_dir
                            .clone()
                            .unwrap_or(assets.minilm_onnx_dir.clone());
                        // The speller reads the encoder's own tokenizer.json.
                        ec.model_dir = dir.clone();
                        let enc = vlmfuse_labeler::OnnxSentenceEncoder::load(
                            &vlmfuse_labeler::OnnxEncoderConfig {
                                session: vlmfuse_ort::SessionOptions {
                                    threads: lc.threads,
                                    library: onnx_library(&assets),
                                },
                                ..vlmfuse_labeler::OnnxEncoderConfig::new(&dir)
                            },
                        )
                        .with_context(|| {
                            format!(
                                "embedding labeler: the ONNX encoder in {} (run \
                                 scripts/fetch-assets.sh, set labeler.model_dir, or use \
                                 encoder = \"candle\")",
                                dir.display()
                            )
                        })?;
                        vlmfuse_labeler::EmbeddingLabeler::with_encoder(ontology, ec, Arc::new(enc))
                            .context("embedding labeler")?
                    }
                    EncoderEngine::Candle => {
                        let dir = lc.model_dir.clone().unwrap_or(assets.minilm_dir);
                        if !dir.join("model.safetensors").is_file() {
                            bail!(
                                "embedding labeler: no MiniLM model in {} (run \
                                 scripts/fetch-assets.sh or set labeler.model_dir)",
                                dir.display()
                            );
                        }
                        ec.model_dir = dir;
                        vlmfuse_labeler::EmbeddingLabeler::load(ontology, ec)
                            .context("embedding labeler")?
                    }
                };
                pooled_labeler(l)
            }
            LabelerConfig::Gguf(lc) => {
                let path = lc.model_path.clone().unwrap_or(assets.gemma_gguf);
                // The GGUF labeler decodes a label list; it has no threshold.
                let mut gc = vlmfuse_labeler::GgufConfig::new(path);
                gc.chat_template = lc.chat_template;
                if let Some(n) = lc.max_answer_tokens {
                    gc.max_answer_tokens = n;
                }
                let l = vlmfuse_labeler::GgufLabeler::load(ontology, gc).context("gguf labeler")?;
                pooled_labeler(l)
            }
            LabelerConfig::Openai(lc) => {
                let mut oc = vlmfuse_labeler::OpenAiConfig::default();
                if let Some(u) = lc.base_url {
                    oc.base_url = u;
                }
                if let Some(m) = lc.model {
                    oc.model = m;
                }
                if let Some(var) = lc.api_key_env {
                    oc.api_key = std::env::var(&var).ok().filter(|v| !v.is_empty());
                }
                if let Some(j) = lc.json_mode {
                    oc.json_mode = j;
                }
                if let Some(t) = lc.timeout_s {
                    oc.timeout = Duration::from_secs_f64(t);
                }
                let l =
                    vlmfuse_labeler::OpenAiLabeler::new(ontology, oc).context("openai labeler")?;
                Ok(Arc::new(l) as Arc<dyn Labeler>)
            }
        }
    }
}

/// The ONNX Runtime library: `$ORT_DYLIB_PATH` when set, else the fetched one under the
/// configured asset directory.
fn onnx_library(assets: &vlmfuse_labeler::assets::AssetPaths) -> Option<std::path::PathBuf> {
    let env = std::env::var_os(vlmfuse_ort::DYLIB_ENV).filter(|v| !v.is_empty());
    env.is_none().then(|| assets.onnxruntime.clone())
}

/// A local labeler behind its own worker thread.
fn pooled_labeler<L: vlmfuse_labeler::BlockingLabeler>(l: L) -> anyhow::Result<Arc<dyn Labeler>> {
    let name = vlmfuse_labeler::BlockingLabeler::name(&l).to_string();
    let pool =
        BackendPool::new(name, Arc::new(l), PoolConfig::default()).context("labeler worker")?;
    Ok(Arc::new(pool))
}

/// An error chain as one line: each cause's first line, joined by ": ". `{:#}` alone is not
/// enough: some errors (candle's, under `RUST_BACKTRACE=1`) carry a backtrace in their own
/// message, which put 40 frames of build paths into `/readyz`.
pub fn one_line(e: &anyhow::Error) -> String {
    let mut parts: Vec<String> = Vec::new();
    for cause in e.chain() {
        let text = cause.to_string();
        let Some(first) = text.lines().map(str::trim).find(|l| !l.is_empty()) else {
            continue;
        };
        // A wrapper often repeats its source's message.
        if !parts.last().is_some_and(|p| p.contains(first)) {
            parts.push(first.to_string());
        }
    }
    parts.join(": ")
}

fn entry_name(name: &Option<String>, model: &str) -> String {
    name.clone().unwrap_or_else(|| model.to_string())
}

#[cfg(test)]
mod tests {
    use super::one_line;

    /// A cause whose message carries a backtrace (candle's `WithBacktrace` does) is cut to its
    /// first line; the chain stays.
    #[test]
    fn load_errors_are_one_line() {
        #[derive(Debug)]
        struct WithBacktrace;
        impl std::fmt::Display for WithBacktrace {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "cannot find tensor visual_projection.weight\n   0: candle_core::error\n             at /root/.cargo/registry/src/x.rs:12\n   1: main")
            }
        }
        impl std::error::Error for WithBacktrace {}
        let e = anyhow::Error::new(WithBacktrace).context("models/clip (cpu)");
        let s = one_line(&e);
        assert_eq!(
            s,
            "models/clip (cpu): cannot find tensor visual_projection.weight"
        );
        assert!(!s.contains('\n'));
    }
}
