//! The operator page (docs/UI.md): `/ui` and its assets, embedded in the binary (no CDN, no
//! network fetch), the login that turns the bearer token into a cookie, and the `/ui/api/*`
//! reads the page polls. With `server.api_key` set, the page without a valid cookie is the login
//! form only, and every `/ui/api/*` read needs the cookie or the bearer header.
//!
//! The cookie holds no token: it is `<expiry>.<SHA-256 of the key and the expiry>`, HttpOnly
//! (scripts cannot read it) and SameSite=Strict (another site's page cannot send it). A writing
//! route takes it only with the `X-Vlmfuse-Ui: 1` header, which a cross-site form cannot set and a
//! cross-site script cannot send without a CORS preflight this server never answers, so the
//! cookie is no way around the token for anyone but the page.

use super::error::ApiError;
use super::{constant_time_eq, has_token, AppState};
use crate::service::{EdgeCounts, ServiceError};
use axum::extract::rejection::{FormRejection, PathRejection, QueryRejection};
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::{Form, Json};
use serde::Deserialize;
use sha2::{Digest, Sha256};
use std::sync::atomic::Ordering;

const INDEX: &str = include_str!("../ui/assets/index.html");
const LOGIN: &str = include_str!("../ui/assets/login.html");
const APP_JS: &str = include_str!("../ui/assets/app.js");
const APP_CSS: &str = include_str!("../ui/assets/app.css");

/// The login cookie's name.
pub const COOKIE: &str = "vlmfuse_ui";
/// The header that lets a writing route take the cookie.
pub const UI_HEADER: &str = "x-vlmfuse-ui";

/// Scripts and styles from this server only; frames, forms and plugins nowhere else.
const CSP: &str = "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; \
                   img-src 'self' data:; connect-src 'self'; form-action 'self'; \
                   frame-ancestors 'none'; base-uri 'none'; object-src 'none'";

fn now_s() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

fn seal(key: &str, expires: u64) -> String {
    let mut h = Sha256::new();
    h.update(b"vlmfuse-ui-session\0");
    h.update(expires.to_string().as_bytes());
    h.update(b"\0");
    h.update(key.as_bytes());
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

/// The cookie's value for a session ending at `expires` (Unix seconds).
fn cookie_value(key: &str, expires: u64) -> String {
    format!("{expires}.{}", seal(key, expires))
}

/// Whether the request carries a login cookie that is ours and not expired.
pub(crate) fn has_cookie(st: &AppState, headers: &HeaderMap) -> bool {
    let Some(key) = &st.service.config().server.api_key else {
        return false;
    };
    let now = now_s();
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .filter_map(|c| c.trim().strip_prefix(COOKIE)?.strip_prefix('='))
        .any(|v| {
            let Some((exp, mac)) = v.split_once('.') else {
                return false;
            };
            let Ok(exp) = exp.parse::<u64>() else {
                return false;
            };
            exp > now && constant_time_eq(mac.as_bytes(), seal(key, exp).as_bytes())
        })
}

/// Whether a read of the page's data may go ahead: no key configured, the bearer token, or the
/// cookie.
pub(crate) fn operator(st: &AppState, headers: &HeaderMap) -> bool {
    st.service.config().server.api_key.is_none()
        || has_token(st, headers)
        || has_cookie(st, headers)
}

/// Whether a writing route may take the cookie instead of the bearer token.
pub(crate) fn page_write(st: &AppState, headers: &HeaderMap) -> bool {
    headers.get(UI_HEADER).is_some_and(|v| v.as_bytes() == b"1") && has_cookie(st, headers)
}

fn enabled(st: &AppState) -> Result<(), ApiError> {
    if st.service.config().ui.enabled {
        Ok(())
    } else {
        Err(ApiError::NotFound("/ui (ui.enabled = false)".into()))
    }
}

fn page(body: String) -> Response {
    let mut resp = (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        body,
    )
        .into_response();
    let h = resp.headers_mut();
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    resp
}

fn redirect(to: &'static str, cookie: Option<String>) -> Response {
    let mut resp = (StatusCode::SEE_OTHER, [(header::LOCATION, to)]).into_response();
    if let Some(c) = cookie.and_then(|c| HeaderValue::from_str(&c).ok()) {
        resp.headers_mut().insert(header::SET_COOKIE, c);
    }
    resp.headers_mut()
        .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    resp
}

/// `GET /`: to the operator page.
pub async fn root() -> Response {
    redirect("/ui", None)
}

/// `GET /ui`: the page, or the login form when a key is set and the request has no session.
pub async fn index(State(st): State<AppState>, headers: HeaderMap) -> Result<Response, ApiError> {
    enabled(&st)?;
    if !operator(&st, &headers) {
        return Ok(page(LOGIN.to_string()));
    }
    let poll = st.service.config().ui.poll_ms;
    Ok(page(INDEX.replace(
        "name=\"vlmfuse-poll-ms\" content=\"2000\"",
        &format!("name=\"vlmfuse-poll-ms\" content=\"{poll}\""),
    )))
}

#[derive(Deserialize)]
pub struct LoginIn {
    token: String,
}

/// `POST /ui/login`: the right token sets the session cookie; either way back to `/ui`.
pub async fn login(
    State(st): State<AppState>,
    form: Result<Form<LoginIn>, FormRejection>,
) -> Result<Response, ApiError> {
    enabled(&st)?;
    let Form(form) = form.map_err(|r| ApiError::Body {
        status: r.status(),
        kind: "invalid_request",
        message: r.body_text(),
    })?;
    let cfg = st.service.config();
    let Some(key) = &cfg.server.api_key else {
        return Ok(redirect("/ui", None));
    };
    if !constant_time_eq(form.token.trim().as_bytes(), key.as_bytes()) {
        metrics::counter!("vlmfuse_ui_logins_total", "result" => "refused").increment(1);
        return Ok(redirect("/ui?login=failed", None));
    }
    metrics::counter!("vlmfuse_ui_logins_total", "result" => "accepted").increment(1);
    let max_age = cfg.ui.session_s;
    let value = cookie_value(key, now_s() + max_age);
    Ok(redirect(
        "/ui",
        Some(format!(
            "{COOKIE}={value}; Path=/; Max-Age={max_age}; HttpOnly; SameSite=Strict"
        )),
    ))
}

/// `POST /ui/logout`: forgets the session cookie.
pub async fn logout(State(st): State<AppState>) -> Result<Response, ApiError> {
    enabled(&st)?;
    Ok(redirect(
        "/ui",
        Some(format!(
            "{COOKIE}=; Path=/; Max-Age=0; HttpOnly; SameSite=Strict"
        )),
    ))
}

fn asset(ct: &'static str, body: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, ct),
            (header::CACHE_CONTROL, "no-cache"),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
        ],
        body,
    )
        .into_response()
}

