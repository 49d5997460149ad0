//! Reporters: the VLMs whose free-text reports the fusion engine combines. A round runs them all
//! on one clip; a slow or broken reporter must cost at most its timeout and never sink the round.

pub mod candle_vlm;
mod openai;

pub use candle_vlm::{CandleVlmConfig, CandleVlmReporter, Generation, Trace};
pub use openai::{FrameFormat, OpenAiMode, OpenAiReporter, OpenAiReporterConfig};

use std::panic::AssertUnwindSafe;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures::future::BoxFuture;
use futures::FutureExt;
use serde::{Deserialize, Serialize};
use vlmfuse_core::backend::panic_message;
use vlmfuse_core::{BackendError, BackendPool};

use crate::{Frame, ModelError};

/// The paper's three-step chain-of-thought prompt. Steps are labelled so the labeler can find
/// the manoeuvre recommendation without a second model call when the VLM follows the format.
pub const DEFAULT_PROMPT: &str = "\
You are given a dashcam clip recorded from the ego vehicle. Think step by step and answer in three steps.
Step 1 - Scene: describe the driving scene: road type and layout, the traffic participants \
(vehicles, pedestrians, cyclists) and what they are doing, traffic lights and signs, weather, \
lighting, road surface, and any hazard.
Step 2 - Manoeuvres: recommend the manoeuvre(s) the ego vehicle should perform next \
(for example keep lane, accelerate, slow down, stop, yield, change lane left or right, \
turn left or right, overtake, pull over).
Step 3 - Rationale: explain why these manoeuvres are appropriate, referring to the elements of \
the scene from Step 1.
Answer with the headings \"Scene:\", \"Manoeuvres:\" and \"Rationale:\".";

/// What the media layer knows about a clip; sent to no model by default, but kept with the
/// input so reporters can adapt (e.g. tell a server the sampling fps).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ClipMeta {
    pub clip_id: Option<String>,
    pub duration_s: Option<f64>,
    pub fps: Option<f64>,
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// Frames decoded for the reporters that pick their own ([`Reporter::frame_times`]), by
    /// reporter name, in presentation order. A reporter absent here takes `frames`.
    #[serde(skip)]
    pub own_frames: std::collections::BTreeMap<String, Arc<[Frame]>>,
}

/// One clip as every reporter sees it. Frames are behind an `Arc` so reporters can move them to
/// blocking threads (encoding, forward passes) without copying.
#[derive(Debug, Clone)]
pub struct ClipInput {
    /// The clip file on local disk (for reporters that send the whole video).
    pub path: PathBuf,
    /// Frames sampled by the media layer, in presentation order.
    pub frames: Arc<[Frame]>,
    pub meta: ClipMeta,
}

impl ClipInput {
    /// The frames reporter `name` takes: its own ([`ClipMeta::own_frames`]) or the media
    /// layer's.
    pub fn frames_for(&self, name: &str) -> &[Frame] {
        self.meta.own_frames.get(name).unwrap_or(&self.frames)
    }
}

/// A reporter's answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReporterOutput {
    pub text: String,
    /// Wall time of the whole `run`, retries included: what the round actually waited.
    pub latency_ms: f64,
    /// The model that answered, as the backend names it (a server may resolve an alias).
    pub model: String,
}

/// A VLM that describes a clip. Returns a boxed future so reporters of different kinds can sit
/// together in one `Vec<Arc<dyn Reporter>>`.
///
/// Implementations must not block the executor: `run_all` polls every reporter on one task, so a
/// blocking forward pass inside the future would stall the others. In-process models implement
/// [`LocalReporter`] and get this trait from [`BackendPool`].
pub trait Reporter: Send + Sync {
    fn name(&self) -> &str;
    fn run<'a>(&'a self, clip: &'a ClipInput) -> BoxFuture<'a, Result<ReporterOutput, ModelError>>;

    /// The presentation times of the frames this reporter's own sampler takes from a clip of
    /// `duration_s` at `fps` (an in-process checkpoint whose processor picks frames, as its
    /// reference does); the caller decodes them into [`ClipMeta::own_frames`]. `None` (the
    /// default): the media layer's frames.
    fn frame_times(&self, _duration_s: f64, _fps: f64) -> Option<Vec<f64>> {
        None
    }

    /// The `(width, height)` those frames are decoded at (the checkpoint's decoder scales
    /// while decoding); `None`: the source size.
    fn frame_size(&self) -> Option<(u32, u32)> {
        None
    }

