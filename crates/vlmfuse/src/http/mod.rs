//! The HTTP edge of `vlmfuse serve` (PAPER-METHOD.md §9): the route table, its middleware (authentication,
//! the concurrency limit, timeouts, metrics) and [`app`], which builds the router over a
//! [`Service`]. Handlers read the request and call the service; `error` turns failures into
//! statuses, in one place.

pub mod error;
mod handlers;
mod infer;
pub mod ui;

pub use error::ApiError;
pub use handlers::OPENAPI;

use crate::service::Service;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::header::AUTHORIZATION;
use axum::middleware::{from_fn, from_fn_with_state, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, MethodRouter};
use axum::Router;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::Semaphore;

/// What every handler sees.
#[derive(Clone)]
pub struct AppState {
    pub service: Arc<Service>,
    limiter: Arc<Semaphore>,
    counts: Arc<EdgeCounters>,
}

/// Responses by class since start, for the operator page's health panel.
#[derive(Default)]
struct EdgeCounters {
    client: AtomicU64,
    server: AtomicU64,
    overload: AtomicU64,
}

impl AppState {
    pub fn new(service: Arc<Service>) -> Self {
        let limiter = Arc::new(Semaphore::new(service.config().limits.concurrency_limit));
        Self {
            service,
            limiter,
            counts: Arc::default(),
        }
    }
}

/// Who may call a route.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// Probes and documents: never limited, never authenticated.
    Open,
    /// Reads under the concurrency limit.
    Limited,
    /// Writes, and routes that run models: bearer token (when configured), then the
    /// concurrency limit. The operator page's session cookie counts as the token when the
    /// request says it comes from the page (`X-Vlmfuse-Ui: 1`; http/ui.rs says why).
    Write,
    /// The operator page's reads: the bearer token or the page's session cookie (when a key is
    /// configured), then the concurrency limit.
    Operator,
}

/// How large a body a route takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BodyLimit {
    /// `limits.max_body_bytes` (413 above).
    Json,
    /// Uploads streamed to disk with their own limits (`media.max_bytes` per clip,
    /// `media.max_clips`), so the JSON limit does not apply.
    Streamed,
}

/// Which timeout a route runs under.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimeoutClass {
    /// `limits.request_timeout_s`.
    Request,
    /// `media.request_timeout_s`: a clip goes through decoding and every model.
    Clip,
}

/// One row of the route table: the path, its handler and its policy.
pub struct RouteDef {
    /// Lower-case, as OpenAPI spells it; the handler already carries the method, so only the
    /// route-table test reads this.
    #[cfg_attr(not(test), allow(dead_code))]
    pub method: &'static str,
    pub path: &'static str,
    pub access: Access,
    pub body: BodyLimit,
    pub timeout: TimeoutClass,
    pub handler: MethodRouter<AppState>,
}

/// The route table: the router is built from it and a test holds it equal to openapi.yaml.
pub fn routes() -> Vec<RouteDef> {
    use handlers as h;
    use Access::*;
    let r = |method, path, access, handler| RouteDef {
        method,
        path,
        access,
        body: BodyLimit::Json,
        timeout: TimeoutClass::Request,
        handler,
    };
    vec![
        r("post", "/v1/fuse", Write, post(h::fuse)),
        RouteDef {
            body: BodyLimit::Streamed,
            timeout: TimeoutClass::Clip,
            ..r("post", "/v1/infer", Write, post(infer::infer))
        },
        r("post", "/v1/feedback", Write, post(h::feedback)),
        // Labelling runs a model: behind the key and the limit like the other model routes.
        r("post", "/v1/label", Write, post(h::label)),
        r("get", "/v1/state", Limited, get(h::state)),
        r("get", "/v1/ontology", Limited, get(h::ontology)),
        r("get", "/v1/review", Limited, get(h::review)),
        r("get", "/healthz", Open, get(h::healthz)),
        r("get", "/readyz", Open, get(h::readyz)),
        r("get", "/metrics", Open, get(h::metrics)),
        r("get", "/openapi.yaml", Open, get(h::openapi)),
        // The operator page (docs/UI.md). The page itself decides between the page and the login
        // form, so it is open; its data is behind the key.
        r("get", "/", Open, get(ui::root)),
        r("get", "/ui", Open, get(ui::index)),
        r("get", "/ui/app.js", Open, get(ui::app_js)),
        r("get", "/ui/app.css", Open, get(ui::app_css)),
        r("post", "/ui/login", Limited, post(ui::login)),
        r("post", "/ui/logout", Open, post(ui::logout)),
        r("get", "/ui/api/summary", Operator, get(ui::summary)),
        r("get", "/ui/api/rounds", Operator, get(ui::rounds)),
        r("get", "/ui/api/rounds/{round_id}", Operator, get(ui::round)),
        r(
            "get",
            "/ui/api/rounds/{round_id}/frames/{index}",
            Operator,
            get(ui::frame),
        ),
    ]
}

