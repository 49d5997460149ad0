//! `vlmfuse serve`: the stateful HTTP service (SPEC §5 and §9).
//!
//! The engine lives in memory behind an `RwLock`; the database (vlmfuse-store) is the truth it is
//! rebuilt from on start. Reads (`/v1/fuse` inference, `/v1/state`) take the read lock; the single
//! writer thread ([`writer`]) is the only code that takes the write lock.

mod error;
mod handlers;
mod infer;
mod pipeline;
mod writer;

use crate::config::Config;
pub use crate::config::ServeArgs;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::header::AUTHORIZATION;
use axum::middleware::{from_fn, from_fn_with_state, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, MethodRouter};
use axum::Router;
use error::ApiError;
use metrics_exporter_prometheus::{PrometheusBuilder, PrometheusHandle};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Mutex, RwLock};
use std::time::{Duration, Instant};
use tokio::sync::Semaphore;
use vlmfuse_fusion::Engine;
use vlmfuse_store::{Identity, Store};
use writer::{Cmd, Shared};

/// What every handler sees.
#[derive(Clone)]
pub struct AppState {
    shared: Arc<Shared>,
    tx: mpsc::Sender<Cmd>,
    cfg: Arc<Config>,
    metrics: PrometheusHandle,
    limiter: Arc<Semaphore>,
    pipeline: Arc<pipeline::Pipeline>,
}

impl AppState {
    fn send(&self, cmd: Cmd) -> Result<(), ApiError> {
        if self.shared.broken.load(Ordering::SeqCst) {
            return Err(ApiError::NotReady {
                message: "the service refuses writes; see /readyz".into(),
                not_ready: self.not_ready(),
            });
        }
        self.tx.send(cmd).map_err(|_| ApiError::NotReady {
            message: "the writer has stopped".into(),
            not_ready: vec!["store: writer stopped".into()],
        })
    }

    /// Components that are configured but not ready, each with its reason (a failed load of
    /// the embedder, a reporter or the labeler is listed here).
    fn not_ready(&self) -> Vec<String> {
        let mut out = Vec::new();
        if self.shared.broken.load(Ordering::SeqCst) {
            let why = self
                .shared
                .broken_reason
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone()
                .unwrap_or_default();
            out.push(format!("store: {why}"));
        }
        out.extend(self.pipeline.failed.iter().cloned());
        out
    }
}

/// Who may call a route.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// Probes and documents: never limited, never authenticated.
    Open,
    /// Reads under the concurrency limit.
    Limited,
    /// Writes: bearer token (when configured), then the concurrency limit.
    Write,
}

/// One row of the route table.
pub struct RouteDef {
    /// Lower-case, as OpenAPI spells it; the handler already carries the method, so only the
    /// route-table test reads this.
    #[cfg_attr(not(test), allow(dead_code))]
    pub method: &'static str,
    pub path: &'static str,
    pub access: Access,
    pub handler: MethodRouter<AppState>,
}

/// The route table: the router is built from it and a test holds it equal to openapi.yaml.
pub fn routes() -> Vec<RouteDef> {
    use handlers as h;
    let r = |method, path, access, handler| RouteDef {
        method,
        path,
        access,
        handler,
    };
    vec![
        r("post", "/v1/fuse", Access::Write, post(h::fuse)),
        r("post", "/v1/infer", Access::Write, post(infer::infer)),
        r("post", "/v1/feedback", Access::Write, post(h::feedback)),
        r("get", "/v1/state", Access::Limited, get(h::state)),
        r("get", "/v1/ontology", Access::Limited, get(h::ontology)),
        r("get", "/healthz", Access::Open, get(h::healthz)),
        r("get", "/readyz", Access::Open, get(h::readyz)),
        r("get", "/metrics", Access::Open, get(h::metrics)),
        r("get", "/openapi.yaml", Access::Open, get(h::openapi)),
    ]
}

pub fn router(state: AppState) -> Router {
    let mut app = Router::new();
    for def in routes() {
        let mut handler = def.handler;
        // route_layer: the last added runs first, so authentication precedes the limit and an
        // unauthenticated flood cannot take the slots.
        if def.access != Access::Open {
            handler = handler.route_layer(from_fn_with_state(state.clone(), limit));
        }
        if def.access == Access::Write {
            handler = handler.route_layer(from_fn_with_state(state.clone(), auth));
        }
        if def.path == "/v1/infer" {
            // Uploads are streamed to disk with their own limits (media.max_bytes per clip,
            // media.max_clips), so the JSON body limit does not apply.
            handler = handler.layer(DefaultBodyLimit::disable());
        }
        app = app.route(def.path, handler);
    }
    app.fallback(handlers::not_found)
        .method_not_allowed_fallback(handlers::method_not_allowed)
        .layer(DefaultBodyLimit::max(state.cfg.limits.max_body_bytes))
        .layer(from_fn_with_state(state.clone(), timeout))
        .layer(from_fn(track))
        .with_state(state)
}