/// `GET /ui/app.js`.
pub async fn app_js(State(st): State<AppState>) -> Result<Response, ApiError> {
    enabled(&st)?;
    Ok(asset("text/javascript; charset=utf-8", APP_JS))
}

/// `GET /ui/app.css`.
pub async fn app_css(State(st): State<AppState>) -> Result<Response, ApiError> {
    enabled(&st)?;
    Ok(asset("text/css; charset=utf-8", APP_CSS))
}

/// `GET /ui/api/summary`: every panel's numbers.
pub async fn summary(State(st): State<AppState>) -> Result<Response, ApiError> {
    enabled(&st)?;
    let c = &st.counts;
    let limit = st.service.config().limits.concurrency_limit;
    let edge = EdgeCounts {
        in_flight: limit.saturating_sub(st.limiter.available_permits()),
        limit,
        client: c.client.load(Ordering::Relaxed),
        server: c.server.load(Ordering::Relaxed),
        overload: c.overload.load(Ordering::Relaxed),
    };
    let mut resp = Json(st.service.ui_summary(edge).await).into_response();
    no_store(&mut resp);
    Ok(resp)
}

fn no_store(resp: &mut Response) {
    resp.headers_mut()
        .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RoundsQuery {
    before: Option<u64>,
    limit: Option<usize>,
}

fn bad_request(status: StatusCode, message: String) -> ApiError {
    ApiError::Body {
        status,
        kind: "invalid_request",
        message,
    }
}

/// `GET /ui/api/rounds?before=&limit=`.
pub async fn rounds(
    State(st): State<AppState>,
    q: Result<Query<RoundsQuery>, QueryRejection>,
) -> Result<Response, ApiError> {
    enabled(&st)?;
    let Query(q) = q.map_err(|r| bad_request(r.status(), r.body_text()))?;
    let limit = q.limit.unwrap_or(20);
    if limit == 0 || limit > crate::service::MAX_PAGE {
        return Err(ServiceError::Invalid(format!(
            "limit must be between 1 and {}, got {limit}",
            crate::service::MAX_PAGE
        ))
        .into());
    }
    let mut resp = Json(st.service.ui_rounds(q.before, limit).await?).into_response();
    no_store(&mut resp);
    Ok(resp)
}

/// `GET /ui/api/rounds/{round_id}`.
pub async fn round(
    State(st): State<AppState>,
    id: Result<Path<String>, PathRejection>,
) -> Result<Response, ApiError> {
    enabled(&st)?;
    let Path(id) = id.map_err(|r| bad_request(r.status(), r.body_text()))?;
    let mut resp = Json(st.service.ui_round(&id).await?).into_response();
    no_store(&mut resp);
    Ok(resp)
}

/// `GET /ui/api/rounds/{round_id}/frames/{index}`.
pub async fn frame(
    State(st): State<AppState>,
    p: Result<Path<(String, u32)>, PathRejection>,
) -> Result<Response, ApiError> {
    enabled(&st)?;
    let Path((id, index)) = p.map_err(|r| bad_request(r.status(), r.body_text()))?;
    let jpeg = st.service.ui_frame(&id, index).await?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/jpeg"),
            (header::CACHE_CONTROL, "private, max-age=3600"),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
        ],
        jpeg,
    )
        .into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sealed_session_names_its_key_and_expiry() {
        let v = cookie_value("k", 100);
        let (exp, mac) = v.split_once('.').unwrap();
        assert_eq!(exp, "100");
        assert_eq!(mac, seal("k", 100));
        assert_ne!(mac, seal("k", 101));
        assert_ne!(mac, seal("other", 100));
        assert_eq!(mac.len(), 64);
    }
}
