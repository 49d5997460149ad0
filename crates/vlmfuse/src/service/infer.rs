//! `/v1/infer`'s work once the clips are on disk: decode and sample → context embedding →
//! reporters in parallel (each sees all of the request's clips at once: an in-process model runs
//! them as one batch) → labeler → the /v1/fuse store path. Blocking steps run off the async
//! threads: decoding on the blocking pool, the models on their own workers.

use super::fuse::{fingerprint, idempotency_key, Answer, IdemRequest, Render};
use super::{Service, ServiceError};
use crate::wire::{ClipOut, InferClipOut, Ordered, ReporterOut};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use vlmfuse_fusion::RoundRecord;
use vlmfuse_models::{ClipInput, ClipMeta};

/// One uploaded clip, spooled to a temporary file that is removed when this is dropped.
pub struct Upload {
    pub file: tempfile::NamedTempFile,
    pub file_name: Option<String>,
    pub bytes: u64,
    pub upload_ms: f64,
    /// SHA-256 of the clip's bytes: what an idempotency key's request is recognised by.
    pub sha256: [u8; 32],
    /// The clip's vehicle-signal track (a `signals` part after its `video` part), as sent.
    pub signals: Option<Vec<u8>>,
}

/// A clip decoded and embedded, ready for the reporters.
struct Decoded {
    input: ClipInput,
    context: Vec<f32>,
    clip: ClipOut,
    timings: Vec<(String, f64)>,
    thumbnails: Vec<vlmfuse_store::browse::Thumbnail>,
}

/// A clip that went through every stage up to fusion.
struct Processed {
    /// What the rules derived from the clip's signal track.
    derived: Option<vlmfuse_annotate::Annotation>,
    /// What the detector derived from the clip's frames, or why it did not run.
    detected: Option<Result<vlmfuse_detect::DetectAnnotation, String>>,
    record: RoundRecord,
    request: Value,
    reporters: Vec<(String, ReporterOut)>,
    failed: Vec<(String, String)>,
    clip: ClipOut,
    timings: Vec<(String, f64)>,
    thumbnails: Vec<vlmfuse_store::browse::Thumbnail>,
}

/// Labels a round's answers the way `labeler_eval` scores them: in one `label_batch` call (the
/// embedding labeler encodes every clause of every answer in one pass; a pooled labeler takes one
/// queue slot for the round). Each answer's `label_ms` is the round's, since they were labelled
/// together. When the batch fails, the answers are labelled one by one so that a failure (a
/// remote LLM's bad answer) is charged to the reporter whose text caused it and the others still
/// count.
async fn label_round(
    labeler: &dyn vlmfuse_labeler::Labeler,
    answered: Vec<(String, vlmfuse_models::ReporterOutput)>,
) -> Vec<(
    String,
    vlmfuse_models::ReporterOutput,
    Result<vlmfuse_labeler::LabelerOutput, vlmfuse_labeler::LabelerError>,
    f64,
)> {
    let t = Instant::now();
    let texts: Vec<&str> = answered.iter().map(|(_, o)| o.text.as_str()).collect();
    match labeler.label_batch(&texts).await {
        Ok(outs) if outs.len() == answered.len() => {
            let ms = t.elapsed().as_secs_f64() * 1e3;
            answered
                .into_iter()
                .zip(outs)
                .map(|((name, out), l)| (name, out, Ok(l), ms))
                .collect()
        }
        first => {
            if let Err(e) = &first {
                tracing::warn!(error = %e, "labelling the round failed; labelling each answer");
            }
            futures::future::join_all(answered.into_iter().map(|(name, out)| async move {
                let t = Instant::now();
                let res = labeler.label(&out.text).await;
                (name, out, res, t.elapsed().as_secs_f64() * 1e3)
            }))
            .await
        }
    }
}

/// A clip's derived truth for a partial feedback (`None`: nothing decided or not sent).
type Truth = Option<Vec<u8>>;