    /// Several clips of one request, one outcome per clip in order. The default runs them
    /// concurrently (a remote server batches on its side); an in-process model runs them as
    /// one batch.
    fn run_batch<'a>(
        &'a self,
        clips: &'a [ClipInput],
    ) -> BoxFuture<'a, Vec<Result<ReporterOutput, ModelError>>> {
        Box::pin(futures::future::join_all(clips.iter().map(|c| self.run(c))))
    }
}

/// An in-process VLM: generation blocks the calling thread for seconds. `cancel` is set when the
/// round no longer waits (its timeout passed); a generation should stop at its next token.
///
/// Wrapped in a [`BackendPool`] it is a [`Reporter`]: queued clips wait in the pool's bounded
/// queue (not on threads), one generation runs at a time per worker, and a timed-out round
/// cancels its generation.
pub trait LocalReporter: Send + Sync + 'static {
    fn name(&self) -> &str;
    /// [`Reporter::frame_times`].
    fn frame_times(&self, _duration_s: f64, _fps: f64) -> Option<Vec<f64>> {
        None
    }
    /// [`Reporter::frame_size`].
    fn frame_size(&self) -> Option<(u32, u32)> {
        None
    }
    fn generate(&self, clip: &ClipInput, cancel: &AtomicBool)
        -> Result<ReporterOutput, ModelError>;

    /// Several clips at once, one outcome per clip in order. Default: one after another. Models
    /// that batch (padding plus an attention mask) override it to run one forward pass per step
    /// for all clips.
    fn generate_batch(
        &self,
        clips: &[ClipInput],
        cancel: &AtomicBool,
    ) -> Vec<Result<ReporterOutput, ModelError>> {
        clips.iter().map(|c| self.generate(c, cancel)).collect()
    }
}

impl<B: LocalReporter + ?Sized> Reporter for BackendPool<B> {
    fn name(&self) -> &str {
        self.backend().name()
    }

    fn frame_times(&self, duration_s: f64, fps: f64) -> Option<Vec<f64>> {
        self.backend().frame_times(duration_s, fps)
    }

    fn frame_size(&self) -> Option<(u32, u32)> {
        self.backend().frame_size()
    }

    fn run<'a>(&'a self, clip: &'a ClipInput) -> BoxFuture<'a, Result<ReporterOutput, ModelError>> {
        Box::pin(async move {
            let t0 = Instant::now();
            let clip = clip.clone();
            match self.call(move |b, cancel| b.generate(&clip, cancel)).await {
                Ok(out) => out.map(|o| ReporterOutput {
                    // What the round waited, queue included.
                    latency_ms: t0.elapsed().as_secs_f64() * 1e3,
                    ..o
                }),
                // Re-raised so that `run_all` reports it as the panic it was.
                Err(BackendError::Panicked { message, .. }) => {
                    std::panic::resume_unwind(Box::new(message))
                }
                Err(e) => Err(e.into()),
            }
        })
    }

    fn run_batch<'a>(
        &'a self,
        clips: &'a [ClipInput],
    ) -> BoxFuture<'a, Vec<Result<ReporterOutput, ModelError>>> {
        Box::pin(async move {
            let t0 = Instant::now();
            let owned: Vec<ClipInput> = clips.to_vec();
            let n = owned.len();
            match self
                .call(move |b, cancel| b.generate_batch(&owned, cancel))
                .await
            {
                Ok(outs) if outs.len() == n => outs
                    .into_iter()
                    .map(|o| {
                        o.map(|o| ReporterOutput {
                            latency_ms: t0.elapsed().as_secs_f64() * 1e3,
                            ..o
                        })
                    })
                    .collect(),
                Ok(outs) => (0..n)
                    .map(|_| {
                        Err(ModelError::InvalidInput(format!(
                            "the batch returned {} outcomes for {n} clips",
                            outs.len()
                        )))
                    })
                    .collect(),
                Err(BackendError::Panicked { message, .. }) => {
                    std::panic::resume_unwind(Box::new(message))
                }
                Err(e) => (0..n).map(|_| Err(e.clone().into())).collect(),
            }
        })
    }
}

/// A reporter with the time a round gives it (retries included) before it is left out.
#[derive(Clone)]
pub struct RoundReporter {
    pub reporter: Arc<dyn Reporter>,
    pub timeout: Duration,
}

