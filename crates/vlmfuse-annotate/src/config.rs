//! The thresholds of the kinematic rules ([`crate::rules`]), one documented field each.
//!
//! Most rules have two levels: a *decision* level past which the label is positive, and a
//! *clear* level inside which it is confidently negative. Between them the rule abstains: a
//! deceleration of 1.1 m/s² is neither a clear brake nor clear coasting, and a kinematic label
//! the fusion trusts should only be emitted where the signals leave no doubt.
//!
//! The defaults come from vehicle dynamics first (a comfortable brake is 2–4 m/s², engine-drag
//! coasting under 1 m/s², a lane 3–3.75 m wide, a junction turn about 90°), then were checked
//! on simulated clips of seed 0 ([`crate::sim::evaluate`], 40 per manoeuvre) and are tested on
//! the held-out seeds 1 and 2 (tests/eval.rs).

use serde::{Deserialize, Serialize};

/// Thresholds and model constants for [`crate::annotate`]. Deserialises from a TOML/JSON table
/// where every field is optional (missing fields take the default) and unknown fields are
/// refused, so a misspelt threshold fails loudly instead of silently using the default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AnnotateConfig {
    // ---- signal conditioning ----
    /// Consecutive samples further apart than this (s) break a signal: no run, integral or
    /// window spans the gap, because nothing is known about what happened inside it.
    pub max_gap_s: f64,
    /// Share of a window's samples (0..1] a signal must have (non-missing) to be used. Below
    /// it the signal counts as absent and the labels that need it are undecided.
    pub min_coverage: f64,
    /// Full width (s) of the moving average applied to measured acceleration, speed and yaw
    /// rate before thresholds: sensor noise must not make or break a 0.5 s run.
    pub smooth_s: f64,
    /// Full width (s) of the local linear fit that estimates acceleration from speed when the
    /// track has no `accel_mps2`. Differentiating raw speed amplifies its noise (0.05 m/s at
    /// 10 Hz is 0.7 m/s² sample to sample); a 1 s fit brings it near 0.05 m/s².
    pub speed_slope_s: f64,

    // ---- brake ----
    /// Deceleration (m/s², positive number) that counts as braking when held for
    /// `brake_min_s`. Above engine-drag coasting (0.2–0.8 m/s²), below a comfortable brake.
    pub brake_decel_mps2: f64,
    /// "Clearly no brake" when no deceleration beyond this (m/s²) is held for `brake_min_s`.
    pub brake_clear_mps2: f64,
    /// How long (s) a deceleration or pedal press must be held: a bump or a noise spike is not
    /// a brake.
    pub brake_min_s: f64,
    /// Brake pedal position (0..1) that counts as pressing the brake.
    pub brake_pedal: f64,
    /// Deceleration (m/s²) that must come with the pressed pedal: holding the brake at a
    /// standstill, or resting a foot on it, is not braking.
    pub brake_pedal_decel_mps2: f64,

    // ---- accelerate ----
    /// Acceleration (m/s²) that counts as accelerating when held for `accel_min_s`.
    pub accel_mps2: f64,
    /// "Clearly not accelerating" when no acceleration beyond this (m/s²) is held.
    pub accel_clear_mps2: f64,
    /// How long (s) the acceleration must be held.
    pub accel_min_s: f64,
    /// Throttle position (0..1) that counts as pressing the accelerator; cruising takes about
    /// 0.1–0.25.
    pub throttle: f64,
    /// Acceleration (m/s²) that must come with the pressed throttle (uphill, full throttle
    /// can hold speed without accelerating).
    pub throttle_accel_mps2: f64,

    // ---- stop ----
    /// Speed (m/s) at or below which the vehicle is standing. Wheel-speed sensors read 0–0.2
    /// at a standstill; creeping in a queue is 0.5 m/s and up.
    pub stop_speed_mps: f64,
    /// "Clearly never stopped" when the smoothed speed never drops to this (m/s).
    pub stop_clear_mps: f64,
    /// How long (s) the standstill must last: rolling through 0.3 m/s is not a stop.
    pub stop_min_s: f64,

    // ---- turns ----
    /// Heading change (°) within `turn_window_s` that makes a turn. A junction turn is about
    /// 90°; a lane change or a bend stays well below.
    pub turn_heading_deg: f64,
    /// "Clearly no turn" when the heading never changes by this much (°) within the window.
    pub turn_clear_deg: f64,
    /// Window (s) in which the heading change must happen.
    pub turn_window_s: f64,
    /// Below this speed (m/s) the yaw rate is taken as zero: a standing car does not turn, so
    /// gyro noise at a standstill must not add up to a heading change.
    pub moving_speed_mps: f64,
    /// Steering-wheel to road-wheel ratio of the bicycle model, used when the track has
    /// steering but no yaw rate: yaw_rate = v · tan(steering / ratio) / wheelbase.
    pub steering_ratio: f64,
    /// Wheelbase (m) of the bicycle model.
    pub wheelbase_m: f64,

    // ---- merge (lane change) ----
    /// Lateral displacement (m) that makes a lane change when the turn signal on that side
    /// was on.
    pub merge_lateral_m: f64,
    /// Lateral displacement (m) that makes a lane change without a matching turn signal
    /// (about a full lane): without the signal's corroboration the motion alone must be
    /// unmistakable.
    pub merge_lateral_unsignalled_m: f64,
    /// "Clearly no lane change" when no window shows lateral motion beyond this (m).
    pub merge_clear_m: f64,
    /// The net heading change (°) across a lane change window must stay below this: the
    /// vehicle ends up parallel to where it started, unlike a turn.
    pub merge_max_heading_deg: f64,
    /// Longest window (s) a lane change is looked for in.
    pub merge_window_s: f64,
    /// A lane-change window must start and end driving straight: smoothed |yaw rate| at or
    /// below this (°/s). Without it the tail of a turn, measured against a heading taken
    /// mid-turn, looks like a sideways drift.
    pub merge_straight_dps: f64,
    /// How long (s) before the lateral motion a turn signal still counts for it: drivers
    /// signal first, then move.
    pub merge_signal_lead_s: f64,

    // ---- confidence ----
    /// Slope of the confidence curve: confidence = 1 / (1 + exp(−margin / (scale · |threshold|))).
    /// A margin of one `scale` times the threshold gives 0.73, two give 0.88, four 0.98.
    pub confidence_scale: f64,
}

