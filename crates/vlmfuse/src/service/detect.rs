//! Labels from the object detector for the service: run it on a clip's frames (the request's
//! sample, or `[detect] frames` of its own), track, apply the rules, and turn the decisions
//! into a partial feedback's truth (source `detector`).

use std::sync::Arc;
use std::time::Duration;

use super::Service;
use vlmfuse_detect::DetectAnnotation;
use vlmfuse_fusion::{Ontology, UNKNOWN};
use vlmfuse_models::Frame;

/// The source name of detector feedback.
pub const DETECTOR: &str = "detector";

impl Service {
    /// The detector's labels for one clip, or why it could not run (the round is fused and
    /// stored either way: the detector is a second opinion, not a gate). `None` without a
    /// detector.
    pub(crate) async fn detect_clip(
        &self,
        path: &std::path::Path,
        frames: &Arc<[Frame]>,
    ) -> Option<Result<DetectAnnotation, String>> {
        let detector = self.pipeline.detector.clone()?;
        let cfg = self.cfg.detect.clone();
        let media = self.cfg.media.clone();
        let frames = frames.clone();
        let path = path.to_path_buf();
        let interrupt = match Duration::try_from_secs_f64(media.request_timeout_s) {
            Ok(t) => vlmfuse_media::Interrupt::with_timeout(t),
            Err(_) => vlmfuse_media::Interrupt::new(),
        };
        let _stop_on_drop = interrupt.cancel_on_drop();
        let res = tokio::task::spawn_blocking(move || -> Result<DetectAnnotation, String> {
            let own;
            let frames: &[Frame] = if cfg.frames == 0 {
                &frames
            } else {
                // The detector's own, denser sample, scaled so the letterbox still downsizes.
                let (h, w) = detector.input_size();
                let opts = vlmfuse_media::SampleOptions {
                    frames: cfg.frames,
                    size: vlmfuse_media::FrameSize::ShortSide(h.min(w)),
                };
                let decoded = vlmfuse_media::sample_frames_with_interrupt(
                    &path,
                    &opts,
                    &media.limits(),
                    &interrupt,
                )
                .map_err(|e| format!("decoding the detector's frames: {e}"))?;
                own = decoded
                    .frames
                    .into_iter()
                    .map(|f| f.frame)
                    .collect::<Vec<_>>();
                &own
            };
            let dets = detector
                .detect_frames(frames)
                .map_err(|e| format!("{}: {e}", e.kind()))?;
            Ok(vlmfuse_detect::derive(
                &dets,
                detector.names(),
                &cfg.tracker_config(),
                &cfg.rules,
            ))
        })
        .await
        .unwrap_or_else(|e| Err(format!("detector task failed: {e}")));
        if let Err(e) = &res {
            metrics::counter!("vlmfuse_detector_failures_total").increment(1);
            tracing::warn!(error = %e, "the detector did not run on a clip");
        }
        Some(res)
    }
}

/// The truth a detector annotation gives: 0/1 for each decided label the ontology has and
/// `skip` (the same clip's kinematic truth) leaves unknown, `UNKNOWN` elsewhere. `None` when it
/// decides nothing.
///
/// Why `skip`: two derived sources that disagree on a label are a conflict the engine refuses
/// whole (409), and the vehicle's own signals say what the car did (`stop`) more directly than
/// a stop sign in view.
pub fn truth_of(ontology: &Ontology, a: &DetectAnnotation, skip: Option<&[u8]>) -> Option<Vec<u8>> {
    let mut y = vec![UNKNOWN; ontology.len()];
    for d in &a.labels {
        if let Some(k) = ontology.lookup(&d.label) {
            if skip.is_some_and(|s| s.get(k).is_some_and(|&v| v <= 1)) {
                continue;
            }
            y[k] = d.value as u8;
        }
    }
    y.iter().any(|&v| v <= 1).then_some(y)
}