/// Records a stage's time in `vlmfuse_stage_seconds` and returns it in milliseconds.
pub(crate) fn stage(name: &'static str, start: Instant) -> f64 {
    let s = start.elapsed().as_secs_f64();
    metrics::histogram!("vlmfuse_stage_seconds", "stage" => name).record(s);
    s * 1e3
}

impl Service {
    /// Refuses `/v1/infer` before its upload is read when a component it needs is missing.
    pub fn check_infer_ready(&self) -> Result<(), ServiceError> {
        let pipeline = &self.pipeline;
        let blockers = pipeline.infer_blockers();
        if blockers.is_empty() {
            return Ok(());
        }
        let what = if pipeline.not_configured.is_empty() {
            "not ready"
        } else {
            "not configured"
        };
        Err(ServiceError::NotReady {
            message: format!(
                "clip ingestion is {what}: {}; POST /v1/fuse still takes reports with a context",
                blockers.join("; ")
            ),
            not_ready: blockers,
        })
    }

    /// Processes every clip, then fuses and stores them together (all or nothing). With an
    /// idempotency key (header or `request_id` part) a repeat of a stored request answers the
    /// stored answer before any model runs.
    pub async fn infer(
        &self,
        uploads: Vec<Upload>,
        header_key: Option<&str>,
        field_key: Option<&str>,
    ) -> Result<Answer, ServiceError> {
        self.check_infer_ready()?;
        let idem = match idempotency_key(header_key, field_key)? {
            None => None,
            Some(key) => {
                let mut parts: Vec<&[u8]> = vec![b"/v1/infer"];
                for u in &uploads {
                    parts.push(u.file_name.as_deref().unwrap_or("").as_bytes());
                    parts.push(&u.sha256);
                    // A clip with a track is another request than the clip alone.
                    parts.push(match &u.signals {
                        Some(s) => s,
                        None => b"\0no-signals",
                    });
                }
                Some(IdemRequest {
                    key,
                    fingerprint: fingerprint(&parts),
                })
            }
        };
        if let Some(i) = &idem {
            if let Some(answer) = self.replay("/v1/infer", i).await? {
                return Ok(answer);
            }
        }
        let batch = uploads.len() > 1;
        // Tracks first: a bad one is refused before any decoding or model work.
        let at = |i: usize, e: ServiceError| match e {
            ServiceError::Signals { kind, message } if batch => ServiceError::Signals {
                kind,
                message: format!("clip {i}: {message}"),
            },
            e => e,
        };
        let mut tracks = Vec::with_capacity(uploads.len());
        for (i, up) in uploads.iter().enumerate() {
            tracks.push(match &up.signals {
                Some(b) => Some(
                    super::annotate::parse_track(&self.cfg.annotate, b).map_err(|e| at(i, e))?,
                ),
                None => None,
            });
        }
        let mut decoded = Vec::with_capacity(uploads.len());
        let mut derived = Vec::with_capacity(uploads.len());
        for (i, (up, track)) in uploads.iter().zip(&tracks).enumerate() {
            let d = self.decode_and_embed(up).await?;
            derived.push(match track {
                Some(t) => Some(
                    super::annotate::derive(&self.cfg.annotate, t, Some(d.clip.info.duration_s))
                        .map_err(|e| at(i, e))?,
                ),
                None => None,
            });
            decoded.push(d);
        }
        // Every reporter sees all the request's clips at once: an in-process model runs them as
        // one batch (one vision pass, one prefill), a remote one concurrently. The detector
        // (clip by clip, on the blocking pool) runs meanwhile: behind remote reporters it costs
        // no time.
        let inputs: Vec<ClipInput> = decoded.iter().map(|d| d.input.clone()).collect();
        let reporters = async {
            let start = Instant::now();
            let runs = vlmfuse_models::run_all_batch(&self.pipeline.reporters, &inputs).await;
            (runs, stage("reporters", start))
        };
        let detections = async {
            let mut out = Vec::with_capacity(inputs.len());
            for input in &inputs {
                let start = Instant::now();
                let det = self.detect_clip(&input.path, &input.frames).await;
                let ms = det.is_some().then(|| stage("detect", start));
                out.push((det, ms));
            }
            out
        };
        let ((runs, reporters_ms), detections) = tokio::join!(reporters, detections);
        let mut detected = Vec::with_capacity(uploads.len());
        for (d, (det, ms)) in decoded.iter_mut().zip(detections) {
            if let Some(ms) = ms {
                d.timings.push(("detect".into(), ms));
            }
            detected.push(det);
        }
        let mut processed = Vec::with_capacity(uploads.len());
        for ((((up, d), runs), derived), detected) in uploads
            .iter()
            .zip(decoded)
            .zip(runs)
            .zip(derived)
            .zip(detected)
        {
            let mut p = self.label_and_record(up, d, runs, reporters_ms).await?;
            if let Some(a) = &derived {
                p.request["signals"] = serde_json::to_value(a).unwrap_or_default();
            }
            match &detected {
                Some(Ok(a)) => {
                    p.request["detections"] = serde_json::to_value(a).unwrap_or_default()
                }
                Some(Err(e)) => p.request["detections"] = json!({ "error": e }),
                None => {}
            }
            p.derived = derived;
            p.detected = detected;
            processed.push(p);
        }
        // What the vehicle's signals and the detector say, as partial feedback once the rounds
        // are stored. The detector leaves out the labels the signals decided (two derived
        // sources that disagree are refused whole).
        let (feedback, detector_feedback): (Vec<Truth>, Vec<Truth>) = {
            let eng = self.shared.engine.read().await;
            processed
                .iter()
                .map(|p| {
                    let kin = p
                        .derived
                        .as_ref()
                        .and_then(|a| super::annotate::truth_of(eng.ontology(), a));
                    let det = match (&p.detected, self.cfg.detect.feedback) {
                        (Some(Ok(a)), true) => super::detect::truth_of(
                            eng.ontology(),
                            a,
                            kin.as_deref().filter(|_| self.cfg.annotate.feedback),
                        ),
                        _ => None,
                    };
                    (kin.filter(|_| self.cfg.annotate.feedback), det)
                })
                .unzip()
        };
        let records = processed
            .iter_mut()
            .map(|p| {
                (
                    p.record.clone(),
                    std::mem::take(&mut p.request),
                    std::mem::take(&mut p.thumbnails),
                )
            })
            .collect();
        let fuse_start = Instant::now();
        let render: Render = Box::new(move |fused| {
            let fuse_ms = fuse_start.elapsed().as_secs_f64() * 1e3;
            let mut clips: Vec<InferClipOut> = fused
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
                        derived: p.derived,
                        detect_error: p.detected.as_ref().and_then(|r| r.as_ref().err().cloned()),
                        detected: p.detected.and_then(Result::ok),
                        timings_ms: Ordered(timings),
                    }
                })
                .collect();
            if batch {
                serde_json::to_value(crate::wire::InferBatchOut { clips })
            } else {
                serde_json::to_value(clips.remove(0))
            }
            .unwrap_or_else(|e| json!({"error": format!("serialising: {e}")}))
        });
        let mut answer = self
            .fuse_and_store(records, batch, "/v1/infer", idem, render)
            .await?;
        stage("fuse", fuse_start);
        drop(uploads);
        if !answer.replayed && feedback.iter().any(Option::is_some) {
            self.derived_feedback(
                &mut answer.body,
                batch,
                feedback,
                super::annotate::KINEMATICS,
                "kinematics_feedback",
            )
            .await;
        }
        if !answer.replayed && detector_feedback.iter().any(Option::is_some) {
            self.derived_feedback(
                &mut answer.body,
                batch,
                detector_feedback,
                super::detect::DETECTOR,
                "detector_feedback",
            )
            .await;
        }
        Ok(answer)
    }

    /// `[annotate] feedback = true` / `[detect] feedback = true`: each stored clip's derived
    /// labels go in as partial feedback (source `kinematics` or `detector`), and its answer
    /// gains `field` (`kinematics_feedback`, `detector_feedback`: the feedback's answer, or why
    /// it failed: the round is stored either way, and the feedback can be sent again on
    /// `/v1/feedback`).
    async fn derived_feedback(
        &self,
        body: &mut Value,
        batch: bool,
        truths: Vec<Option<Vec<u8>>>,
        source: &str,
        field: &str,
    ) {
        for (i, truth) in truths.into_iter().enumerate() {
            let Some(truth) = truth else { continue };
            let clip = if batch {
                &mut body["clips"][i]
            } else {
                &mut *body
            };
            let Some(round_id) = clip["round_id"].as_str().map(str::to_string) else {
                continue;
            };
            let res = self.feedback_truth(round_id, truth, source.into()).await;
            clip[field] = match res {
                Ok((out, _)) => serde_json::to_value(out).unwrap_or_default(),
                Err(e) => {
                    tracing::warn!(error = %e, source, "derived feedback failed");
                    json!({"error": e.to_string()})
                }
            };
        }
    }

    /// The frames of the reporters that pick their own (an in-process checkpoint's sampler,
    /// [`vlmfuse_models::Reporter::frame_times`]), decoded under the clip's limits and the
    /// request's deadline; reporters asking for the same times share one decode.
    async fn own_frames(
        &self,
        path: &std::path::Path,
        info: &vlmfuse_media::ClipInfo,
        limits: &vlmfuse_media::MediaLimits,
        stop: &vlmfuse_media::Interrupt,
    ) -> Result<std::collections::BTreeMap<String, Arc<[vlmfuse_models::Frame]>>, ServiceError>
    {
        let mut out = std::collections::BTreeMap::new();
        let mut done: Vec<(
            Vec<f64>,
            vlmfuse_media::FrameSize,
            Arc<[vlmfuse_models::Frame]>,
        )> = Vec::new();
        for rr in &self.pipeline.reporters {
            let r = &rr.reporter;
            let Some(times) = r.frame_times(info.duration_s, info.fps) else {
                continue;
            };
            let size = match r.frame_size() {
                Some((width, height)) => vlmfuse_media::FrameSize::Exact { width, height },
                None => vlmfuse_media::FrameSize::Native,
            };
            if let Some((_, _, f)) = done.iter().find(|(t, z, _)| *t == times && *z == size) {
                out.insert(r.name().to_string(), f.clone());
                continue;
            }
            let (p, l, s, t) = (
                path.to_path_buf(),
                limits.clone(),
                stop.clone(),
                times.clone(),
            );
            let decoded = tokio::task::spawn_blocking(move || {
                vlmfuse_media::sample_frames_at(&p, &t, size, &l, &s)
            })
            .await
            .map_err(|e| ServiceError::Internal(format!("decoding task failed: {e}")))??;
            let frames: Arc<[vlmfuse_models::Frame]> =
                decoded.frames.into_iter().map(|f| f.frame).collect();
            tracing::debug!(reporter = %r.name(), frames = frames.len(), "own frames decoded");
            done.push((times, size, frames.clone()));
            out.insert(r.name().to_string(), frames);
        }
        Ok(out)
    }

    /// Decode and embed one clip.
    async fn decode_and_embed(&self, up: &Upload) -> Result<Decoded, ServiceError> {
        let p = &self.pipeline;
        let media = &self.cfg.media;
        let mut timings = vec![("upload".to_string(), up.upload_ms)];

        let start = Instant::now();
        let path = up.file.path().to_path_buf();
        let (opts, limits) = (media.sample_options(), media.limits());
        let decode_path = path.clone();
        // The decode stops at the request's deadline, and as soon as this future is dropped
        // (client gone, request timeout): the guard cancels it, so no thread keeps decoding for
        // an abandoned request.
        let interrupt = match Duration::try_from_secs_f64(media.request_timeout_s) {
            Ok(timeout) => vlmfuse_media::Interrupt::with_timeout(timeout),
            Err(_) => vlmfuse_media::Interrupt::new(),
        };
        let _stop_on_drop = interrupt.cancel_on_drop();
        let (stop, own_limits) = (interrupt.clone(), limits.clone());
        let decoded = tokio::task::spawn_blocking(move || {
            vlmfuse_media::sample_frames_with_interrupt(&decode_path, &opts, &limits, &interrupt)
        })
        .await
        .map_err(|e| ServiceError::Internal(format!("decoding task failed: {e}")))??;
        let info = decoded.info.clone();
        let own_frames = self.own_frames(&path, &info, &own_limits, &stop).await?;
        timings.push(("decode".into(), stage("decode", start)));
        let clip = ClipOut {
            file_name: up.file_name.clone(),
            bytes: up.bytes,
            info: info.clone(),
            timestamps_s: decoded.timestamps(),
        };
        let frames: Arc<[vlmfuse_models::Frame]> =
            decoded.frames.into_iter().map(|f| f.frame).collect();

        let start = Instant::now();
        let embedder = p.embedder.clone().expect("checked before");
        let context = embedder
            .embed(frames.clone())
            .await
            .map_err(ServiceError::Embedder)?;
        timings.push(("embed".into(), stage("embed", start)));
        let (count, width) = (self.cfg.ui.thumbnails, self.cfg.ui.thumbnail_width);
        let thumbnails = if count == 0 {
            Vec::new()
        } else {
            let frames = frames.clone();
            tokio::task::spawn_blocking(move || super::thumbs::make(&frames, count, width))
                .await
                .unwrap_or_default()
        };

        let input = ClipInput {
            path,
            frames,
            meta: ClipMeta {
                clip_id: up.file_name.clone(),
                duration_s: Some(info.duration_s),
                fps: Some(info.fps),
                width: Some(info.width),
                height: Some(info.height),
                own_frames,
            },
        };
        Ok(Decoded {
            input,
            context,
            clip,
            timings,
            thumbnails,
        })
    }

    /// Label one clip's answers (`runs`, from the request's reporter batch) and build its round.
    async fn label_and_record(
        &self,
        up: &Upload,
        d: Decoded,
        runs: Vec<(
            String,
            Result<vlmfuse_models::ReporterOutput, vlmfuse_models::ReporterFailure>,
        )>,
        reporters_ms: f64,
    ) -> Result<Processed, ServiceError> {
        let p = &self.pipeline;
        let Decoded {
            context,
            clip,
            mut timings,
            thumbnails,
            ..
        } = d;
        timings.push(("reporters".into(), reporters_ms));
        let start = Instant::now();
        let labeler = p.labeler.clone().expect("checked before");
        let mut failed = p.unloaded_reporters.clone();
        let mut answered = Vec::new();
        for (name, res) in runs {
            self.shared
                .record_reporter(&name, res.as_ref().map(|o| o.latency_ms).map_err(|_| ()));
            match res {
                Ok(out) => answered.push((name, out)),
                Err(e) => {
                    metrics::counter!("vlmfuse_reporter_failures_total", "reporter" => name.clone(), "stage" => "run")
                        .increment(1);
                    failed.push((name, format!("{}: {e}", e.kind())));
                }
            }
        }
        let labelled = label_round(labeler.as_ref(), answered).await;
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
            return Err(ServiceError::ReportersFailed(failed));
        }
        // Keep the configured order in `failed` whatever finished first.
        let order = |n: &str| self.cfg.reporters.iter().position(|r| r == n);
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
            derived: None,
            detected: None,
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
            thumbnails,
        })
    }
}