impl RoundReporter {
    pub fn new(reporter: Arc<dyn Reporter>, timeout: Duration) -> Self {
        Self { reporter, timeout }
    }
}

/// Why a reporter produced no output in a round.
#[derive(Debug, thiserror::Error)]
pub enum ReporterFailure {
    #[error("timed out after {:.3}s", .0.as_secs_f64())]
    TimedOut(Duration),
    #[error(transparent)]
    Failed(#[from] ModelError),
    #[error("reporter panicked: {0}")]
    Panicked(String),
}

impl ReporterFailure {
    /// Short tag for metrics and API bodies.
    pub fn kind(&self) -> &'static str {
        match self {
            ReporterFailure::TimedOut(_) => "timeout",
            ReporterFailure::Failed(e) => e.kind(),
            ReporterFailure::Panicked(_) => "panic",
        }
    }
}

/// Runs all reporters concurrently on `clip`, each under its own timeout. Never fails as a
/// whole: each entry is `(reporter name, outcome)`, in the order of `reporters`. A timed-out
/// reporter's future is dropped, which cancels its in-flight HTTP request or its queued or
/// running local generation.
pub async fn run_all(
    reporters: &[RoundReporter],
    clip: &ClipInput,
) -> Vec<(String, Result<ReporterOutput, ReporterFailure>)> {
    let futs = reporters.iter().map(|rr| async move {
        let (r, timeout) = (&rr.reporter, rr.timeout);
        let name = r.name().to_string();
        let fut = AssertUnwindSafe(r.run(clip)).catch_unwind();
        let res = match tokio::time::timeout(timeout, fut).await {
            Err(_) => Err(ReporterFailure::TimedOut(timeout)),
            Ok(Err(panic)) => Err(ReporterFailure::Panicked(panic_message(panic.as_ref()))),
            Ok(Ok(Err(e))) => Err(ReporterFailure::Failed(e)),
            Ok(Ok(Ok(o))) => Ok(o),
        };
        if let Err(e) = &res {
            tracing::warn!(reporter = %name, kind = e.kind(), error = %e, "reporter failed");
        }
        (name, res)
    });
    futures::future::join_all(futs).await
}

/// [`run_all`] for the clips of one request: each reporter gets all of them in one
/// [`Reporter::run_batch`] call (one batch for an in-process model), under its timeout times
/// the number of clips (each clip is a round's work). Returns, per clip in order, what
/// [`run_all`] returns for it. One clip runs exactly as [`run_all`].
pub async fn run_all_batch(
    reporters: &[RoundReporter],
    clips: &[ClipInput],
) -> Vec<Vec<(String, Result<ReporterOutput, ReporterFailure>)>> {
    let n = clips.len();
    if n == 1 {
        return vec![run_all(reporters, &clips[0]).await];
    }
    let futs = reporters.iter().map(|rr| async move {
        let r = &rr.reporter;
        let timeout = rr.timeout.saturating_mul(n.max(1) as u32);
        let name = r.name().to_string();
        let fut = AssertUnwindSafe(r.run_batch(clips)).catch_unwind();
        let outs: Vec<Result<ReporterOutput, ReporterFailure>> =
            match tokio::time::timeout(timeout, fut).await {
                Err(_) => (0..n)
                    .map(|_| Err(ReporterFailure::TimedOut(timeout)))
                    .collect(),
                Ok(Err(panic)) => {
                    let m = panic_message(panic.as_ref());
                    (0..n)
                        .map(|_| Err(ReporterFailure::Panicked(m.clone())))
                        .collect()
                }
                Ok(Ok(v)) => v
                    .into_iter()
                    .map(|o| o.map_err(ReporterFailure::Failed))
                    .collect(),
            };
        for e in outs.iter().filter_map(|o| o.as_ref().err()) {
            tracing::warn!(reporter = %name, kind = e.kind(), error = %e, "reporter failed");
        }
        (name, outs)
    });
    let per_reporter = futures::future::join_all(futs).await;
    let mut per_clip: Vec<Vec<_>> = (0..n)
        .map(|_| Vec::with_capacity(reporters.len()))
        .collect();
    for (name, outs) in per_reporter {
        let mut outs = outs.into_iter();
        for slot in per_clip.iter_mut() {
            let o = outs.next().unwrap_or_else(|| {
                Err(ReporterFailure::Failed(ModelError::InvalidInput(
                    "the reporter returned fewer outcomes than clips".into(),
                )))
            });
            slot.push((name.clone(), o));
        }
    }
    per_clip
}
