//! `POST /v1/infer` at the HTTP edge: the multipart upload streamed to temporary files, then the
//! service's clip pipeline.

use super::error::ApiError;
use super::AppState;
use crate::service::{stage, ServiceError, Upload};
use axum::body::{Body, Bytes};
use axum::extract::multipart::Field;
use axum::extract::{FromRequest, Multipart, Request, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use futures::StreamExt;
use sha2::Digest;
use std::time::Instant;
use tokio::io::AsyncWriteExt;
use vlmfuse_media::MediaError;

/// `POST /v1/infer`. A refusal may come before the body was read to its end (a long preamble,
/// a clip over the size limit, a bad part): the answer then says `Connection: close`, since
/// the unread rest of the body would otherwise be taken for the next request, and a client
/// reusing the connection would fail its next request.
pub async fn infer(st: State<AppState>, req: Request) -> Response {
    match infer_inner(st, req).await {
        Ok(r) => r,
        Err(e) => {
            let mut resp = e.into_response();
            resp.headers_mut().insert(
                header::CONNECTION,
                axum::http::HeaderValue::from_static("close"),
            );
            resp
        }
    }
}

async fn infer_inner(State(st): State<AppState>, req: Request) -> Result<Response, ApiError> {
    // Refuse before reading a byte of the upload when a component is missing.
    st.service.check_infer_ready()?;
    let header_key = super::handlers::idempotency_header(req.headers())?;
    let req = refuse_long_preamble(req).await?;
    let mut multipart = Multipart::from_request(req, &st).await?;
    let media = &st.service.config().media;
    let spool_dir = st.service.config().spool_dir();
    let mut uploads = Vec::new();
    let mut request_id: Option<String> = None;
    while let Some(field) = multipart.next_field().await? {
        if field.name() == Some("request_id") {
            request_id = Some(read_request_id(field).await?);
            continue;
        }
        if field.name() != Some("video") {
            return Err(ServiceError::Invalid(format!(
                "unexpected part {:?}: send each clip as a part named \"video\" (and an \
                 optional idempotency key as a part named \"request_id\")",
                field.name().unwrap_or("")
            ))
            .into());
        }
        if uploads.len() == media.max_clips {
            return Err(ServiceError::TooManyClips(media.max_clips).into());
        }
        uploads.push(spool(field, Some(&spool_dir), media.max_bytes).await?);
    }
    if uploads.is_empty() {
        return Err(ServiceError::Invalid(
            "no part named \"video\": send clips as multipart/form-data parts named \"video\""
                .into(),
        )
        .into());
    }
    let answer = st
        .service
        .infer(uploads, header_key.as_deref(), request_id.as_deref())
        .await?;
    Ok(super::handlers::answer_response(answer))
}

/// The `request_id` part: a short text (an idempotency key).
async fn read_request_id(mut field: Field<'_>) -> Result<String, ApiError> {
    let mut buf = Vec::new();
    while let Some(chunk) = field.chunk().await? {
        buf.extend_from_slice(&chunk);
        if buf.len() > crate::service::fuse_max_key_len() {
            return Err(ServiceError::Invalid(format!(
                "the request_id part is longer than {} bytes",
                crate::service::fuse_max_key_len()
            ))
            .into());
        }
    }
    String::from_utf8(buf)
        .map_err(|_| ServiceError::Invalid("the request_id part is not UTF-8".into()).into())
}

/// Streams one part to a temporary file, refusing it as soon as it passes `max_bytes`.
async fn spool(
    mut field: Field<'_>,
    dir: Option<&std::path::Path>,
    max_bytes: u64,
) -> Result<Upload, ApiError> {
    let start = Instant::now();
    let file_name = field.file_name().map(str::to_string);
    // Keep a short alphanumeric extension: some reporters (video_url) guess the type from it.
    let suffix = file_name
        .as_deref()
        .and_then(|n| n.rsplit_once('.'))
        .map(|(_, e)| e)
        .filter(|e| !e.is_empty() && e.len() <= 5 && e.chars().all(|c| c.is_ascii_alphanumeric()))
        .map(|e| format!(".{e}"))
        .unwrap_or_default();
    let io = |e: std::io::Error| ApiError::Internal(format!("cannot spool the upload: {e}"));
    let mut b = tempfile::Builder::new();
    let prefix = crate::service::spool_prefix();
    b.prefix(&prefix).suffix(&suffix);
    let file = match dir {
        Some(d) => b.tempfile_in(d),
        None => b.tempfile(),
    }
    .map_err(io)?;
    let mut out = tokio::fs::File::from_std(file.reopen().map_err(io)?);
    let mut bytes = 0u64;
    let mut hash = sha2::Sha256::new();
    while let Some(chunk) = field.chunk().await? {
        bytes += chunk.len() as u64;
        if bytes > max_bytes {
            return Err(MediaError::TooLarge { bytes, max_bytes }.into());
        }
        hash.update(&chunk);
        out.write_all(&chunk).await.map_err(io)?;
    }
    out.flush().await.map_err(io)?;
    drop(out);
    Ok(Upload {
        file,
        file_name,
        bytes,
        upload_ms: stage("upload", start),
        sha256: hash.finalize().into(),
    })
}

/// Most bytes a multipart body may carry before its first boundary. RFC 2046 allows a preamble
/// that parsers ignore, and no client has a reason to send more than a line of it (browsers and
/// curl send none). The parser buffers everything before the first boundary and rescans it as it
/// grows, so without this a 200 MiB preamble held 200 MB per request and took minutes of CPU.
/// A constant, not a config field: no legitimate upload comes near it.
pub const MAX_MULTIPART_PREAMBLE: usize = 8 * 1024;

/// The `boundary` parameter of a `multipart/*` content type (quoted or not).
fn boundary_of(req: &Request) -> Option<String> {
    let ct = req.headers().get(header::CONTENT_TYPE)?.to_str().ok()?;
    let (mime, params) = ct.split_once(';')?;
    if !mime.trim().to_ascii_lowercase().starts_with("multipart/") {
        return None;
    }
    params.split(';').find_map(|p| {
        let (k, v) = p.split_once('=')?;
        k.trim()
            .eq_ignore_ascii_case("boundary")
            .then(|| v.trim().trim_matches('"').to_string())
            .filter(|b| !b.is_empty())
    })
}

/// Reads the body up to its first boundary and refuses it (400 `multipart_preamble_too_long`)
/// once more than [`MAX_MULTIPART_PREAMBLE`] bytes came without one; the bytes read are put back
/// in front of the rest of the stream for the multipart parser. Without a parsable boundary the
/// request passes unchanged and the parser's own rejection names the problem.
async fn refuse_long_preamble(req: Request) -> Result<Request, ApiError> {
    let Some(boundary) = boundary_of(&req) else {
        return Ok(req);
    };
    let delimiter = format!("--{boundary}").into_bytes();
    // The delimiter must start within the allowed preamble.
    let window = MAX_MULTIPART_PREAMBLE + delimiter.len();
    let (parts, body) = req.into_parts();
    let mut stream = body.into_data_stream();
    let mut head: Vec<u8> = Vec::new();
    loop {
        let searched = head.len().min(window);
        if head[..searched]
            .windows(delimiter.len())
            .any(|w| w == delimiter.as_slice())
        {
            break;
        }
        if head.len() >= window {
            return Err(ApiError::Body {
                status: StatusCode::BAD_REQUEST,
                kind: "multipart_preamble_too_long",
                message: format!(
                    "more than {MAX_MULTIPART_PREAMBLE} bytes before the first multipart boundary \
                     \"--{boundary}\": a multipart/form-data body starts with its boundary"
                ),
            });
        }
        match stream.next().await {
            Some(Ok(chunk)) => head.extend_from_slice(&chunk),
            Some(Err(e)) => {
                return Err(ApiError::Body {
                    status: StatusCode::BAD_REQUEST,
                    kind: "invalid_multipart",
                    message: format!("cannot read the request body: {e}"),
                })
            }
            // The parser says what an unterminated body is.
            None => break,
        }
    }
    let rest =
        futures::stream::once(async move { Ok::<_, axum::Error>(Bytes::from(head)) }).chain(stream);
    Ok(Request::from_parts(parts, Body::from_stream(rest)))
}
