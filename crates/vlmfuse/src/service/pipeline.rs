//! The clip pipeline's components (embedder, reporters, labeler), loaded once at startup.
//!
//! A component that is configured but fails to load is kept out and named in `/readyz` (503); one
//! that is simply not configured is named too, but only `/v1/infer` refuses (503) because of it:
//! `/v1/fuse` does not need it.

use crate::config::{Config, EmbedderBackend, LabelerConfig, ReporterBackend};
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
    /// Name of the labeler, as responses report it.
    pub labeler_name: String,
    /// Configured components that failed to load: `/readyz` answers 503 while any is listed.
    pub failed: Vec<String>,
    /// Components /v1/infer needs but the config leaves out.
    pub not_configured: Vec<String>,
    /// Configured reporters that failed to load (also in `failed`): /v1/infer runs without
    /// them and names them in every response's `failed`.
    pub unloaded_reporters: Vec<(String, String)>,
}

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
                let task =
                    tokio::task::spawn_blocking(move || -> anyhow::Result<Arc<dyn Reporter>> {
                        Ok(match entry.backend {
                            ReporterBackend::Openai(mut c) => {
                                c.name = Some(entry_name(&c.name, &c.model));
                                Arc::new(vlmfuse_models::OpenAiReporter::new(c)?)
                            }
                            ReporterBackend::Candle(c) => {
                                let r = vlmfuse_models::CandleVlmReporter::load(c)?;
                                let pool = BackendPool::new(
                                    name_for_pool,
                                    Arc::new(r),
                                    PoolConfig::default(),
                                )
                                .context("reporter worker")?;
                                Arc::new(pool)
                            }
                        })
                    });
                (name, timeout, task)
            })
            .collect();

        // Labeler: only loaded when there is a clip pipeline to serve; a /v1/fuse-only
        // deployment must not load (or be unready for lack of) a model it never uses.
        let wanted = cfg.embedder.is_some() || !cfg.reporter.is_empty();
        // The labeler and the engine share one ontology type: no translation.
        let ontology = cfg.ontology.clone();
        let assets = cfg.assets();
        let lc = cfg.labeler.clone();
        let labeler = tokio::task::spawn_blocking(move || -> anyhow::Result<Arc<dyn Labeler>> {
            if !wanted {
                bail!("not loaded: no clip pipeline is configured");
            }
            match lc {
                LabelerConfig::Embedding(lc) => {
                    let dir = lc.model_dir.clone().unwrap_or(assets.minilm_dir);
                    if !dir.join("model.safetensors").is_file() {
                        bail!(
                            "embedding labeler: no MiniLM model in {} (run scripts/fetch-assets.sh \
                             or set labeler.model_dir)",
                            dir.display()
                        );
                    }
                    let mut ec = vlmfuse_labeler::EmbeddingConfig::new(dir);
                    if let Some(t) = lc.threshold {
                        ec.threshold = t;
                    }
                    let l = vlmfuse_labeler::EmbeddingLabeler::load(ontology, ec)
                        .context("embedding labeler")?;
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
                    let l =
                        vlmfuse_labeler::GgufLabeler::load(ontology, gc).context("gguf labeler")?;
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
                    let l = vlmfuse_labeler::OpenAiLabeler::new(ontology, oc)
                        .context("openai labeler")?;
                    Ok(Arc::new(l) as Arc<dyn Labeler>)
                }
            }
        });

        match embedder {
            None => p.not_configured.push("embedder: not configured".into()),
            Some(task) => match task.await {
                Ok(Ok(e)) => p.embedder = Some(e),
                Ok(Err(e)) => p.failed.push(format!("embedder: {e:#}")),
                Err(e) => p.failed.push(format!("embedder: load panicked: {e}")),
            },
        }
        if cfg.reporter.is_empty() {
            p.not_configured
                .push("reporters: no [[reporter]] configured".into());
        }
        for (name, timeout, task) in reporters {
            match task.await {
                Ok(Ok(reporter)) => p.reporters.push(RoundReporter::new(reporter, timeout)),
                Ok(Err(e)) => {
                    p.failed.push(format!("reporter {name}: {e:#}"));
                    p.unloaded_reporters
                        .push((name, format!("not loaded at startup: {e:#}")));
                }
                Err(e) => {
                    p.failed
                        .push(format!("reporter {name}: load panicked: {e}"));
                    p.unloaded_reporters
                        .push((name, "not loaded at startup: load panicked".into()));
                }
            }
        }
        match labeler.await {
            Ok(Ok(l)) => {
                p.labeler_name = l.name().to_string();
                p.labeler = Some(l);
            }
            Ok(Err(e)) if !wanted => p.not_configured.push(format!("labeler: {e:#}")),
            Ok(Err(e)) => p.failed.push(format!("labeler: {e:#}")),
            Err(e) => p.failed.push(format!("labeler: load panicked: {e}")),
        }
        for f in &p.failed {
            tracing::error!("component not loaded: {f}");
        }
        p
    }
}

/// A local labeler behind its own worker thread.
fn pooled_labeler<L: vlmfuse_labeler::BlockingLabeler>(l: L) -> anyhow::Result<Arc<dyn Labeler>> {
    let name = vlmfuse_labeler::BlockingLabeler::name(&l).to_string();
    let pool =
        BackendPool::new(name, Arc::new(l), PoolConfig::default()).context("labeler worker")?;
    Ok(Arc::new(pool))
}

fn entry_name(name: &Option<String>, model: &str) -> String {
    name.clone().unwrap_or_else(|| model.to_string())
}