/// The router over a service: every route of [`routes`] with its policy applied.
pub fn app(state: AppState) -> Router {
    let cfg = state.service.config();
    let mut app = Router::new();
    for def in routes() {
        let mut handler = def.handler;
        // route_layer: the last added runs first, so authentication precedes the limit and an
        // unauthenticated flood cannot take the slots; the timeout covers both.
        if def.access != Access::Open {
            handler = handler.route_layer(from_fn_with_state(state.clone(), limit));
        }
        if def.access == Access::Write {
            handler = handler.route_layer(from_fn_with_state(state.clone(), auth));
        }
        if def.access == Access::Operator {
            handler = handler.route_layer(from_fn_with_state(state.clone(), auth_operator));
        }
        let secs = match def.timeout {
            TimeoutClass::Request => cfg.limits.request_timeout_s,
            TimeoutClass::Clip => cfg.media.request_timeout_s,
        };
        handler = handler.route_layer(from_fn_with_state(secs, timeout));
        handler = handler.layer(match def.body {
            BodyLimit::Json => DefaultBodyLimit::max(cfg.limits.max_body_bytes),
            BodyLimit::Streamed => DefaultBodyLimit::disable(),
        });
        app = app.route(def.path, handler);
    }
    app.fallback(handlers::not_found)
        .method_not_allowed_fallback(handlers::method_not_allowed)
        .layer(from_fn_with_state(state.clone(), track))
        .layer(from_fn(close_on_refusal))
        .layer(from_fn_with_state(state.clone(), scope_metrics))
        .with_state(state)
}

/// A refusal of a request that came with a body (401, 405, 413, 429, a timeout, any error)
/// says `Connection: close`: the body may be unread (an upload refused by a middleware), and
/// the server will not read megabytes it refused only to keep the connection, so a client
/// must not send its next request on this one expecting it to be served.
async fn close_on_refusal(req: Request, next: Next) -> Response {
    let has_body = req
        .headers()
        .get(axum::http::header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok())
        .is_some_and(|n| n > 0)
        || req
            .headers()
            .contains_key(axum::http::header::TRANSFER_ENCODING);
    let mut resp = next.run(req).await;
    if has_body && (resp.status().is_client_error() || resp.status().is_server_error()) {
        resp.headers_mut().insert(
            axum::http::header::CONNECTION,
            axum::http::HeaderValue::from_static("close"),
        );
    }
    resp
}

/// Everything a request does runs with this service's metrics recorder in force.
async fn scope_metrics(State(st): State<AppState>, req: Request, next: Next) -> Response {
    let metrics = st.service.metrics().clone();
    metrics.instrument(next.run(req)).await
}

/// TEI's pattern: a full server answers 429 at once instead of queueing without bound.
async fn limit(State(st): State<AppState>, req: Request, next: Next) -> Result<Response, ApiError> {
    let Ok(permit) = st.limiter.clone().try_acquire_owned() else {
        metrics::counter!("vlmfuse_overload_total").increment(1);
        st.counts.overload.fetch_add(1, Ordering::Relaxed);
        return Err(ApiError::Overloaded(
            st.service.config().limits.concurrency_limit,
        ));
    };
    let resp = next.run(req).await;
    drop(permit);
    Ok(resp)
}

