//! `[detect]`: labels from an object detector (docs/DETECT.md). Off until `model` names a YOLO
//! ONNX export; then `/v1/infer` runs it on each clip's frames, tracks the objects and derives
//! `traffic_light_ahead`, `pedestrian_crossing_ahead` and `stop` with their evidence.
//! `[detect.tracker]` and `[detect.rules]` are file only (vlmfuse-detect documents each field).

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use vlmfuse_detect::{NmsConfig, RulesConfig, TrackerConfig, TrackerKind};

/// Most frames the detector samples of its own from one clip.
pub const MAX_FRAMES: usize = 128;

#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DetectSection {
    /// The detector: an ultralytics YOLO export to ONNX (`[1, 4 + classes, anchors]` output,
    /// class names in its metadata). Unset: no detector.
    #[arg(
        long = "detect-model",
        id = "detect-model",
        env = "VLMFUSE_DETECT_MODEL",
        required = false
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model: Option<PathBuf>,
    /// A detection needs a score above this.
    #[arg(
        long = "detect-conf",
        id = "detect-conf",
        env = "VLMFUSE_DETECT_CONF",
        required = false
    )]
    pub conf: f32,
    /// NMS: a box whose IoU with a better one of its class is above this is dropped.
    #[arg(
        long = "detect-iou",
        id = "detect-iou",
        env = "VLMFUSE_DETECT_IOU",
        required = false
    )]
    pub iou: f64,
    /// Most detections kept per frame.
    #[arg(
        long = "detect-max-det",
        id = "detect-max-det",
        env = "VLMFUSE_DETECT_MAX_DET",
        required = false
    )]
    pub max_det: usize,
    /// Frames the detector samples from each clip: 0 uses the request's sampled frames
    /// (`media.frames`); more (at most 128) decode the clip again at that many frames, because
    /// tracking needs frames close enough in time that an object's boxes overlap.
    #[arg(
        long = "detect-frames",
        id = "detect-frames",
        env = "VLMFUSE_DETECT_FRAMES",
        required = false
    )]
    pub frames: usize,
    /// Send a clip's derived labels as partial feedback (`source = "detector"`) once
    /// `/v1/infer` has stored its round.
    #[arg(
        long = "detect-feedback",
        id = "detect-feedback",
        env = "VLMFUSE_DETECT_FEEDBACK",
        action = clap::ArgAction::Set,
        required = false
    )]
    pub feedback: bool,
    /// Intra-op threads of the detector's session (unset: one per core).
    #[arg(
        long = "detect-threads",
        id = "detect-threads",
        env = "VLMFUSE_DETECT_THREADS",
        required = false
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub threads: Option<usize>,
    /// `libonnxruntime.so` to load (unset: `ORT_DYLIB_PATH`, else the asset cache).
    #[arg(
        long = "detect-onnx-library",
        id = "detect-onnx-library",
        env = "VLMFUSE_DETECT_ONNX_LIBRARY",
        required = false
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub onnx_library: Option<PathBuf>,
    /// The tracker (`botsort` or `bytetrack`); its thresholds are `[detect.tracker]`.
    #[arg(long = "detect-tracker", id = "detect-tracker", env = "VLMFUSE_DETECT_TRACKER", value_parser = tracker_kind, required = false)]
    #[serde(skip)]
    pub tracker_kind: Option<TrackerKind>,
    #[arg(skip)]
    pub tracker: TrackerConfig,
    #[arg(skip)]
    pub rules: RulesConfig,
}

fn tracker_kind(s: &str) -> Result<TrackerKind, String> {
    match s {
        "botsort" => Ok(TrackerKind::Botsort),
        "bytetrack" => Ok(TrackerKind::Bytetrack),
        other => Err(format!("tracker {other:?} is not botsort or bytetrack")),
    }
}

impl Default for DetectSection {
    fn default() -> Self {
        let nms = NmsConfig::default();
        Self {
            model: None,
            conf: nms.conf,
            iou: nms.iou,
            max_det: nms.max_det,
            frames: 0,
            feedback: false,
            threads: None,
            onnx_library: None,
            tracker_kind: None,
            tracker: TrackerConfig::default(),
            rules: RulesConfig::default(),
        }
    }
}

impl DetectSection {
    pub fn validate(&self) -> anyhow::Result<()> {
        self.nms()
            .validate()
            .map_err(|e| anyhow::anyhow!("detect: {e}"))?;
        self.tracker_config()
            .validate()
            .map_err(|e| anyhow::anyhow!("detect.tracker: {e}"))?;
        self.rules
            .validate()
            .map_err(|e| anyhow::anyhow!("detect.rules: {e}"))?;
        // A clip's sample is held in memory at once (at the model's input size on its short
        // side: 640 px frames of a 16:9 clip are 2.2 MB each).
        anyhow::ensure!(
            self.frames <= MAX_FRAMES,
            "detect.frames must be 0..={MAX_FRAMES}, got {}",
            self.frames
        );
        anyhow::ensure!(self.threads != Some(0), "detect.threads must be at least 1");
        Ok(())
    }

    pub fn nms(&self) -> NmsConfig {
        NmsConfig {
            conf: self.conf,
            iou: self.iou,
            max_det: self.max_det,
            agnostic: false,
        }
    }

    /// `[detect.tracker]` with the `--detect-tracker` kind applied.
    pub fn tracker_config(&self) -> TrackerConfig {
        let mut t = self.tracker.clone();
        if let Some(k) = self.tracker_kind {
            t.kind = k;
        }
        t
    }

    pub fn detector_config(&self) -> Option<vlmfuse_detect::DetectorConfig> {
        Some(vlmfuse_detect::DetectorConfig {
            model: self.model.clone()?,
            nms: self.nms(),
            session: vlmfuse_ort::SessionOptions {
                threads: self.threads,
                library: self.onnx_library.clone(),
            },
        })
    }
}
