//! `POST /v1/infer` at the HTTP edge: the multipart upload streamed to temporary files, then the
//! service's clip pipeline.

use super::error::ApiError;
use super::AppState;
use crate::service::{stage, ServiceError, Upload};
use axum::extract::multipart::Field;
use axum::extract::{FromRequest, Multipart, Request, State};
use axum::response::{IntoResponse, Response};
use std::time::Instant;
use tokio::io::AsyncWriteExt;
use vlmfuse_media::MediaError;

/// `POST /v1/infer`.
pub async fn infer(State(st): State<AppState>, req: Request) -> Result<Response, ApiError> {
    // Refuse before reading a byte of the upload when a component is missing.
    st.service.check_infer_ready()?;
    let mut multipart = Multipart::from_request(req, &st).await?;
    let media = &st.service.config().media;
    let spool_dir = st.service.config().spool_dir();
    let mut uploads = Vec::new();
    while let Some(field) = multipart.next_field().await? {
        if field.name() != Some("video") {
            return Err(ServiceError::Invalid(format!(
                "unexpected part {:?}: send each clip as a part named \"video\"",
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
    let out = st.service.infer(uploads).await?;
    Ok(if out.batch {
        axum::Json(crate::wire::InferBatchOut { clips: out.clips }).into_response()
    } else {
        axum::Json(out.clips.into_iter().next().expect("one clip")).into_response()
    })
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
    b.prefix(crate::service::SPOOL_PREFIX).suffix(&suffix);
    let file = match dir {
        Some(d) => b.tempfile_in(d),
        None => b.tempfile(),
    }
    .map_err(io)?;
    let mut out = tokio::fs::File::from_std(file.reopen().map_err(io)?);
    let mut bytes = 0u64;
    while let Some(chunk) = field.chunk().await? {
        bytes += chunk.len() as u64;
        if bytes > max_bytes {
            return Err(MediaError::TooLarge { bytes, max_bytes }.into());
        }
        out.write_all(&chunk).await.map_err(io)?;
    }
    out.flush().await.map_err(io)?;
    drop(out);
    Ok(Upload {
        file,
        file_name,
        bytes,
        upload_ms: stage("upload", start),
    })
}
