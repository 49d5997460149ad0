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
/// a clip over the size limit, a bad part); the router's outermost layer then adds
/// `Connection: close`, as for every refusal of a request with a body.
pub async fn infer(st: State<AppState>, req: Request) -> Response {
    match infer_inner(st, req).await {
        Ok(r) => r,
        Err(e) => e.into_response(),
    }
}

async fn infer_inner(State(st): State<AppState>, req: Request) -> Result<Response, ApiError> {
    // Refuse before reading a byte of the upload when a component is missing.
    st.service.check_infer_ready()?;
    let header_key = super::handlers::idempotency_header(req.headers())?;
    let media_cfg = &st.service.config().media;
    let pace = UploadPace {
        min_bytes_per_s: media_cfg.min_upload_bytes_per_s,
        grace: std::time::Duration::from_secs_f64(media_cfg.upload_grace_s),
    };
    let (req, refused) = refuse_long_preamble(req, pace).await?;
    // A refusal by the guard surfaces in the parser as a body error; answer the guard's.
    let guard_err = |e: ApiError| {
        refused
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take()
            .unwrap_or(e)
    };
    let mut multipart = Multipart::from_request(req, &st).await?;
    let media = &st.service.config().media;
    let spool_dir = st.service.config().spool_dir();
    let mut uploads = Vec::new();
    let mut request_id: Option<String> = None;
    while let Some(field) = multipart
        .next_field()
        .await
        .map_err(|e| guard_err(e.into()))?
    {
        if field.name() == Some("request_id") {
            request_id = Some(read_request_id(field).await.map_err(guard_err)?);
            continue;
        }
        if field.name() == Some("signals") {
            let max = st.service.config().annotate.max_bytes;
            let bytes = read_signals(field, max).await.map_err(guard_err)?;
            match uploads.last_mut() {
                Some(Upload { signals: None, .. }) => {
                    uploads.last_mut().expect("just matched").signals = Some(bytes)
                }
                Some(_) => {
                    return Err(ServiceError::Invalid(
                        "two \"signals\" parts for one clip: send each clip's track right \
                         after its \"video\" part"
                            .into(),
                    )
                    .into())
                }
                None => {
                    return Err(ServiceError::Invalid(
                        "a \"signals\" part before any \"video\" part: send each clip's \
                         track right after its \"video\" part"
                            .into(),
                    )
                    .into())
                }
            }
            continue;
        }
        if field.name() != Some("video") {
            return Err(ServiceError::Invalid(format!(
                "unexpected part {:?}: send each clip as a part named \"video\" (an optional \
                 vehicle-signal track for it as a part named \"signals\" right after it, and \
                 an optional idempotency key as a part named \"request_id\")",
                field.name().unwrap_or("")
            ))
            .into());
        }
        if uploads.len() == media.max_clips {
            return Err(ServiceError::TooManyClips(media.max_clips).into());
        }
        uploads.push(
            spool(field, Some(&spool_dir), media.max_bytes)
                .await
                .map_err(guard_err)?,
        );
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
    Ok(super::handlers::with_position(&st, super::handlers::answer_response(answer)).await)
}

/// A `signals` part: a vehicle-signal track, read into memory up to `max` bytes (413 past it).
async fn read_signals(mut field: Field<'_>, max: u64) -> Result<Vec<u8>, ApiError> {
    let mut buf = Vec::new();
    while let Some(chunk) = field.chunk().await? {
        if (buf.len() + chunk.len()) as u64 > max {
            return Err(ServiceError::SignalsTooLarge(max).into());
        }
        buf.extend_from_slice(&chunk);
    }
    Ok(buf)
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
        signals: None,
    })
}

/// Most bytes a multipart body may carry before its first boundary. RFC 2046 allows a preamble
/// that parsers ignore, and no client has a reason to send more than a line of it (browsers and
/// curl send none). The parser buffers everything before the first boundary and rescans it as it
/// grows, so without this a 200 MiB preamble held 200 MB per request and took minutes of CPU.
/// A constant, not a config field: no legitimate upload comes near it.
pub const MAX_MULTIPART_PREAMBLE: usize = 8 * 1024;

