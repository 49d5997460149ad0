//! `/readyz`: each component's state, and whether `/v1/infer` can serve. Remote reporters are
//! probed in the background (`GET /v1/models` every `server.probe_interval_s`), so readiness
//! follows a reporter whose server went down instead of saying what was true at startup.

use super::pipeline::Pipeline;
use super::Service;
use crate::config::{Config, EmbedderBackend, EncoderEngine, LabelerConfig, ReporterBackend};
use serde_json::{json, Map, Value};
use std::collections::BTreeMap;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime};

/// The last probe of one remote reporter.
#[derive(Debug, Clone, Default)]
pub struct Probe {
    /// `None` until the first probe has answered.
    pub ok: Option<bool>,
    pub at: Option<SystemTime>,
    pub error: Option<String>,
}

/// Probe results by reporter name (remote reporters only).
#[derive(Default)]
pub struct Health {
    reporters: BTreeMap<String, Mutex<Probe>>,
}

impl Health {
    fn probe(&self, name: &str) -> Option<Probe> {
        self.reporters
            .get(name)
            .map(|p| p.lock().unwrap_or_else(|e| e.into_inner()).clone())
    }

    /// Whether a loaded reporter counts as serving: a remote one until a probe fails.
    fn serving(&self, name: &str) -> bool {
        self.probe(name).is_none_or(|p| p.ok != Some(false))
    }
}

/// Stops the probe task when the service goes.
pub struct ProbeTask(tokio::task::AbortHandle);

impl Drop for ProbeTask {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Starts probing every remote reporter of `pipeline`, at once and then every `interval`.
pub fn start_probes(
    pipeline: &Arc<Pipeline>,
    interval: Duration,
) -> (Arc<Health>, Option<ProbeTask>) {
    let health = Arc::new(Health {
        reporters: pipeline
            .remote
            .iter()
            .map(|(n, _)| (n.clone(), Mutex::new(Probe::default())))
            .collect(),
    });
    if pipeline.remote.is_empty() {
        return (health, None);
    }
    let timeout = interval.min(Duration::from_secs(5));
    let (p, h) = (pipeline.clone(), health.clone());
    let task = tokio::spawn(async move {
        let mut tick = tokio::time::interval(interval);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tick.tick().await;
            let probes = p.remote.iter().map(|(name, r)| async move {
                let res = r.probe(timeout).await;
                (name, res)
            });
            for (name, res) in futures::future::join_all(probes).await {
                let Some(slot) = h.reporters.get(name) else {
                    continue;
                };
                let mut slot = slot.lock().unwrap_or_else(|e| e.into_inner());
                // The first failure is logged too: /readyz shows it without the address.
                if slot.ok != Some(false) && res.is_err() {
                    tracing::warn!(reporter = %name, error = ?res.as_ref().err(), "reporter probe failed");
                }
                if slot.ok == Some(false) && res.is_ok() {
                    tracing::info!(reporter = %name, "reporter probe answers again");
                }
                *slot = Probe {
                    ok: Some(res.is_ok()),
                    at: Some(SystemTime::now()),
                    error: res.err(),
                };
            }
        }
    });
    (health, Some(ProbeTask(task.abort_handle())))
}

/// What `/readyz` answers.
pub struct Readiness {
    /// False: answer 503.
    pub ready: bool,
    pub body: Value,
}

fn labeler_kind(cfg: &Config) -> (&'static str, &'static str) {
    match &cfg.labeler {
        LabelerConfig::Embedding(e) => (
            "embedding",
            match e.encoder {
                EncoderEngine::Onnx => "onnx",
                EncoderEngine::Candle => "candle",
            },
        ),
        LabelerConfig::Gguf(_) => ("gguf", "candle"),
        LabelerConfig::Openai(_) => ("openai", "remote"),
    }
}