/// TEI's pattern: a full server answers 429 at once instead of queueing without bound.
async fn limit(State(st): State<AppState>, req: Request, next: Next) -> Result<Response, ApiError> {
    let Ok(permit) = st.limiter.clone().try_acquire_owned() else {
        metrics::counter!("vlmfuse_overload_total").increment(1);
        return Err(ApiError::Overloaded(st.cfg.limits.concurrency_limit));
    };
    let resp = next.run(req).await;
    drop(permit);
    Ok(resp)
}

async fn auth(State(st): State<AppState>, req: Request, next: Next) -> Result<Response, ApiError> {
    if let Some(key) = &st.cfg.server.api_key {
        let given = req
            .headers()
            .get(AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "));
        if !given.is_some_and(|t| constant_time_eq(t.as_bytes(), key.as_bytes())) {
            return Err(ApiError::Unauthorized);
        }
    }
    Ok(next.run(req).await)
}

/// Compares without an early exit, so response time does not reveal a matching prefix.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

async fn timeout(State(st): State<AppState>, req: Request, next: Next) -> Response {
    let secs = if req.uri().path() == "/v1/infer" {
        st.cfg.media.request_timeout_s
    } else {
        st.cfg.limits.request_timeout_s
    };
    match tokio::time::timeout(Duration::from_secs_f64(secs), next.run(req)).await {
        Ok(resp) => resp,
        Err(_) => ApiError::Timeout(secs).into_response(),
    }
}

/// Per-route request count and latency, labelled by the route pattern (not the raw path, which
/// would make one series per round id).
async fn track(req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|m| m.as_str().to_string())
        .unwrap_or_else(|| "unmatched".into());
    let method = req.method().as_str().to_string();
    let start = Instant::now();
    let resp = next.run(req).await;
    let status = resp.status().as_u16().to_string();
    metrics::histogram!("vlmfuse_http_request_duration_seconds", "route" => route.clone(), "method" => method.clone())
        .record(start.elapsed().as_secs_f64());
    metrics::counter!("vlmfuse_http_requests_total", "route" => route, "method" => method, "status" => status)
        .increment(1);
    resp
}

fn install_metrics() -> Result<PrometheusHandle, String> {
    const BUCKETS: [f64; 14] = [
        0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 5.0,
    ];
    let handle = PrometheusBuilder::new()
        .set_buckets(&BUCKETS)
        .map_err(|e| e.to_string())?
        .install_recorder()
        .map_err(|e| format!("metrics recorder: {e}"))?;
    use metrics::{describe_counter, describe_gauge, describe_histogram, Unit};
    describe_counter!(
        "vlmfuse_http_requests_total",
        "HTTP requests by route, method and status"
    );
    describe_histogram!(
        "vlmfuse_http_request_duration_seconds",
        Unit::Seconds,
        "HTTP request latency by route"
    );
    describe_histogram!(
        "vlmfuse_fusion_duration_seconds",
        Unit::Seconds,
        "Inference time of one /v1/fuse request (all its rounds)"
    );
    describe_histogram!(
        "vlmfuse_feedback_duration_seconds",
        Unit::Seconds,
        "Feedback time in the writer: credit, commit, apply"
    );
    describe_gauge!("vlmfuse_reputation", "Public reputation w of each reporter");
    describe_gauge!("vlmfuse_labelled_rounds", "Labelled rounds in the bank");
    describe_gauge!("vlmfuse_threshold", "Decision threshold in force");
    describe_counter!(
        "vlmfuse_rejected_requests_total",
        "Requests answered with an error, by kind"
    );
    describe_counter!(
        "vlmfuse_overload_total",
        "Requests refused with 429 at the concurrency limit"
    );
    describe_counter!("vlmfuse_rounds_stored_total", "Rounds fused and committed");
    describe_histogram!(
        "vlmfuse_stage_seconds",
        Unit::Seconds,
        "Time of each /v1/infer stage per clip: upload, decode, embed, reporters, label, fuse"
    );
    describe_counter!(
        "vlmfuse_reporter_failures_total",
        "Reporters left out of a /v1/infer round, by reporter and stage (run, label)"
    );
    Ok(handle)
}

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
    tracing::info!("shutting down: finishing requests in flight");
}

