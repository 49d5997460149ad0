//! `[ui]`: the operator page at `/ui` (docs/UI.md). Every window here bounds memory and the work
//! of one page load: the aggregates are kept up to date by the writer as rounds and feedback
//! commit, so a page never scans the store, whatever its size.

use serde::{Deserialize, Serialize};

#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct UiSection {
    /// Serve the operator page (`/ui` and its `/ui/api/*` reads). Off: those routes answer 404.
    #[arg(
        long = "ui-enabled",
        id = "ui-enabled",
        env = "VLMFUSE_UI_ENABLED",
        action = clap::ArgAction::Set,
        required = false
    )]
    pub enabled: bool,
    /// How often the page asks for new numbers, in milliseconds.
    #[arg(
        long = "ui-poll-ms",
        id = "ui-poll-ms",
        env = "VLMFUSE_UI_POLL_MS",
        required = false
    )]
    pub poll_ms: u64,
    /// Most points of the reputation chart: the history is thinned evenly past it, so a
    /// million labelled rounds draw as fast as a hundred.
    #[arg(
        long = "ui-history-points",
        id = "ui-history-points",
        env = "VLMFUSE_UI_HISTORY_POINTS",
        required = false
    )]
    pub history_points: usize,
    /// Labelled rounds in each of the two windows a drift alarm compares: a reporter's mean
    /// credit share (its Shapley credit over the round's total |credit|) over the latest
    /// `drift_window` rounds it was in, against the `drift_window` before.
    #[arg(
        long = "ui-drift-window",
        id = "ui-drift-window",
        env = "VLMFUSE_UI_DRIFT_WINDOW",
        required = false
    )]
    pub drift_window: usize,
    /// Fall in mean credit share between the two windows that raises a drift alarm (0.1: ten
    /// points of the rounds' credit).
    #[arg(
        long = "ui-drift-threshold",
        id = "ui-drift-threshold",
        env = "VLMFUSE_UI_DRIFT_THRESHOLD",
        required = false
    )]
    pub drift_threshold: f64,
    /// Latest labelled rounds the "overall" reliability heat map counts.
    #[arg(
        long = "ui-reliability-window",
        id = "ui-reliability-window",
        env = "VLMFUSE_UI_RELIABILITY_WINDOW",
        required = false
    )]
    pub reliability_window: usize,
    /// Latest rounds (labelled or not) whose scenes the "latest scenes" heat map averages the
    /// engine's contextual reliabilities over; also the window of the serving decisions.
    #[arg(
        long = "ui-recent-rounds",
        id = "ui-recent-rounds",
        env = "VLMFUSE_UI_RECENT_ROUNDS",
        required = false
    )]
    pub recent_rounds: usize,
    /// Latest labelled rounds the reliability diagram and ECE are computed over.
    #[arg(
        long = "ui-calibration-window",
        id = "ui-calibration-window",
        env = "VLMFUSE_UI_CALIBRATION_WINDOW",
        required = false
    )]
    pub calibration_window: usize,
    /// Frame thumbnails kept with each round `/v1/infer` stores (0: none), for the round page.
    #[arg(
        long = "ui-thumbnails",
        id = "ui-thumbnails",
        env = "VLMFUSE_UI_THUMBNAILS",
        required = false
    )]
    pub thumbnails: usize,
    /// Width of a thumbnail in pixels (JPEG; the height follows the frame's aspect).
    #[arg(
        long = "ui-thumbnail-width",
        id = "ui-thumbnail-width",
        env = "VLMFUSE_UI_THUMBNAIL_WIDTH",
        required = false
    )]
    pub thumbnail_width: u32,
    /// Lifetime of the login cookie in seconds.
    #[arg(
        long = "ui-session-s",
        id = "ui-session-s",
        env = "VLMFUSE_UI_SESSION_S",
        required = false
    )]
    pub session_s: u64,
}

impl Default for UiSection {
    fn default() -> Self {
        Self {
            enabled: true,
            poll_ms: 2000,
            history_points: 500,
            drift_window: 20,
            drift_threshold: 0.1,
            reliability_window: 10_000,
            recent_rounds: 100,
            calibration_window: 500,
            thumbnails: 4,
            thumbnail_width: 192,
            session_s: 8 * 3600,
        }
    }
}

impl UiSection {
    pub fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            (250..=3_600_000).contains(&self.poll_ms),
            "ui.poll_ms must be between 250 and 3600000, got {}",
            self.poll_ms
        );
        anyhow::ensure!(
            (2..=100_000).contains(&self.history_points),
            "ui.history_points must be between 2 and 100000, got {}",
            self.history_points
        );
        for (name, v) in [
            ("drift_window", self.drift_window),
            ("reliability_window", self.reliability_window),
            ("recent_rounds", self.recent_rounds),
            ("calibration_window", self.calibration_window),
        ] {
            anyhow::ensure!(
                (1..=1_000_000).contains(&v),
                "ui.{name} must be between 1 and 1000000, got {v}"
            );
        }
        anyhow::ensure!(
            self.drift_threshold.is_finite() && self.drift_threshold > 0.0,
            "ui.drift_threshold must be a number > 0, got {}",
            self.drift_threshold
        );
        anyhow::ensure!(
            self.thumbnails <= 16,
            "ui.thumbnails must be at most 16, got {}",
            self.thumbnails
        );
        anyhow::ensure!(
            (16..=640).contains(&self.thumbnail_width),
            "ui.thumbnail_width must be between 16 and 640 pixels, got {}",
            self.thumbnail_width
        );
        anyhow::ensure!(
            (60..=30 * 86_400).contains(&self.session_s),
            "ui.session_s must be between 60 and 2592000 seconds, got {}",
            self.session_s
        );
        Ok(())
    }
}