/// Bytes available to this process on the filesystem holding `dir` (statvfs `f_bavail`).
fn free_bytes(dir: &std::path::Path) -> std::io::Result<u64> {
    use std::os::unix::ffi::OsStrExt;
    let path = std::ffi::CString::new(dir.as_os_str().as_bytes())
        .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))?;
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `path` is a valid NUL-terminated string and `st` a writable statvfs.
    if unsafe { libc::statvfs(path.as_ptr(), &mut st) } != 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(st.f_bavail as u64 * st.f_frsize as u64)
}

/// The reason a component is not ready, from its `failed` entry ("embedder: why" -> "why").
fn failure<'a>(p: &'a Pipeline, prefix: &str) -> Option<&'a str> {
    p.failed
        .iter()
        .find_map(|f| f.strip_prefix(prefix))
        .map(str::trim_start)
}

impl Service {
    /// Why the store cannot be trusted with the next write: the writer broke, or the data
    /// directory's filesystem is below `server.min_free_bytes` (a full disk would fail the
    /// next commit; saying so first lets a balancer move writes away).
    fn store_problem(&self) -> Option<String> {
        if self.shared.broken.load(Ordering::SeqCst) {
            return Some(self.shared.broken_reason());
        }
        let min = self.cfg.server.min_free_bytes;
        if min == 0 {
            return None;
        }
        let dir = &self.cfg.server.data_dir;
        match free_bytes(dir) {
            Ok(free) if free < min => Some(format!(
                "disk nearly full: {free} bytes free for {}, below server.min_free_bytes = {min}",
                dir.display()
            )),
            Ok(_) => None,
            Err(e) => Some(format!("cannot read free space of {}: {e}", dir.display())),
        }
    }

    /// Components that are configured but not ready, each with its reason: a failed load of the
    /// embedder, a reporter or the labeler, a remote reporter whose last probe failed, a broken
    /// store.
    pub fn not_ready(&self) -> Vec<String> {
        let mut out = Vec::new();
        if let Some(why) = self.store_problem() {
            out.push(format!("store: {why}"));
        }
        out.extend(self.pipeline.failed.iter().cloned());
        for (name, _) in &self.pipeline.remote {
            if let Some(Probe {
                ok: Some(false),
                error,
                ..
            }) = self.health.probe(name)
            {
                out.push(format!(
                    "reporter {name}: {}",
                    error.unwrap_or_else(|| "probe failed".into())
                ));
            }
        }
        out
    }

    /// Why `/v1/infer` cannot serve now (load failures, missing components, every reporter
    /// down), or empty when it can.
    fn infer_blockers_now(&self) -> Vec<String> {
        let p = &self.pipeline;
        let mut out = p.infer_blockers();
        let serving = p
            .reporters
            .iter()
            .filter(|r| self.health.serving(r.reporter.name()))
            .count();
        if !p.reporters.is_empty() && serving == 0 {
            out.push("reporters: every loaded reporter fails its health probe".into());
        }
        out
    }

