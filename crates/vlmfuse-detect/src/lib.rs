//! Detections: the paper's second annotation component. An object detector (a YOLO-family
//! ONNX export run on ONNX Runtime), a tracker across a clip's sampled frames, and rules that
//! turn persistent tracks into driving labels (`traffic_light_ahead`,
//! `pedestrian_crossing_ahead`, `stop`) with their evidence.
//!
//! Why it matters: like the vehicle's signals (`vlmfuse-annotate`), a detector's errors are not
//! the vision-language models' errors, so its labels are cheap partial feedback
//! (`source = "detector"`) that the fusion can learn reliabilities from.
//!
//! Layout (everything but [`onnx`] is pure computation, testable without ONNX Runtime):
//! - [`letterbox`]: ultralytics' `LetterBox` and OpenCV's bilinear resize, bit-exact.
//! - [`decode`]: the `[1, 4 + nc, anchors]` output, confidence filter, class-aware NMS with
//!   torchvision's semantics, `scale_boxes`.
//! - [`names`]: class names from the export's metadata (a Python dict literal).
//! - [`track`]: BoT-SORT (no ReID, no GMC) and ByteTrack as ultralytics implements them.
//! - [`rules`]: persistent tracks to labels, with evidence.
//! - [`onnx`]: the [`Detector`] (session, metadata, one frame per run).
//!
//! Parity with ultralytics 8.4.190 is tested against `tests/data/parity/detect/`, written by
//! `scripts/parity/yolo_detect.py`.

pub mod decode;
pub mod letterbox;
pub mod names;
pub mod onnx;
pub mod rules;
pub mod track;

pub use decode::{Detection, NmsConfig};
pub use onnx::{Detector, DetectorConfig};
pub use rules::{derive, DetectAnnotation, FrameDetections, LabelRule, RulesConfig};
pub use track::{Tracker, TrackerConfig, TrackerKind};

/// Why detection failed. One type for the crate; the service maps it into its own.
#[derive(Debug, thiserror::Error)]
pub enum DetectError {
    /// ONNX Runtime missing, the model not loadable or not a YOLO export, a run failing.
    #[error(transparent)]
    Ort(#[from] vlmfuse_ort::OrtError),
    /// A frame buffer that does not match its size.
    #[error("frame: {0}")]
    Frame(#[from] vlmfuse_core::FrameError),
    /// A raw output that does not fit the model's layout.
    #[error("output: {0}")]
    Decode(#[from] decode::DecodeError),
    /// Settings that cannot work.
    #[error("detect config: {0}")]
    Config(String),
}

impl DetectError {
    /// A short stable tag for logs and metrics.
    pub fn kind(&self) -> &'static str {
        match self {
            DetectError::Ort(e) => e.kind(),
            DetectError::Frame(_) => "bad_frame",
            DetectError::Decode(_) => "bad_output",
            DetectError::Config(_) => "bad_config",
        }
    }
}