/// Most bytes of one part's header block (`Content-Disposition`, `Content-Type`, ...). The
/// parser buffers a header block until its blank line and rescans it on every read, so an
/// endless header cost CPU and memory without bound; real clients send well under 1 KiB.
pub const MAX_PART_HEADER: usize = 8 * 1024;

/// The boundary exactly as the multipart parser reads it (multer's own parser: a quoted
/// `boundary="x;y"` is one parameter, which splitting the header at `;` got wrong).
fn boundary_of(req: &Request) -> Option<String> {
    let ct = req.headers().get(header::CONTENT_TYPE)?.to_str().ok()?;
    multer::parse_boundary(ct).ok().filter(|b| !b.is_empty())
}

/// Where [`MultipartGuard`] is in the body.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Before the first delimiter; `seen` bytes so far.
    Preamble { seen: usize },
    /// Just after a delimiter: `--` closes the body, anything else starts a header block.
    AfterDelimiter,
    /// In a part's header block, `len` bytes so far, looking for its blank line.
    Header { len: usize },
    /// In a part's data, looking for the next `CRLF--boundary`.
    Data,
    /// After the close delimiter.
    Epilogue,
}

/// Watches a multipart body as it streams past (nothing is buffered but a few bytes carried
/// across chunk edges, so the scan is linear) and refuses it at the first preamble or part
/// header longer than its limit, before the parser has buffered either.
struct MultipartGuard {
    boundary: String,
    /// `--boundary` (the first one may open the body without a line break).
    first: Vec<u8>,
    /// `\r\n--boundary`.
    next: Vec<u8>,
    phase: Phase,
    /// The last bytes of the previous chunk, so a delimiter split across chunks is found.
    carry: Vec<u8>,
}

impl MultipartGuard {
    fn new(boundary: String) -> Self {
        let first = format!("--{boundary}").into_bytes();
        let next = [b"\r\n".as_slice(), &first].concat();
        Self {
            boundary,
            first,
            next,
            phase: Phase::Preamble { seen: 0 },
            carry: Vec::new(),
        }
    }

    fn refuse(&self, kind: &'static str, message: String) -> ApiError {
        ApiError::Body {
            status: StatusCode::BAD_REQUEST,
            kind,
            message,
        }
    }

    /// Scans one chunk; an error refuses the body.
    fn feed(&mut self, chunk: &[u8]) -> Result<(), ApiError> {
        use memchr::memmem;
        let mut buf = std::mem::take(&mut self.carry);
        buf.extend_from_slice(chunk);
        let mut i = 0;
        loop {
            match self.phase {
                Phase::Epilogue => return Ok(()),
                Phase::Preamble { .. } | Phase::Data => {
                    let (pre, seen) = match self.phase {
                        Phase::Preamble { seen } => (true, seen),
                        _ => (false, 0),
                    };
                    let pat: &[u8] = if pre { &self.first } else { &self.next };
                    match memmem::find(&buf[i..], pat) {
                        Some(j) => {
                            if pre && seen + j > MAX_MULTIPART_PREAMBLE {
                                return Err(self.preamble_error());
                            }
                            i += j + pat.len();
                            self.phase = Phase::AfterDelimiter;
                        }
                        None => {
                            let keep = (pat.len() - 1).min(buf.len() - i);
                            let done = buf.len() - i - keep;
                            if pre {
                                let seen = seen + done;
                                if seen > MAX_MULTIPART_PREAMBLE {
                                    return Err(self.preamble_error());
                                }
                                self.phase = Phase::Preamble { seen };
                            }
                            self.carry = buf[buf.len() - keep..].to_vec();
                            return Ok(());
                        }
                    }
                }
                Phase::AfterDelimiter => {
                    if buf.len() - i < 2 {
                        self.carry = buf[i..].to_vec();
                        return Ok(());
                    }
                    self.phase = if &buf[i..i + 2] == b"--" {
                        Phase::Epilogue
                    } else {
                        Phase::Header { len: 0 }
                    };
                }
                Phase::Header { len } => match memmem::find(&buf[i..], b"\r\n\r\n") {
                    Some(j) => {
                        if len + j > MAX_PART_HEADER {
                            return Err(self.header_error());
                        }
                        i += j + 4;
                        self.phase = Phase::Data;
                    }
                    None => {
                        let keep = 3.min(buf.len() - i);
                        let len = len + buf.len() - i - keep;
                        if len > MAX_PART_HEADER {
                            return Err(self.header_error());
                        }
                        self.phase = Phase::Header { len };
                        self.carry = buf[buf.len() - keep..].to_vec();
                        return Ok(());
                    }
                },
            }
        }
    }

