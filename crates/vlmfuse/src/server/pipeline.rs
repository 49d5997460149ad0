//! The clip pipeline's components (embedder, reporters, labeler), loaded once at startup.
//!
//! A component that is configured but fails to load is kept out and named in `/readyz` (503); one
//! that is simply not configured is named too, but only `/v1/infer` refuses (503) because of it:
//! `/v1/fuse` does not need it.

use crate::config::{Config, LabelerKind, ReporterBackend};
use std::sync::Arc;
use std::time::Duration;
use vlmfuse_labeler::Labeler;
use vlmfuse_models::{ContextEmbedder, Reporter};

/// One loaded reporter and its timeout per round.
pub struct LoadedReporter {
    pub reporter: Arc<dyn Reporter>,
    pub timeout: Duration,
}

#[derive(Default)]
pub struct Pipeline {
    pub embedder: Option<Arc<dyn ContextEmbedder>>,
    pub reporters: Vec<LoadedReporter>,
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
                let device = vlmfuse_models::parse_device(&e.device).map_err(|x| x.to_string())?;
                vlmfuse_models::ClipEmbedder::load(&e.weights, &device)
                    .map(|m| Arc::new(m) as Arc<dyn ContextEmbedder>)
                    .map_err(|x| format!("{} ({}): {x}", e.weights.describe(), e.device))
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
                let task =
                    tokio::task::spawn_blocking(move || -> Result<Arc<dyn Reporter>, String> {
                        match entry.backend {
                            ReporterBackend::Openai(mut c) => {
                                c.name = Some(entry_name(&c.name, &c.model));
                                vlmfuse_models::OpenAiReporter::new(c)
                                    .map(|r| Arc::new(r) as Arc<dyn Reporter>)
                                    .map_err(|e| e.to_string())
                            }
                            ReporterBackend::Candle(c) => {
                                vlmfuse_models::CandleVlmReporter::load(c)
                                    .map(|r| Arc::new(r) as Arc<dyn Reporter>)
                                    .map_err(|e| e.to_string())
                            }
                        }
                    });
                (name, timeout, task)
            })
            .collect();

        // Labeler: only loaded when there is a clip pipeline to serve; a /v1/fuse-only
        // deployment must not load (or be unready for lack of) a model it never uses.
        let wanted = cfg.embedder.is_some() || !cfg.reporter.is_empty();
        let ontology = labeler_ontology(cfg);
        let lc = cfg.labeler.clone();
        let labeler = tokio::task::spawn_blocking(move || -> Result<Arc<dyn Labeler>, String> {
            if !wanted {
                return Err("not loaded: no clip pipeline is configured".into());
            }
            let ontology = ontology?;
            match lc.kind {
                LabelerKind::Embedding => {
                    let dir = lc
                        .model_dir
                        .clone()
                        .unwrap_or_else(|| vlmfuse_labeler::assets::asset_paths().minilm_dir);
                    if !dir.join("model.safetensors").is_file() {
                        return Err(format!(
                            "embedding labeler: no MiniLM model in {} (run scripts/fetch-assets.sh \
                             or set labeler.model_dir)",
                            dir.display()
                        ));
                    }
                    let mut ec = vlmfuse_labeler::EmbeddingConfig::new(dir);
                    if let Some(t) = lc.threshold {
                        ec.threshold = t;
                    }
                    vlmfuse_labeler::EmbeddingLabeler::load(ontology, ec)
                        .map(|l| Arc::new(l) as Arc<dyn Labeler>)
                        .map_err(|e| format!("embedding labeler: {e}"))
                }
                LabelerKind::Gguf => {
                    let path = lc
                        .model_path
                        .clone()
                        .unwrap_or_else(|| vlmfuse_labeler::assets::asset_paths().gemma_gguf);
                    // The GGUF labeler decodes a label list; it has no threshold.
                    let gc = vlmfuse_labeler::GgufConfig::new(path);
                    vlmfuse_labeler::GgufLabeler::load(ontology, gc)
                        .map(|l| Arc::new(l) as Arc<dyn Labeler>)
                        .map_err(|e| format!("gguf labeler: {e}"))
                }
                LabelerKind::Openai => {
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
                    vlmfuse_labeler::OpenAiLabeler::new(ontology, oc)
                        .map(|l| Arc::new(l) as Arc<dyn Labeler>)
                        .map_err(|e| format!("openai labeler: {e}"))
                }
            }
        });

        match embedder {
            None => p.not_configured.push("embedder: not configured".into()),
            Some(task) => match task.await {
                Ok(Ok(e)) => p.embedder = Some(e),
                Ok(Err(e)) => p.failed.push(format!("embedder: {e}")),
                Err(e) => p.failed.push(format!("embedder: load panicked: {e}")),
            },
        }
        if cfg.reporter.is_empty() {
            p.not_configured
                .push("reporters: no [[reporter]] configured".into());
        }
        for (name, timeout, task) in reporters {
            match task.await {
                Ok(Ok(reporter)) => p.reporters.push(LoadedReporter { reporter, timeout }),
                Ok(Err(e)) => {
                    p.failed.push(format!("reporter {name}: {e}"));
                    p.unloaded_reporters
                        .push((name, format!("not loaded at startup: {e}")));
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
            Ok(Err(e)) if !wanted => p.not_configured.push(format!("labeler: {e}")),
            Ok(Err(e)) => p.failed.push(format!("labeler: {e}")),
            Err(e) => p.failed.push(format!("labeler: load panicked: {e}")),
        }
        for f in &p.failed {
            tracing::error!("component not loaded: {f}");
        }
        p
    }
}

fn entry_name(name: &Option<String>, model: &str) -> String {
    name.clone().unwrap_or_else(|| model.to_string())
}

/// The labeler speaks the fusion ontology's ids, so its labels need no translation.
fn labeler_ontology(cfg: &Config) -> Result<vlmfuse_labeler::Ontology, String> {
    vlmfuse_labeler::Ontology::new(
        cfg.ontology
            .labels()
            .iter()
            .map(|l| vlmfuse_labeler::LabelDef::new(&l.id, &l.name, l.description.as_deref()))
            .collect(),
    )
    .map_err(|e| format!("ontology: {e}"))
}