impl Default for AnnotateConfig {
    fn default() -> Self {
        AnnotateConfig {
            max_gap_s: 1.0,
            min_coverage: 0.8,
            smooth_s: 0.5,
            speed_slope_s: 1.0,
            brake_decel_mps2: 1.5,
            brake_clear_mps2: 0.75,
            brake_min_s: 0.5,
            brake_pedal: 0.2,
            brake_pedal_decel_mps2: 0.3,
            accel_mps2: 1.0,
            accel_clear_mps2: 0.5,
            accel_min_s: 0.5,
            throttle: 0.3,
            throttle_accel_mps2: 0.5,
            stop_speed_mps: 0.3,
            stop_clear_mps: 0.45,
            stop_min_s: 1.0,
            turn_heading_deg: 45.0,
            turn_clear_deg: 20.0,
            turn_window_s: 10.0,
            moving_speed_mps: 0.5,
            steering_ratio: 15.0,
            wheelbase_m: 2.8,
            merge_lateral_m: 2.5,
            merge_lateral_unsignalled_m: 3.0,
            merge_clear_m: 1.0,
            merge_max_heading_deg: 15.0,
            merge_window_s: 10.0,
            merge_straight_dps: 2.0,
            merge_signal_lead_s: 3.0,
            confidence_scale: 0.25,
        }
    }
}