    fn preamble_error(&self) -> ApiError {
        self.refuse(
            "multipart_preamble_too_long",
            format!(
                "more than {MAX_MULTIPART_PREAMBLE} bytes before the first multipart boundary \
                 \"--{}\": a multipart/form-data body starts with its boundary",
                self.boundary
            ),
        )
    }

    fn header_error(&self) -> ApiError {
        self.refuse(
            "multipart_header_too_long",
            format!(
                "a part's headers run past {MAX_PART_HEADER} bytes without the blank line that \
                 ends them"
            ),
        )
    }
}

/// The guard's refusal, for the handler to answer instead of the parser's generic body error.
type Refusal = std::sync::Arc<std::sync::Mutex<Option<ApiError>>>;

/// The slowest upload waited for: `min_bytes_per_s` on average from the first poll, after
/// `grace`. `min_bytes_per_s = 0`: no minimum.
#[derive(Debug, Clone, Copy)]
struct UploadPace {
    min_bytes_per_s: u64,
    grace: std::time::Duration,
}

/// `body`, ended with an error (and a 408 `upload_too_slow` in `refused`) when the next chunk
/// has not come by the time the average rate would fall below the minimum. A stalled client
/// is refused at that deadline too, not at the request timeout.
fn paced(
    body: axum::body::BodyDataStream,
    pace: UploadPace,
    refused: Refusal,
) -> futures::stream::BoxStream<'static, Result<Bytes, axum::Error>> {
    if pace.min_bytes_per_s == 0 {
        return body.boxed();
    }
    let start = tokio::time::Instant::now();
    futures::stream::unfold((body, 0u64, false), move |(mut body, bytes, over)| {
        let refused = refused.clone();
        async move {
            if over {
                return None;
            }
            let due = start
                + pace.grace
                + std::time::Duration::from_secs_f64(bytes as f64 / pace.min_bytes_per_s as f64);
            match tokio::time::timeout_at(due, body.next()).await {
                Ok(Some(Ok(chunk))) => {
                    let n = bytes + chunk.len() as u64;
                    Some((Ok(chunk), (body, n, false)))
                }
                Ok(Some(Err(e))) => Some((Err(e), (body, bytes, true))),
                Ok(None) => None,
                Err(_) => {
                    let secs = start.elapsed().as_secs_f64();
                    let msg = format!(
                        "the upload is too slow: {bytes} bytes in {secs:.1} s, below \
                             media.min_upload_bytes_per_s = {}",
                        pace.min_bytes_per_s
                    );
                    *refused.lock().unwrap_or_else(|p| p.into_inner()) = Some(ApiError::Body {
                        status: StatusCode::REQUEST_TIMEOUT,
                        kind: "upload_too_slow",
                        message: msg.clone(),
                    });
                    Some((
                        Err(axum::Error::new(std::io::Error::other(msg))),
                        (body, bytes, true),
                    ))
                }
            }
        }
    })
    .boxed()
}