async fn auth(State(st): State<AppState>, req: Request, next: Next) -> Result<Response, ApiError> {
    if st.service.config().server.api_key.is_some()
        && !has_token(&st, req.headers())
        && !ui::page_write(&st, req.headers())
    {
        return Err(ApiError::Unauthorized);
    }
    Ok(next.run(req).await)
}

async fn auth_operator(
    State(st): State<AppState>,
    req: Request,
    next: Next,
) -> Result<Response, ApiError> {
    if !ui::operator(&st, req.headers()) {
        return Err(ApiError::Unauthorized);
    }
    Ok(next.run(req).await)
}

/// Whether the request carries the configured bearer token (false when none is configured: then
/// nothing distinguishes the operator from anyone else).
pub(crate) fn has_token(st: &AppState, headers: &axum::http::HeaderMap) -> bool {
    let Some(key) = &st.service.config().server.api_key else {
        return false;
    };
    headers
        .get(AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(bearer_token)
        .is_some_and(|t| constant_time_eq(t.as_bytes(), key.as_bytes()))
}

/// The token of an `Authorization: Bearer <token>` header. The scheme is case-insensitive
/// (RFC 7235 §2.1), so `bearer` and `BEARER` are accepted.
fn bearer_token(header: &str) -> Option<&str> {
    let (scheme, token) = header.trim().split_once(' ')?;
    scheme
        .eq_ignore_ascii_case("bearer")
        .then(|| token.trim_start())
}

/// Compares in time that depends only on the key's length, never on where or whether the
/// given token differs (no early exit on a length mismatch either), so response time reveals
/// neither a matching prefix nor the key's length from the token's.
pub(crate) fn constant_time_eq(given: &[u8], key: &[u8]) -> bool {
    let mut diff = u8::from(given.len() != key.len());
    for (i, &k) in key.iter().enumerate() {
        diff |= given.get(i).copied().unwrap_or(0) ^ k;
    }
    diff == 0
}

async fn timeout(State(secs): State<f64>, req: Request, next: Next) -> Response {
    match tokio::time::timeout(Duration::from_secs_f64(secs), next.run(req)).await {
        Ok(resp) => resp,
        Err(_) => ApiError::Timeout(secs).into_response(),
    }
}

/// The `method` label of the request metrics: the standard methods by name, anything else
/// folded into `other`, so that a client inventing methods cannot add series without bound.
fn method_label(m: &axum::http::Method) -> &'static str {
    use axum::http::Method;
    match *m {
        Method::GET => "GET",
        Method::POST => "POST",
        Method::PUT => "PUT",
        Method::DELETE => "DELETE",
        Method::HEAD => "HEAD",
        Method::OPTIONS => "OPTIONS",
        Method::PATCH => "PATCH",
        Method::CONNECT => "CONNECT",
        Method::TRACE => "TRACE",
        _ => "other",
    }
}

/// Per-route request count and latency, labelled by the route pattern (not the raw path, which
/// would make one series per round id).
async fn track(State(st): State<AppState>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|m| m.as_str().to_string())
        .unwrap_or_else(|| "unmatched".into());
    let method = method_label(req.method()).to_string();
    let start = Instant::now();
    let resp = next.run(req).await;
    if resp.status().is_client_error() {
        st.counts.client.fetch_add(1, Ordering::Relaxed);
    } else if resp.status().is_server_error() {
        st.counts.server.fetch_add(1, Ordering::Relaxed);
    }
    let status = resp.status().as_u16().to_string();
    metrics::histogram!("vlmfuse_http_request_duration_seconds", "route" => route.clone(), "method" => method.clone())
        .record(start.elapsed().as_secs_f64());
    metrics::counter!("vlmfuse_http_requests_total", "route" => route, "method" => method, "status" => status)
        .increment(1);
    resp
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    /// Fails when a route is in the router but not in openapi.yaml, or the reverse.
    #[test]
    fn routes_and_openapi_agree() {
        let doc: serde_norway::Value = serde_norway::from_str(OPENAPI).unwrap();
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
        let doc: serde_norway::Value = serde_norway::from_str(OPENAPI).unwrap();
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
            if matches!(r.access, Access::Write | Access::Operator) {
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