impl AnnotateConfig {
    /// Refuses settings under which the rules mean nothing: non-finite or negative values,
    /// zero durations, and "clear" levels that are not inside their decision levels (the
    /// abstain band would be empty or inverted, and negatives could overlap positives).
    pub fn validate(&self) -> Result<(), String> {
        let fields: [(&str, f64); 31] = [
            ("max_gap_s", self.max_gap_s),
            ("min_coverage", self.min_coverage),
            ("smooth_s", self.smooth_s),
            ("speed_slope_s", self.speed_slope_s),
            ("brake_decel_mps2", self.brake_decel_mps2),
            ("brake_clear_mps2", self.brake_clear_mps2),
            ("brake_min_s", self.brake_min_s),
            ("brake_pedal", self.brake_pedal),
            ("brake_pedal_decel_mps2", self.brake_pedal_decel_mps2),
            ("accel_mps2", self.accel_mps2),
            ("accel_clear_mps2", self.accel_clear_mps2),
            ("accel_min_s", self.accel_min_s),
            ("throttle", self.throttle),
            ("throttle_accel_mps2", self.throttle_accel_mps2),
            ("stop_speed_mps", self.stop_speed_mps),
            ("stop_clear_mps", self.stop_clear_mps),
            ("stop_min_s", self.stop_min_s),
            ("turn_heading_deg", self.turn_heading_deg),
            ("turn_clear_deg", self.turn_clear_deg),
            ("turn_window_s", self.turn_window_s),
            ("moving_speed_mps", self.moving_speed_mps),
            ("steering_ratio", self.steering_ratio),
            ("wheelbase_m", self.wheelbase_m),
            ("merge_lateral_m", self.merge_lateral_m),
            (
                "merge_lateral_unsignalled_m",
                self.merge_lateral_unsignalled_m,
            ),
            ("merge_clear_m", self.merge_clear_m),
            ("merge_max_heading_deg", self.merge_max_heading_deg),
            ("merge_window_s", self.merge_window_s),
            ("merge_straight_dps", self.merge_straight_dps),
            ("merge_signal_lead_s", self.merge_signal_lead_s),
            ("confidence_scale", self.confidence_scale),
        ];
        for (name, v) in fields {
            if !v.is_finite() {
                return Err(format!("annotate.{name} must be a finite number, got {v}"));
            }
            if v < 0.0 {
                return Err(format!("annotate.{name} must not be negative, got {v}"));
            }
        }
        // Zero would make a rule fire on nothing (a 0 s run, a 0 m/s² brake) or divide by 0.
        let positive: [(&str, f64); 21] = [
            ("max_gap_s", self.max_gap_s),
            ("min_coverage", self.min_coverage),
            ("smooth_s", self.smooth_s),
            ("speed_slope_s", self.speed_slope_s),
            ("brake_decel_mps2", self.brake_decel_mps2),
            ("brake_min_s", self.brake_min_s),
            ("brake_pedal", self.brake_pedal),
            ("accel_mps2", self.accel_mps2),
            ("accel_min_s", self.accel_min_s),
            ("throttle", self.throttle),
            ("stop_speed_mps", self.stop_speed_mps),
            ("stop_min_s", self.stop_min_s),
            ("turn_heading_deg", self.turn_heading_deg),
            ("turn_clear_deg", self.turn_clear_deg),
            ("turn_window_s", self.turn_window_s),
            ("steering_ratio", self.steering_ratio),
            ("wheelbase_m", self.wheelbase_m),
            ("merge_lateral_m", self.merge_lateral_m),
            ("merge_clear_m", self.merge_clear_m),
            ("merge_window_s", self.merge_window_s),
            ("confidence_scale", self.confidence_scale),
        ];
        for (name, v) in positive {
            if v <= 0.0 {
                return Err(format!("annotate.{name} must be greater than 0, got {v}"));
            }
        }
        if self.min_coverage > 1.0 {
            return Err(format!(
                "annotate.min_coverage is a share in (0, 1], got {}",
                self.min_coverage
            ));
        }
        for (name, v) in [
            ("brake_pedal", self.brake_pedal),
            ("throttle", self.throttle),
        ] {
            if v > 1.0 {
                return Err(format!(
                    "annotate.{name} is a pedal position in (0, 1], got {v}"
                ));
            }
        }
        let inside: [(&str, f64, &str, f64); 6] = [
            (
                "brake_clear_mps2",
                self.brake_clear_mps2,
                "brake_decel_mps2",
                self.brake_decel_mps2,
            ),
            (
                "accel_clear_mps2",
                self.accel_clear_mps2,
                "accel_mps2",
                self.accel_mps2,
            ),
            (
                "stop_speed_mps",
                self.stop_speed_mps,
                "stop_clear_mps",
                self.stop_clear_mps,
            ),
            (
                "turn_clear_deg",
                self.turn_clear_deg,
                "turn_heading_deg",
                self.turn_heading_deg,
            ),
            (
                "merge_clear_m",
                self.merge_clear_m,
                "merge_lateral_m",
                self.merge_lateral_m,
            ),
            (
                "merge_max_heading_deg",
                self.merge_max_heading_deg,
                "turn_heading_deg",
                self.turn_heading_deg,
            ),
        ];
        for (a, va, b, vb) in inside {
            if va >= vb {
                return Err(format!(
                    "annotate.{a} ({va}) must be below annotate.{b} ({vb})"
                ));
            }
        }
        if self.merge_lateral_unsignalled_m < self.merge_lateral_m {
            return Err(format!(
                "annotate.merge_lateral_unsignalled_m ({}) must not be below annotate.merge_lateral_m ({}): \
                 an unsignalled lane change needs more evidence, not less",
                self.merge_lateral_unsignalled_m, self.merge_lateral_m
            ));
        }
        Ok(())
    }
}
