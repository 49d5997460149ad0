//! `POST /v1/infer`: upload → decode and sample → context embedding → reporters in parallel →
//! labeler → the /v1/fuse store path. Every blocking step runs on the blocking pool.

use super::error::ApiError;
use super::handlers::{fuse_and_store, FuseOut, Ordered};
use super::pipeline::Pipeline;
use super::AppState;
use axum::extract::multipart::{Field, MultipartError, MultipartRejection};
use axum::extract::{FromRequest, Multipart, Request, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;
use tokio::io::AsyncWriteExt;
use vlmfuse_fusion::RoundRecord;
use vlmfuse_media::MediaError;
use vlmfuse_models::{ClipInput, ClipMeta, FrameRef};

/// One uploaded clip, spooled to a temporary file that is removed when this is dropped.
struct Upload {
    file: tempfile::NamedTempFile,
    file_name: Option<String>,
    bytes: u64,
    upload_ms: f64,
}

#[derive(Serialize)]
struct ReporterOut {
    text: String,
    labels: Vec<String>,
    latency_ms: f64,
    label_ms: f64,
    labeler: String,
}

#[derive(Serialize, Clone)]
struct ClipOut {
    #[serde(skip_serializing_if = "Option::is_none")]
    file_name: Option<String>,
    bytes: u64,
    container: String,
    codec: String,
    duration_s: f64,
    width: u32,
    height: u32,
    fps: f64,
    /// Presentation times of the sampled frames, seconds.
    timestamps_s: Vec<f64>,
}

#[derive(Serialize)]
struct InferClipOut {
    #[serde(flatten)]
    fused: FuseOut,
    reporters: Ordered<ReporterOut>,
    /// Reporters left out of this round, with why.
    failed: Ordered<String>,
    clip: ClipOut,
    timings_ms: Ordered<f64>,
}

#[derive(Serialize)]
struct InferBatchOut {
    clips: Vec<InferClipOut>,
}

/// A clip that went through every stage up to fusion.
struct Processed {
    record: RoundRecord,
    request: Value,
    reporters: Vec<(String, ReporterOut)>,
    failed: Vec<(String, String)>,
    clip: ClipOut,
    timings: Vec<(String, f64)>,
}

fn multipart_error(status: StatusCode, message: String) -> ApiError {
    let kind = match status {
        StatusCode::PAYLOAD_TOO_LARGE => "payload_too_large",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_media_type",
        _ => "invalid_multipart",
    };
    ApiError::Body {
        status,
        kind,
        message,
    }
}

impl From<MultipartRejection> for ApiError {
    fn from(r: MultipartRejection) -> Self {
        multipart_error(r.status(), r.body_text())
    }
}

impl From<MultipartError> for ApiError {
    fn from(r: MultipartError) -> Self {
        multipart_error(r.status(), r.body_text())
    }
}

impl From<MediaError> for ApiError {
    /// The HTTP status of each media failure, chosen here at the edge (the media crate only
    /// classifies): 413 over a size limit, 415 for what is not an accepted video, 422 for a
    /// video that breaks a limit or is damaged, 503 when the decode was stopped by the
    /// request's deadline or cancellation.
    fn from(e: MediaError) -> Self {
        let status = match &e {
            MediaError::Io(_) | MediaError::Internal(_) => {
                return ApiError::Internal(format!("media: {e}"))
            }
            MediaError::TooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            MediaError::NotVideo
            | MediaError::UnsupportedContainer(_)
            | MediaError::UnsupportedCodec(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            MediaError::Empty | MediaError::InvalidOptions(_) => StatusCode::BAD_REQUEST,
            MediaError::NoVideoStream
            | MediaError::Corrupt(_)
            | MediaError::TooLong { .. }
            | MediaError::ResolutionTooHigh { .. }
            | MediaError::TooManyFrames { .. } => StatusCode::UNPROCESSABLE_ENTITY,
            MediaError::Cancelled | MediaError::DeadlineExceeded => StatusCode::SERVICE_UNAVAILABLE,
        };
        ApiError::Body {
            status,
            kind: e.kind(),
            message: e.to_string(),
        }
    }
}

fn stage(name: &'static str, start: Instant) -> f64 {
    let s = start.elapsed().as_secs_f64();
    metrics::histogram!("vlmfuse_stage_seconds", "stage" => name).record(s);
    s * 1e3
}

/// `POST /v1/infer`.
pub async fn infer(State(st): State<AppState>, req: Request) -> Result<Response, ApiError> {
    let pipeline = st.pipeline.clone();
    let blockers = pipeline.infer_blockers();
    if !blockers.is_empty() {
        let what = if pipeline.not_configured.is_empty() {
            "not ready"
        } else {
            "not configured"
        };
        return Err(ApiError::NotReady {
            message: format!(
                "clip ingestion is {what}: {}; POST /v1/fuse still takes reports with a context",
                blockers.join("; ")
            ),
            not_ready: blockers,
        });
    }
    let mut multipart = Multipart::from_request(req, &st).await?;
    let media = &st.cfg.media;
    let mut uploads = Vec::new();
    while let Some(field) = multipart.next_field().await? {
        if field.name() != Some("video") {
            return Err(ApiError::Invalid(format!(
                "unexpected part {:?}: send each clip as a part named \"video\"",
                field.name().unwrap_or("")
            )));
        }
        if uploads.len() == media.max_clips {
            return Err(ApiError::Body {
                status: StatusCode::UNPROCESSABLE_ENTITY,
                kind: "too_many_clips",
                message: format!("more than {} clips in one request", media.max_clips),
            });
        }
        uploads.push(spool(field, media.temp_dir.as_deref(), media.max_bytes).await?);
    }
    if uploads.is_empty() {
        return Err(ApiError::Invalid(
            "no part named \"video\": send clips as multipart/form-data parts named \"video\""
                .into(),
        ));
    }
    let batch = uploads.len() > 1;

    let mut processed = Vec::with_capacity(uploads.len());
    for up in &uploads {
        processed.push(process(&st, &pipeline, up).await?);
    }
    let records = processed
        .iter_mut()
        .map(|p| (p.record.clone(), std::mem::take(&mut p.request)))
        .collect();
    let fuse_start = Instant::now();
    let fused = fuse_and_store(&st, records, batch).await?;
    let fuse_ms = stage("fuse", fuse_start);
    drop(uploads);

    let clips: Vec<InferClipOut> = fused
        .into_iter()
        .zip(processed)
        .map(|(fused, p)| {
            let mut timings = p.timings;
            timings.push(("fuse".into(), fuse_ms));
            InferClipOut {
                fused,
                reporters: Ordered(p.reporters),
                failed: Ordered(p.failed),
                clip: p.clip,
                timings_ms: Ordered(timings),
            }
        })
        .collect();
    Ok(if batch {
        axum::Json(InferBatchOut { clips }).into_response()
    } else {
        axum::Json(clips.into_iter().next().expect("one clip")).into_response()
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
    b.prefix("vlmfuse-clip-").suffix(&suffix);
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

/// Decode, embed, report and label one clip.
async fn process(st: &AppState, p: &Arc<Pipeline>, up: &Upload) -> Result<Processed, ApiError> {
    let media = &st.cfg.media;
    let mut timings = vec![("upload".to_string(), up.upload_ms)];

    let start = Instant::now();
    let path = up.file.path().to_path_buf();
    let (opts, limits) = (media.sample_options(), media.limits());
    let decode_path = path.clone();
    let decoded = tokio::task::spawn_blocking(move || {
        vlmfuse_media::sample_frames(&decode_path, &opts, &limits)
    })
    .await
    .map_err(|e| ApiError::Internal(format!("decoding task failed: {e}")))??;
    timings.push(("decode".into(), stage("decode", start)));
    let info = decoded.info.clone();
    let clip = ClipOut {
        file_name: up.file_name.clone(),
        bytes: up.bytes,
        container: info.container.clone(),
        codec: info.codec.clone(),
        duration_s: info.duration_s,
        width: info.width,
        height: info.height,
        fps: info.fps,
        timestamps_s: decoded.timestamps(),
    };
    let frames: Arc<[vlmfuse_models::Frame]> = decoded
        .frames
        .into_iter()
        .map(|f| vlmfuse_models::Frame {
            width: f.width,
            height: f.height,
            rgb: f.rgb,
            t_s: f.pts_s,
        })
        .collect();

    let start = Instant::now();
    let embedder = p.embedder.clone().expect("checked before");
    let embed_frames = frames.clone();
    let context = tokio::task::spawn_blocking(move || {
        let refs: Vec<FrameRef> = embed_frames.iter().map(|f| f.as_ref()).collect();
        embedder.embed(&refs)
    })
    .await
    .map_err(|e| ApiError::Internal(format!("embedding task failed: {e}")))?
    .map_err(|e| ApiError::Internal(format!("embedder: {e}")))?;
    timings.push(("embed".into(), stage("embed", start)));

    let start = Instant::now();
    let input = ClipInput {
        path,
        frames,
        meta: ClipMeta {
            clip_id: up.file_name.clone(),
            duration_s: Some(info.duration_s),
            fps: Some(info.fps),
            width: Some(info.width),
            height: Some(info.height),
        },
    };
    let runs = futures::future::join_all(p.reporters.iter().map(|r| {
        let input = &input;
        async move {
            vlmfuse_models::run_all(std::slice::from_ref(&r.reporter), input, r.timeout)
                .await
                .pop()
                .expect("one reporter, one result")
        }
    }))
    .await;
    timings.push(("reporters".into(), stage("reporters", start)));

    let start = Instant::now();
    let labeler = p.labeler.clone().expect("checked before");
    let mut failed = p.unloaded_reporters.clone();
    let mut answered = Vec::new();
    for (name, res) in runs {
        match res {
            Ok(out) => answered.push((name, out)),
            Err(e) => {
                metrics::counter!("vlmfuse_reporter_failures_total", "reporter" => name.clone(), "stage" => "run")
                    .increment(1);
                failed.push((name, format!("{}: {e}", e.kind())));
            }
        }
    }
    let labelled = futures::future::join_all(answered.into_iter().map(|(name, out)| {
        let labeler = labeler.clone();
        async move {
            let t = Instant::now();
            let res = labeler.label(&out.text).await;
            (name, out, res, t.elapsed().as_secs_f64() * 1e3)
        }
    }))
    .await;
    timings.push(("label".into(), stage("label", start)));

    let mut reports = BTreeMap::new();
    let mut reporters = Vec::new();
    let mut raw = serde_json::Map::new();
    for (name, out, res, label_ms) in labelled {
        match res {
            Ok(l) => {
                reports.insert(name.clone(), l.labels.clone());
                raw.insert(
                    name.clone(),
                    json!({"text": out.text, "labels": l.labels, "latency_ms": out.latency_ms,
                           "model": out.model}),
                );
                reporters.push((
                    name,
                    ReporterOut {
                        text: out.text,
                        labels: l.labels,
                        latency_ms: out.latency_ms,
                        label_ms,
                        labeler: p.labeler_name.clone(),
                    },
                ));
            }
            Err(e) => {
                metrics::counter!("vlmfuse_reporter_failures_total", "reporter" => name.clone(), "stage" => "label")
                    .increment(1);
                failed.push((name, format!("labeling failed: {e}")));
            }
        }
    }
    if reports.is_empty() {
        return Err(ApiError::ReportersFailed(failed));
    }
    // Keep the configured order in `failed` whatever finished first.
    let order = |n: &str| st.cfg.reporters.iter().position(|r| r == n);
    failed.sort_by_key(|(n, _)| order(n));
    reporters.sort_by_key(|(n, _)| order(n));

    let request = json!({
        "id": up.file_name,
        "reports": reports,
        "source": "infer",
        "clip": clip,
        "raw": raw,
        "failed": failed.iter().cloned().collect::<BTreeMap<_, _>>(),
        "labeler": p.labeler_name,
    });
    Ok(Processed {
        record: RoundRecord {
            id: up.file_name.clone(),
            context: context.into_iter().map(f64::from).collect(),
            reports,
            truth: None,
        },
        request,
        reporters,
        failed,
        clip,
        timings,
    })
}