    /// `/readyz`. Ready (200) when the store takes writes and nothing configured for
    /// `/v1/infer` keeps it from serving: a configured embedder and labeler are loaded and, with
    /// reporters configured, at least one is loaded and answers its probe. Components the config
    /// leaves out (a `/v1/fuse`-only deployment) do not make it 503; `infer.ready` and
    /// `infer.not_ready` say /v1/infer is unavailable and why. Every error is one line.
    pub fn readiness(&self) -> Readiness {
        let cfg = &self.cfg;
        let p = &self.pipeline;
        let store_problem = self.store_problem();
        let broken = store_problem.is_some();
        let mut components = Map::new();

        let mut store = json!({
            "ready": !broken,
            "rounds": self.shared.rounds.load(Ordering::SeqCst),
        });
        if let Some(why) = &store_problem {
            store["error"] = why.clone().into();
        }
        let info = &self.store_info;
        store["backend"] = info.backend.into();
        store["location"] = info.location.clone().into();
        if let Some(l) = &info.lease {
            // This replica writes: it holds the lease (a standby does not serve until it does).
            store["role"] = "writer".into();
            store["replica"] = l.holder.clone().into();
            store["lease_age_s"] =
                (((vlmfuse_store::timestamp_ms() - l.since_ms).max(0)) as f64 / 1000.0).into();
        } else if let Some(f) = &self.follower {
            // It follows the writer (or took over from it: the lease age is then unknown here).
            store["role"] = if f.following() { "follower" } else { "writer" }.into();
            if let Some((name, _)) = f.writer().filter(|_| f.following()) {
                store["writer"] = name.into();
            }
            store["replication_lag_s"] = f.synced_age_s().into();
            if !self.cfg.store.replica_name.is_empty() {
                store["replica"] = self.cfg.store.replica_name.clone().into();
            }
        }
        components.insert("store".into(), store);

        let embedder = match &cfg.embedder {
            None => json!({"ready": false, "configured": false}),
            Some(e) => {
                let engine = match e.backend {
                    EmbedderBackend::Candle => "candle",
                    EmbedderBackend::Onnx => "onnx",
                };
                let mut v = json!({"ready": p.embedder.is_some(), "engine": engine,
                                   "device": e.device});
                match &p.embedder {
                    Some(m) => v["dim"] = m.dim().into(),
                    None => {
                        v["error"] = failure(p, "embedder:").unwrap_or("not loaded").into();
                    }
                }
                v
            }
        };
        components.insert("embedder".into(), embedder);

        let mut reporters = Map::new();
        for entry in &cfg.reporter {
            let name = entry.name();
            let kind = match entry.backend {
                ReporterBackend::Openai(_) => "openai",
                ReporterBackend::Candle(_) => "candle",
            };
            let loaded = p.reporters.iter().any(|r| r.reporter.name() == name);
            let mut v = json!({"kind": kind, "ready": loaded});
            if !loaded {
                let prefix = format!("reporter {name}:");
                v["error"] = failure(p, &prefix).unwrap_or("not loaded").into();
            } else if let Some(probe) = self.health.probe(&name) {
                v["ready"] = (probe.ok != Some(false)).into();
                v["last_probe"] = probe.at.map(httpdate::fmt_http_date).into();
                v["last_probe_age_s"] = probe
                    .at
                    .and_then(|t| t.elapsed().ok())
                    .map(|d| (d.as_secs_f64() * 10.0).round() / 10.0)
                    .into();
                if let Some(e) = probe.error {
                    v["error"] = e.into();
                }
            }
            reporters.insert(name, v);
        }
        components.insert("reporters".into(), Value::Object(reporters));

        let (kind, engine) = labeler_kind(cfg);
        let mut labeler = json!({"ready": p.labeler.is_some(), "kind": kind, "engine": engine});
        if let Some(l) = &p.labeler {
            labeler["name"] = l.name().into();
        } else if let Some(why) = failure(p, "labeler:") {
            labeler["error"] = why.into();
        } else {
            labeler["loaded_on_first_use"] = true.into();
        }
        components.insert("labeler".into(), labeler);

        let wanted = cfg.embedder.is_some() || !cfg.reporter.is_empty();
        let blockers = self.infer_blockers_now();
        // What the operator configured and is broken; a component left out of the config
        // only makes /v1/infer answer 503 (it says what is missing), not the probe.
        let broken_parts: Vec<String> = blockers
            .iter()
            .filter(|b| !p.not_configured.contains(b))
            .cloned()
            .collect();
        let ready = !broken && broken_parts.is_empty();
        let not_ready = self.not_ready();
        let mut body = json!({
            "ready": ready,
            "status": if ready { "ready" } else { "not_ready" },
            "components": components,
            "infer": {"ready": blockers.is_empty(), "configured": wanted, "not_ready": blockers},
            "not_ready": not_ready,
        });
        if !ready {
            // The error shape too, so a 503 here reads like every other 503.
            let mut why: Vec<String> = Vec::new();
            if let Some(w) = &store_problem {
                why.push(format!("store: {w}"));
            }
            why.extend(broken_parts);
            body["error"] = format!("not ready: {}", why.join("; ")).into();
            body["kind"] = "not_ready".into();
        }
        Readiness { ready, body }
    }
}