/// Puts a [`MultipartGuard`] in front of the multipart parser. The guard's first refusal (a
/// preamble over [`MAX_MULTIPART_PREAMBLE`], a part header over [`MAX_PART_HEADER`]) is
/// answered as it is, before the parser sees the bytes: the preamble is checked here, before
/// the parser starts, and a later header refusal ends the stream with an error that
/// [`infer_inner`] turns back into the guard's answer. Without a parsable boundary the request
/// passes unchanged and the parser's own rejection names the problem.
async fn refuse_long_preamble(
    req: Request,
    pace: UploadPace,
) -> Result<(Request, Refusal), ApiError> {
    let refused: Refusal = std::sync::Arc::new(std::sync::Mutex::new(None::<ApiError>));
    let Some(boundary) = boundary_of(&req) else {
        return Ok((req, refused));
    };
    let mut guard = MultipartGuard::new(boundary);
    let (parts, body) = req.into_parts();
    let mut stream = paced(body.into_data_stream(), pace, refused.clone());
    // The preamble: read until the first delimiter (or the end), so that refusal needs no
    // parser at all.
    let mut head: Vec<u8> = Vec::new();
    while matches!(guard.phase, Phase::Preamble { .. }) {
        match stream.next().await {
            Some(Ok(chunk)) => {
                guard.feed(&chunk)?;
                head.extend_from_slice(&chunk);
            }
            Some(Err(e)) => {
                if let Some(why) = refused.lock().unwrap_or_else(|p| p.into_inner()).take() {
                    return Err(why);
                }
                return Err(ApiError::Body {
                    status: StatusCode::BAD_REQUEST,
                    kind: "invalid_multipart",
                    message: format!("cannot read the request body: {e}"),
                });
            }
            // The parser says what an unterminated body is.
            None => break,
        }
    }
    let slot = refused.clone();
    let guarded = stream.map(move |item| {
        let chunk = item?;
        if let Err(e) = guard.feed(&chunk) {
            let msg = e.to_string();
            *slot.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
            return Err(axum::Error::new(std::io::Error::other(msg)));
        }
        Ok(chunk)
    });
    let rest = futures::stream::once(async move { Ok::<_, axum::Error>(Bytes::from(head)) })
        .chain(guarded);
    Ok((Request::from_parts(parts, Body::from_stream(rest)), refused))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn body(boundary: &str, parts: usize, header_pad: usize) -> Vec<u8> {
        let mut b = b"a short preamble\r\n".to_vec();
        for i in 0..parts {
            b.extend(
                format!(
                    "--{boundary}\r\nContent-Disposition: form-data; name=\"video\"; \
                     filename=\"{i}.mp4\"\r\nX-Pad: {}\r\n\r\n",
                    "p".repeat(header_pad)
                )
                .into_bytes(),
            );
            // Data that holds the boundary without its line break, and line breaks.
            b.extend(format!("data --{boundary} \r\n-- {i}\r\n").into_bytes());
            b.extend(std::iter::repeat_n(b'z', 3000));
            b.extend(b"\r\n");
        }
        b.extend(format!("--{boundary}--\r\nepilogue").into_bytes());
        b
    }

    /// Every way of cutting a good body into chunks passes, and ends after the close
    /// delimiter; the same body with an oversized header is refused however it is cut.
    #[test]
    fn the_guard_is_indifferent_to_chunk_edges() {
        let good = body("b0und", 3, 100);
        let bad = body("b0und", 2, MAX_PART_HEADER + 10);
        for size in [1, 2, 3, 5, 7, 64, 1000, 1 << 20] {
            let mut g = MultipartGuard::new("b0und".into());
            for c in good.chunks(size) {
                g.feed(c)
                    .unwrap_or_else(|e| panic!("chunks of {size}: {e}"));
            }
            assert_eq!(g.phase, Phase::Epilogue, "chunks of {size}");
            let mut g = MultipartGuard::new("b0und".into());
            let refused = bad.chunks(size).any(|c| g.feed(c).is_err());
            assert!(refused, "chunks of {size}: an oversized header passed");
        }
        let mut g = MultipartGuard::new("b0und".into());
        let junk = vec![b'x'; MAX_MULTIPART_PREAMBLE + 64];
        assert!(g.feed(&junk).is_err());
    }
}