pub fn main(args: ServeArgs) -> Result<(), String> {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .try_init();
    let cfg = Config::load(&args)?;
    let addr = cfg.listen_addr()?;

    let start = Instant::now();
    let mut engine = Engine::new(
        cfg.fusion.clone(),
        cfg.ontology.clone(),
        cfg.reporters.clone(),
    )
    .map_err(|e| e.to_string())?;
    let mut store = Store::open(&cfg.server.data_dir).map_err(|e| e.to_string())?;
    store
        .check_identity(&Identity {
            reporters: cfg.reporters.clone(),
            labels: cfg.ontology.labels().iter().map(|l| l.id.clone()).collect(),
        })
        .map_err(|e| e.to_string())?;
    let loaded = store.load_engine(&mut engine).map_err(|e| e.to_string())?;
    tracing::info!(
        rounds = loaded.rounds,
        labelled = loaded.labelled,
        secs = start.elapsed().as_secs_f64(),
        db = %store.path().display(),
        "state rebuilt from the database"
    );

    let metrics = install_metrics()?;
    writer::publish_gauges(&engine);
    let shared = Arc::new(Shared {
        engine: RwLock::new(engine),
        rounds: AtomicU64::new(loaded.next_seq),
        broken: AtomicBool::new(false),
        broken_reason: Mutex::new(None),
    });
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| e.to_string())?;
    let start = Instant::now();
    let pipeline = rt.block_on(pipeline::Pipeline::load(&cfg));
    tracing::info!(
        embedder = pipeline.embedder.is_some(),
        reporters = pipeline.reporters.len(),
        labeler = %pipeline.labeler_name,
        secs = start.elapsed().as_secs_f64(),
        "clip pipeline loaded"
    );
    let (tx, writer) = writer::spawn(store, shared.clone()).map_err(|e| e.to_string())?;
    let state = AppState {
        shared,
        tx,
        limiter: Arc::new(Semaphore::new(cfg.limits.concurrency_limit)),
        cfg: Arc::new(cfg),
        metrics,
        pipeline: Arc::new(pipeline),
    };

    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .map_err(|e| format!("cannot listen on {addr}: {e}"))?;
        let local = listener.local_addr().map_err(|e| e.to_string())?;
        // Tests and scripts read this line to learn the port when listening on port 0.
        println!("vlmfuse listening on http://{local}");
        tracing::info!("listening on http://{local}");
        axum::serve(listener, router(state))
            .with_graceful_shutdown(shutdown_signal())
            .await
            .map_err(|e| e.to_string())
    })?;
    drop(rt);
    // Every sender is gone with the router: the writer drains its queue, commits and returns.
    writer
        .join()
        .map_err(|_| "the writer thread panicked".to_string())?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    /// Fails when a route is in the router but not in openapi.yaml, or the reverse.
    #[test]
    fn routes_and_openapi_agree() {
        let doc: serde_norway::Value = serde_norway::from_str(handlers::OPENAPI).unwrap();
        let paths = doc["paths"].as_mapping().expect("paths");
        let mut spec = BTreeSet::new();
        for (path, ops) in paths {
            for (method, _) in ops.as_mapping().expect("operations") {
                let m = method.as_str().unwrap();
                if ["get", "post", "put", "patch", "delete", "head", "options"].contains(&m) {
                    spec.insert((m.to_string(), path.as_str().unwrap().to_string()));
                }
            }
        }
        let code: BTreeSet<(String, String)> = routes()
            .iter()
            .map(|r| (r.method.to_string(), r.path.to_string()))
            .collect();
        assert_eq!(code, spec, "router (left) and openapi.yaml (right) differ");
    }

    /// Every operation documents the statuses its access class can produce.
    #[test]
    fn openapi_lists_the_middleware_statuses() {
        let doc: serde_norway::Value = serde_norway::from_str(handlers::OPENAPI).unwrap();
        for r in routes() {
            let op = &doc["paths"][r.path][r.method]["responses"];
            let has = |code: &str| op.get(code).is_some();
            if r.access != Access::Open {
                assert!(
                    has("429") && has("503"),
                    "{} {} lacks 429/503",
                    r.method,
                    r.path
                );
            }
            if r.access == Access::Write {
                assert!(has("401"), "{} {} lacks 401", r.method, r.path);
            }
        }
    }

    #[test]
    fn constant_time_eq_compares() {
        assert!(constant_time_eq(b"abc", b"abc"));
        assert!(!constant_time_eq(b"abc", b"abd"));
        assert!(!constant_time_eq(b"abc", b"ab"));
    }
}
