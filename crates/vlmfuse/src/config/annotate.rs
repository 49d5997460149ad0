//! `[annotate]`: ground truth from the vehicle's own signals (a `signals` track with a clip on
//! `/v1/infer`, or with a round on `/v1/feedback`), and `[annotate.rules]`, the thresholds of
//! the kinematic rules (vlmfuse-annotate documents each).

use serde::{Deserialize, Serialize};
use vlmfuse_annotate::AnnotateConfig;

#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AnnotateSection {
    /// Send a clip's derived labels as partial feedback (`source = "kinematics"`) once
    /// `/v1/infer` has stored its round: the vehicle labels its own clips.
    #[arg(
        long = "annotate-feedback",
        id = "annotate-feedback",
        env = "VLMFUSE_ANNOTATE_FEEDBACK",
        action = clap::ArgAction::Set,
        required = false
    )]
    pub feedback: bool,
    /// Largest signal track in bytes (413 above): a track is read whole into memory.
    #[arg(
        long = "annotate-max-bytes",
        id = "annotate-max-bytes",
        env = "VLMFUSE_ANNOTATE_MAX_BYTES",
        required = false
    )]
    pub max_bytes: u64,
    /// Most samples in one track (422 above): bounds the rules' work.
    #[arg(
        long = "annotate-max-samples",
        id = "annotate-max-samples",
        env = "VLMFUSE_ANNOTATE_MAX_SAMPLES",
        required = false
    )]
    pub max_samples: usize,
    /// Seconds a track may fall short of either end of its clip and still cover it.
    #[arg(
        long = "annotate-cover-tolerance-s",
        id = "annotate-cover-tolerance-s",
        env = "VLMFUSE_ANNOTATE_COVER_TOLERANCE_S",
        required = false
    )]
    pub cover_tolerance_s: f64,
    /// The rules' thresholds (file only).
    #[arg(skip)]
    pub rules: AnnotateConfig,
}

impl Default for AnnotateSection {
    fn default() -> Self {
        Self {
            feedback: false,
            max_bytes: 4 << 20,
            max_samples: 100_000,
            cover_tolerance_s: 0.5,
            rules: AnnotateConfig::default(),
        }
    }
}

impl AnnotateSection {
    pub fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            self.max_bytes > 0 && self.max_samples >= 2,
            "annotate.max_bytes must be at least 1 and annotate.max_samples at least 2"
        );
        anyhow::ensure!(
            self.cover_tolerance_s.is_finite() && self.cover_tolerance_s >= 0.0,
            "annotate.cover_tolerance_s must be a number of seconds >= 0, got {}",
            self.cover_tolerance_s
        );
        self.rules
            .validate()
            .map_err(|e| anyhow::anyhow!("annotate.rules: {e}"))
    }

    pub fn limits(&self) -> vlmfuse_annotate::TrackLimits {
        vlmfuse_annotate::TrackLimits {
            max_samples: self.max_samples,
        }
    }
}
