//! The kinematic rules: driving labels read off a vehicle-signal [`Track`].
//!
//! Why rules and not a model: these labels are the "kinematic" annotator of the paper, the
//! one source whose errors are not correlated with the vision models' (it never looks at a
//! frame). Its worth to the fusion is that it is *right when it speaks*, so every rule has an
//! abstain band: a label the signals cannot decide — a needed column missing or too sparse, a
//! margin inside the band between "clearly yes" and "clearly no" — is left out of
//! [`Annotation::labels`] and listed in [`Annotation::undecided`] with the reason. Nothing is
//! guessed.
//!
//! Conventions: SI units; positive yaw rate and steering turn **left** (counter-clockwise
//! seen from above, ISO 8855); lateral displacement is positive to the left. Every threshold
//! is a field of [`AnnotateConfig`] (defaults in brackets below).
//!
//! Signals used. *Acceleration* is `accel_mps2` smoothed over `smooth_s` [0.5 s], or, when
//! the track has none, the local linear slope of `speed_mps` over `speed_slope_s` [1 s].
//! *Yaw rate* is `yaw_rate_dps`, or, without it, the kinematic bicycle model
//! `v · tan(steering_deg / steering_ratio) / wheelbase_m` [15, 2.8 m]; it is taken as zero
//! below `moving_speed_mps` [0.5] (a standing car does not turn; gyro noise must not
//! integrate into a heading change). *Heading* integrates the yaw rate; *position*
//! integrates `v · (cos, sin)(heading)`. A signal with values at fewer than `min_coverage`
//! [80 %] of the samples counts as absent; nothing spans a gap over `max_gap_s` [1 s].
//! "Held for d" below means the level a signal stays past for at least d seconds (the
//! minimum over d-long stretches of the stretch's maximum), so one noisy sample can neither
//! make nor break it.
//!
//! - **brake**: positive when a deceleration of at least `brake_decel_mps2` [1.5 m/s²] is held
//!   for `brake_min_s` [0.5 s], or when the brake pedal is at least `brake_pedal` [0.2] while
//!   decelerating by at least `brake_pedal_decel_mps2` [0.3], held as long. Negative when no
//!   deceleration beyond `brake_clear_mps2` [0.75] is held and no such pedal stretch exists.
//!   Coasting on engine drag (0.2–0.8 m/s², no pedal) therefore never reads as a brake, and
//!   1.1 m/s² without a pedal is undecided.
//! - **accelerate**: positive when at least `accel_mps2` [1.0] is held for `accel_min_s`
//!   [0.5 s] and the speed (if the track has it) rose across that stretch, or when the throttle
//!   is at least `throttle` [0.3] while accelerating by `throttle_accel_mps2` [0.5]. Negative
//!   when nothing beyond `accel_clear_mps2` [0.5] is held and no such throttle stretch exists.
//! - **stop**: needs `speed_mps` (acceleration alone cannot tell a standstill from cruising).
//!   Positive when the speed stays at or below `stop_speed_mps` [0.3] for `stop_min_s` [1 s]
//!   (the clip contains a standstill); negative when the smoothed speed never drops to
//!   `stop_clear_mps` [0.45]. Creeping in a queue at 0.5–1.5 m/s is not a stop; rolling
//!   through 0.2 m/s for half a second is undecided.
//! - **turn_left / turn_right**: positive when the heading changes by at least
//!   `turn_heading_deg` [45°] to that side within `turn_window_s` [10 s] (the largest rise,
//!   resp. fall, of the heading over any window that long); negative when it never changes by
//!   `turn_clear_deg` [20°] to that side. A lane change swings the heading a few degrees one
//!   way and back, so it is neither.
//! - **merge** (lane change): over windows of at most `merge_window_s` [10 s] that start and
//!   end driving straight (smoothed |yaw| ≤ `merge_straight_dps` [2 °/s]) with a net heading
//!   change under `merge_max_heading_deg` [15°] (the car ends parallel to where it started:
//!   a lane change, not a turn), the lateral displacement, measured in the frames of both
//!   ends and taken as the smaller (0 when they disagree: a bend followed by a straight
//!   drifts sideways in opposite directions in the two frames, a lane change does not).
//!   Positive when it reaches `merge_lateral_m` [2.5 m] with the turn signal of that side on
//!   during the window or up to `merge_signal_lead_s` [3 s] before it, or
//!   `merge_lateral_unsignalled_m` [3 m] without. Negative when no window moves sideways by
//!   `merge_clear_m` [1 m] and no turn signal was on, other than one explained by a turn the
//!   rules found to that side. A track without `turn_signal` is judged on motion alone.
//!
//! Confidence is a logistic function of the margin past the deciding threshold, in units of
//! that threshold: `1 / (1 + exp(−margin / (confidence_scale · |threshold|)))`
//! [`confidence_scale` 0.25]; see [`confidence`]. A decision exactly at its threshold is 0.5,
//! one a quarter of the threshold past it 0.73, one a full threshold past it 0.98. Positives
//! decided by several paths take the most confident; negatives, which need every condition,
//! take the least.
//!
//! Work is O(samples): see [`crate::signal`]'s bounds.

use crate::config::AnnotateConfig;
use crate::signal::{self, Held};
use crate::track::{Track, TurnSignal};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// The labels the rules decide (ontology ids), in output order.
pub const LABELS: [&str; 6] = [
    "brake",
    "accelerate",
    "stop",
    "turn_left",
    "turn_right",
    "merge",
];

/// One observation behind a decision.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Evidence {
    /// What was measured, naming its source (`accel_mps2`, `accel from speed_mps`, `heading
    /// from yaw_rate_dps`, `lateral from steering_deg`…).
    pub signal: String,
    /// When: the start of the stretch or window the value holds over (track time, s).
    pub t_s: f64,
    /// The measured level, in the signal's unit.
    pub value: f64,
    /// The threshold it was compared with.
    pub threshold: f64,
    /// How far past the threshold, in the signal's unit, in the direction of the decision
    /// (never negative): for a positive, how far beyond the decision level; for a negative,
    /// how far inside the clear level.
    pub margin: f64,
    /// The comparison in words, for a reviewer.
    pub note: String,
}

/// A decided label.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Derived {
    pub label: String,
    /// `true`: the manoeuvre happened in the window; `false`: it confidently did not.
    pub value: bool,
    /// In (0.5, 1): see [`confidence`].
    pub confidence: f64,
    pub evidence: Vec<Evidence>,
}

/// A label the signals could not decide, and why.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Undecided {
    pub label: String,
    pub reason: String,
}

/// The rules' output for one window of a track.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Annotation {
    /// The time span of the samples annotated (first and last sample in the window).
    pub start_s: f64,
    pub end_s: f64,
    /// Samples in the window.
    pub samples: usize,
    /// Decided labels, positives and negatives, in [`LABELS`] order.
    pub labels: Vec<Derived>,
    /// Every label of [`LABELS`] not in `labels`, with the reason.
    pub undecided: Vec<Undecided>,
}

impl Annotation {
    /// The decision on `label`, if decided.
    pub fn get(&self, label: &str) -> Option<&Derived> {
        self.labels.iter().find(|d| d.label == label)
    }

    /// `Some(true/false)` when decided, `None` when unknown.
    pub fn value(&self, label: &str) -> Option<bool> {
        self.get(label).map(|d| d.value)
    }

    /// The undecided ("unknown") label ids.
    pub fn unknown(&self) -> Vec<&str> {
        self.undecided.iter().map(|u| u.label.as_str()).collect()
    }

    /// The reason `label` is undecided, if it is.
    pub fn reason(&self, label: &str) -> Option<&str> {
        self.undecided
            .iter()
            .find(|u| u.label == label)
            .map(|u| u.reason.as_str())
    }

    /// The positive label ids.
    pub fn positives(&self) -> Vec<&str> {
        self.labels
            .iter()
            .filter(|d| d.value)
            .map(|d| d.label.as_str())
            .collect()
    }
}

/// Confidence of a decision `margin` past a `threshold` (same unit): logistic in
/// `margin / (scale · |threshold|)`, 0.5 at the threshold, approaching 1 far past it. Why
/// relative to the threshold: margins in m/s², degrees and metres become comparable, and a
/// decision twice as far past its threshold is as sure whatever the unit.
pub fn confidence(margin: f64, threshold: f64, scale: f64) -> f64 {
    let unit = (scale * threshold.abs()).max(1e-9);
    let x = margin.max(0.0) / unit;
    1.0 / (1.0 + (-x).exp())
}

/// Derives [`LABELS`] from the samples of `track` inside `window` (`(start_s, end_s)`,
/// inclusive; `None` for the whole track). Whether the track covers the clip is the caller's
/// check ([`Track::covers`]): a window with fewer than 2 samples leaves every label
/// undecided. An invalid `cfg` (see [`AnnotateConfig::validate`]) does too, with the reason.
pub fn annotate(track: &Track, window: Option<(f64, f64)>, cfg: &AnnotateConfig) -> Annotation {
    let t_all = track.t_s();
    let (lo, hi) = match window {
        None => (0, t_all.len()),
        Some((a, b)) => (
            t_all.partition_point(|&t| t < a),
            t_all.partition_point(|&t| t <= b),
        ),
    };
    let (lo, hi) = (lo, hi.max(lo));
    let all_undecided = |start_s: f64, end_s: f64, reason: String| Annotation {
        start_s,
        end_s,
        samples: hi - lo,
        labels: Vec::new(),
        undecided: LABELS
            .iter()
            .map(|l| Undecided {
                label: l.to_string(),
                reason: reason.clone(),
            })
            .collect(),
    };
    let (ws, we) = window.unwrap_or((t_all[0], t_all[t_all.len() - 1]));
    if let Err(e) = cfg.validate() {
        return all_undecided(ws, we, format!("invalid annotate config: {e}"));
    }
    if hi - lo < 2 {
        return all_undecided(
            ws,
            we,
            format!(
                "the window {ws} s to {we} s holds {} samples (2 needed)",
                hi - lo
            ),
        );
    }
    let ctx = Ctx::new(track, lo, hi, cfg);
    let mut out: Vec<(&str, Result<Derived, String>)> = Vec::with_capacity(LABELS.len());
    out.push(("brake", ctx.brake()));
    out.push(("accelerate", ctx.accelerate()));
    out.push(("stop", ctx.stop()));
    let (left, right) = ctx.turns();
    let turned = (
        left.as_ref().is_ok_and(|d| d.value),
        right.as_ref().is_ok_and(|d| d.value),
    );
    out.push(("turn_left", left));
    out.push(("turn_right", right));
    out.push(("merge", ctx.merge(turned)));
    let mut ann = Annotation {
        start_s: ctx.t[0],
        end_s: ctx.t[ctx.t.len() - 1],
        samples: ctx.t.len(),
        labels: Vec::new(),
        undecided: Vec::new(),
    };
    for (label, r) in out {
        match r {
            Ok(d) => ann.labels.push(d),
            Err(reason) => ann.undecided.push(Undecided {
                label: label.to_string(),
                reason,
            }),
        }
    }
    ann
}

/// A conditioned signal and where it came from.
struct Sig {
    v: Vec<Option<f64>>,
    source: String,
}

/// The window's signals, conditioned once for all rules.
struct Ctx<'a> {
    cfg: &'a AnnotateConfig,
    t: &'a [f64],
    /// Smoothed speed, or why there is none.
    speed: Result<Sig, String>,
    accel: Result<Sig, String>,
    /// Smoothed yaw rate (°/s), gated by speed.
    yaw: Result<Sig, String>,
    brake: Option<&'a [Option<f64>]>,
    throttle: Option<&'a [Option<f64>]>,
    signal: Option<&'a [Option<TurnSignal>]>,
}

fn usable<'a>(
    name: &str,
    col: Option<&'a [Option<f64>]>,
    lo: usize,
    hi: usize,
    cfg: &AnnotateConfig,
) -> Result<&'a [Option<f64>], String> {
    let Some(c) = col else {
        return Err(format!("the track has no `{name}`"));
    };
    let c = &c[lo..hi];
    let cov = signal::coverage(c);
    if cov < cfg.min_coverage {
        return Err(format!(
            "`{name}` has values at {:.0}% of the window's samples (at least {:.0}% needed)",
            cov * 100.0,
            cfg.min_coverage * 100.0
        ));
    }
    Ok(c)
}

impl<'a> Ctx<'a> {
    fn new(track: &'a Track, lo: usize, hi: usize, cfg: &'a AnnotateConfig) -> Ctx<'a> {
        let t = &track.t_s()[lo..hi];
        let raw_speed = usable("speed_mps", track.speed_mps(), lo, hi, cfg);
        let speed = raw_speed.clone().map(|v| Sig {
            v: signal::moving_average(t, v, cfg.smooth_s),
            source: "speed_mps".to_string(),
        });
        let accel = match usable("accel_mps2", track.accel_mps2(), lo, hi, cfg) {
            Ok(a) => Ok(Sig {
                v: signal::moving_average(t, a, cfg.smooth_s),
                source: "accel_mps2".to_string(),
            }),
            Err(why_a) => match &raw_speed {
                Ok(v) => Ok(Sig {
                    v: signal::slope(t, v, cfg.speed_slope_s),
                    source: "accel from speed_mps".to_string(),
                }),
                Err(why_v) => Err(format!("{why_a} and {why_v}")),
            },
        };
        let yaw = match usable("yaw_rate_dps", track.yaw_rate_dps(), lo, hi, cfg) {
            Ok(y) => Ok(Sig {
                v: signal::moving_average(t, y, cfg.smooth_s),
                source: "yaw_rate_dps".to_string(),
            }),
            Err(why_y) => match (
                usable("steering_deg", track.steering_deg(), lo, hi, cfg),
                &speed,
            ) {
                (Ok(st), Ok(v)) => {
                    let st = signal::moving_average(t, st, cfg.smooth_s);
                    let yaw = st
                        .iter()
                        .zip(&v.v)
                        .map(|(s, v)| match (s, v) {
                            (Some(s), Some(v)) => Some(
                                (v * (s / cfg.steering_ratio).to_radians().tan() / cfg.wheelbase_m)
                                    .to_degrees(),
                            ),
                            _ => None,
                        })
                        .collect();
                    Ok(Sig {
                        v: yaw,
                        source: "steering_deg (bicycle model)".to_string(),
                    })
                }
                (Err(why_s), _) => Err(format!("{why_y} and {why_s}")),
                (Ok(_), Err(why_v)) => Err(format!(
                    "{why_y}, and steering_deg alone needs speed_mps: {why_v}"
                )),
            },
        };
        // A standing car does not turn: zero the yaw rate below walking pace.
        let yaw = yaw.map(|mut y| {
            if let Ok(v) = &speed {
                for (y, v) in y.v.iter_mut().zip(&v.v) {
                    if let (Some(yy), Some(vv)) = (y.as_mut(), v) {
                        if *vv < cfg.moving_speed_mps {
                            *yy = 0.0;
                        }
                    }
                }
            }
            y
        });
        let slice = |c: Option<&'a [Option<f64>]>, name: &str| usable(name, c, lo, hi, cfg).ok();
        Ctx {
            cfg,
            t,
            speed,
            accel,
            yaw,
            brake: slice(track.brake(), "brake"),
            throttle: slice(track.throttle(), "throttle"),
            signal: track.turn_signal().map(|s| &s[lo..hi]),
        }
    }

    fn conf(&self, margin: f64, threshold: f64) -> f64 {
        confidence(margin, threshold, self.cfg.confidence_scale)
    }

    fn span(&self, h: &Held) -> String {
        format!(
            "{:.1} s (from {:.2} s to {:.2} s)",
            self.t[h.end] - self.t[h.start],
            self.t[h.start],
            self.t[h.end]
        )
    }

    /// The stretch where pedal ≥ `pedal_level` while the acceleration is past `accel_level`
    /// in direction `dir` (−1: decelerating, +1: accelerating), held for `min_s`: the held
    /// level of min(pedal − pedal_level, dir·accel − accel_level), ≥ 0 when both hold.
    fn pedal_stretch(
        &self,
        pedal: &[Option<f64>],
        accel: &[Option<f64>],
        pedal_level: f64,
        dir: f64,
        accel_level: f64,
        min_s: f64,
    ) -> Option<Held> {
        let m: Vec<Option<f64>> = pedal
            .iter()
            .zip(accel)
            .map(|(p, a)| match (p, a) {
                (Some(p), Some(a)) => Some((p - pedal_level).min(dir * a - accel_level)),
                _ => None,
            })
            .collect();
        signal::held_high(self.t, &m, min_s, self.cfg.max_gap_s)
    }

    fn brake(&self) -> Result<Derived, String> {
        let c = self.cfg;
        let a = self
            .accel
            .as_ref()
            .map_err(|e| format!("no acceleration: {e}"))?;
        let Some(low) = signal::held_low(self.t, &a.v, c.brake_min_s, c.max_gap_s) else {
            return Err(format!(
                "no stretch of {} s with an acceleration estimate",
                c.brake_min_s
            ));
        };
        let pedal = self.brake.and_then(|p| {
            self.pedal_stretch(
                p,
                &a.v,
                c.brake_pedal,
                -1.0,
                c.brake_pedal_decel_mps2,
                c.brake_min_s,
            )
            .map(|h| (p, h))
        });
        let mut pos = Vec::new();
        let mut conf: f64 = 0.0;
        if low.level <= -c.brake_decel_mps2 {
            let margin = -c.brake_decel_mps2 - low.level;
            conf = conf.max(self.conf(margin, c.brake_decel_mps2));
            pos.push(Evidence {
                signal: a.source.clone(),
                t_s: self.t[low.start],
                value: low.level,
                threshold: -c.brake_decel_mps2,
                margin,
                note: format!(
                    "decelerating by at least {:.2} m/s² for {}",
                    -low.level,
                    self.span(&low)
                ),
            });
        }
        if let Some((p, h)) = pedal.filter(|(_, h)| h.level >= 0.0) {
            let pmin = p[h.start..=h.end]
                .iter()
                .flatten()
                .fold(f64::INFINITY, |m, &x| m.min(x));
            let margin = (pmin - c.brake_pedal).max(0.0);
            conf = conf.max(self.conf(margin, c.brake_pedal));
            pos.push(Evidence {
                signal: "brake".to_string(),
                t_s: self.t[h.start],
                value: pmin,
                threshold: c.brake_pedal,
                margin,
                note: format!(
                    "brake pedal at least {pmin:.2} while decelerating by at least {:.2} m/s² for {}",
                    c.brake_pedal_decel_mps2,
                    self.span(&h)
                ),
            });
        }
        if !pos.is_empty() {
            return Ok(derived("brake", true, conf, pos));
        }
        let pedal_clear = pedal.is_none_or(|(_, h)| h.level < 0.0);
        if low.level > -c.brake_clear_mps2 && pedal_clear {
            let margin = low.level + c.brake_clear_mps2;
            let mut ev = vec![Evidence {
                signal: a.source.clone(),
                t_s: self.t[low.start],
                value: low.level,
                threshold: -c.brake_clear_mps2,
                margin,
                note: format!(
                    "no deceleration beyond {:.2} m/s² held for {} s (strongest held: {:.2} m/s²)",
                    c.brake_clear_mps2, c.brake_min_s, -low.level
                ),
            }];
            let mut conf = self.conf(margin, c.brake_clear_mps2);
            if let Some((_, h)) = pedal {
                // The pedal stretch level is in pedal units where the pedal is the binding term.
                let m = -h.level;
                conf = conf.min(self.conf(m, c.brake_pedal));
                ev.push(Evidence {
                    signal: "brake".to_string(),
                    t_s: self.t[h.start],
                    // In pedal units, floored at 0: where the deceleration term binds, the
                    // joint level can sit below any pedal position.
                    value: (h.level + c.brake_pedal).max(0.0),
                    threshold: c.brake_pedal,
                    margin: m,
                    note: format!(
                        "the brake pedal never reached {} while decelerating for {} s",
                        c.brake_pedal, c.brake_min_s
                    ),
                });
            }
            return Ok(derived("brake", false, conf, ev));
        }
        Err(if !pedal_clear {
            "the brake pedal was pressed without a decision from the deceleration".to_string()
        } else {
            format!(
                "strongest deceleration held for {} s is {:.2} m/s²: between the clear level {} \
                 and the brake level {}",
                c.brake_min_s, -low.level, c.brake_clear_mps2, c.brake_decel_mps2
            )
        })
    }

    fn accelerate(&self) -> Result<Derived, String> {
        let c = self.cfg;
        let a = self
            .accel
            .as_ref()
            .map_err(|e| format!("no acceleration: {e}"))?;
        let Some(high) = signal::held_high(self.t, &a.v, c.accel_min_s, c.max_gap_s) else {
            return Err(format!(
                "no stretch of {} s with an acceleration estimate",
                c.accel_min_s
            ));
        };
        let throttle = self.throttle.and_then(|p| {
            self.pedal_stretch(
                p,
                &a.v,
                c.throttle,
                1.0,
                c.throttle_accel_mps2,
                c.accel_min_s,
            )
            .map(|h| (p, h))
        });
        let mut pos = Vec::new();
        let mut conf: f64 = 0.0;
        let mut speed_vetoed = false;
        if high.level >= c.accel_mps2 {
            // An accelerometer also reads pitch (a slope, a bump): insist the speed rose.
            let gain = self
                .speed
                .as_ref()
                .ok()
                .and_then(|v| Some(v.v[high.end]? - v.v[high.start]?));
            if gain.is_none_or(|g| g > 0.0) {
                let margin = high.level - c.accel_mps2;
                conf = conf.max(self.conf(margin, c.accel_mps2));
                pos.push(Evidence {
                    signal: a.source.clone(),
                    t_s: self.t[high.start],
                    value: high.level,
                    threshold: c.accel_mps2,
                    margin,
                    note: format!(
                        "accelerating by at least {:.2} m/s² for {}{}",
                        high.level,
                        self.span(&high),
                        gain.map(|g| format!(", speed +{g:.2} m/s"))
                            .unwrap_or_default()
                    ),
                });
            } else {
                speed_vetoed = true;
            }
        }
        if let Some((p, h)) = throttle.filter(|(_, h)| h.level >= 0.0) {
            let pmin = p[h.start..=h.end]
                .iter()
                .flatten()
                .fold(f64::INFINITY, |m, &x| m.min(x));
            let margin = (pmin - c.throttle).max(0.0);
            conf = conf.max(self.conf(margin, c.throttle));
            pos.push(Evidence {
                signal: "throttle".to_string(),
                t_s: self.t[h.start],
                value: pmin,
                threshold: c.throttle,
                margin,
                note: format!(
                    "throttle at least {pmin:.2} while accelerating by at least {:.2} m/s² for {}",
                    c.throttle_accel_mps2,
                    self.span(&h)
                ),
            });
        }
        if !pos.is_empty() {
            return Ok(derived("accelerate", true, conf, pos));
        }
        if speed_vetoed {
            return Err(format!(
                "{} reads {:.2} m/s² held, but the speed did not rise over it",
                a.source, high.level
            ));
        }
        let throttle_clear = throttle.is_none_or(|(_, h)| h.level < 0.0);
        if high.level < c.accel_clear_mps2 && throttle_clear {
            let margin = c.accel_clear_mps2 - high.level;
            let mut conf = self.conf(margin, c.accel_clear_mps2);
            let mut ev = vec![Evidence {
                signal: a.source.clone(),
                t_s: self.t[high.start],
                value: high.level,
                threshold: c.accel_clear_mps2,
                margin,
                note: format!(
                    "no acceleration beyond {:.2} m/s² held for {} s (strongest held: {:.2})",
                    c.accel_clear_mps2, c.accel_min_s, high.level
                ),
            }];
            if let Some((_, h)) = throttle {
                let m = -h.level;
                conf = conf.min(self.conf(m, c.throttle));
                ev.push(Evidence {
                    signal: "throttle".to_string(),
                    t_s: self.t[h.start],
                    value: (h.level + c.throttle).max(0.0),
                    threshold: c.throttle,
                    margin: m,
                    note: format!(
                        "the throttle never reached {} while accelerating for {} s",
                        c.throttle, c.accel_min_s
                    ),
                });
            }
            return Ok(derived("accelerate", false, conf, ev));
        }
        Err(if !throttle_clear {
            "the throttle was pressed without a decision from the acceleration".to_string()
        } else {
            format!(
                "strongest acceleration held for {} s is {:.2} m/s²: between the clear level {} \
                 and the accelerate level {}",
                c.accel_min_s, high.level, c.accel_clear_mps2, c.accel_mps2
            )
        })
    }

    fn stop(&self) -> Result<Derived, String> {
        let c = self.cfg;
        let v = self
            .speed
            .as_ref()
            .map_err(|e| format!("a stop needs the speed: {e}"))?;
        let Some(low) = signal::held_low(self.t, &v.v, c.stop_min_s, c.max_gap_s) else {
            return Err(format!("no stretch of {} s with a speed", c.stop_min_s));
        };
        if low.level <= c.stop_speed_mps {
            let margin = c.stop_speed_mps - low.level;
            return Ok(derived(
                "stop",
                true,
                self.conf(margin, c.stop_speed_mps),
                vec![Evidence {
                    signal: v.source.clone(),
                    t_s: self.t[low.start],
                    value: low.level,
                    threshold: c.stop_speed_mps,
                    margin,
                    note: format!(
                        "at most {:.2} m/s for {}: standing",
                        low.level,
                        self.span(&low)
                    ),
                }],
            ));
        }
        // "Clearly never stopped" asks more than the positive's mirror image: not one
        // (smoothed) sample may come near a standstill, so rolling through 0.2 m/s for half
        // a second stays undecided rather than "no stop".
        let (kmin, vmin) =
            v.v.iter()
                .enumerate()
                .filter_map(|(k, x)| x.map(|x| (k, x)))
                .fold(
                    (low.start, f64::INFINITY),
                    |b, (k, x)| if x < b.1 { (k, x) } else { b },
                );
        if vmin > c.stop_clear_mps {
            let margin = vmin - c.stop_clear_mps;
            return Ok(derived(
                "stop",
                false,
                self.conf(margin, c.stop_clear_mps),
                vec![Evidence {
                    signal: v.source.clone(),
                    t_s: self.t[kmin],
                    value: vmin,
                    threshold: c.stop_clear_mps,
                    margin,
                    note: format!(
                        "the speed never dropped below {vmin:.2} m/s (at {:.2} s): always moving",
                        self.t[kmin]
                    ),
                }],
            ));
        }
        Err(format!(
            "the speed dropped to {vmin:.2} m/s at {:.2} s, but the lowest held for {} s is \
             {:.2} m/s: not a standstill at or below {} m/s, not always above {} m/s",
            self.t[kmin], c.stop_min_s, low.level, c.stop_speed_mps, c.stop_clear_mps
        ))
    }

    /// Heading (°) per sample, `None` outside the stretches it can be integrated over, and
    /// those stretches.
    fn heading(&self, yaw: &[Option<f64>]) -> (Vec<Option<f64>>, Vec<(usize, usize)>) {
        let segs = signal::segments(self.t, |i| yaw[i].is_some(), self.cfg.max_gap_s);
        let mut psi = vec![None; self.t.len()];
        for &(s, e) in &segs {
            let mut h = 0.0;
            psi[s] = Some(0.0);
            for k in s + 1..e {
                let (y0, y1) = (yaw[k - 1].unwrap_or(0.0), yaw[k].unwrap_or(0.0));
                h += 0.5 * (y0 + y1) * (self.t[k] - self.t[k - 1]);
                psi[k] = Some(h);
            }
        }
        (psi, segs)
    }

    fn turns(&self) -> (Result<Derived, String>, Result<Derived, String>) {
        let c = self.cfg;
        let yaw = match &self.yaw {
            Ok(y) => y,
            Err(e) => {
                let r = format!("no yaw rate: {e}");
                return (Err(r.clone()), Err(r));
            }
        };
        let (psi, segs) = self.heading(&yaw.v);
        let mut rise: Option<Swing> = None;
        let mut fall: Option<Swing> = None;
        for &(s, e) in &segs {
            if let Some(r) = max_swing(self.t, &psi, s, e, c.turn_window_s, 1.0) {
                if rise.is_none_or(|b| r.amount > b.amount) {
                    rise = Some(r);
                }
            }
            if let Some(f) = max_swing(self.t, &psi, s, e, c.turn_window_s, -1.0) {
                if fall.is_none_or(|b| f.amount > b.amount) {
                    fall = Some(f);
                }
            }
        }
        let source = format!("heading from {}", yaw.source);
        let decide = |label: &str, side: &str, sw: Option<Swing>| -> Result<Derived, String> {
            let Some(sw) = sw else {
                return Err("no stretch of yaw rate to integrate".to_string());
            };
            let (t0, t1) = (self.t[sw.start], self.t[sw.end]);
            if sw.amount >= c.turn_heading_deg {
                let margin = sw.amount - c.turn_heading_deg;
                return Ok(derived(
                    label,
                    true,
                    self.conf(margin, c.turn_heading_deg),
                    vec![Evidence {
                        signal: source.clone(),
                        t_s: t0,
                        value: sw.amount,
                        threshold: c.turn_heading_deg,
                        margin,
                        note: format!(
                            "heading turned {:.0}° to the {side} from {t0:.2} s to {t1:.2} s",
                            sw.amount
                        ),
                    }],
                ));
            }
            if sw.amount < c.turn_clear_deg {
                let margin = c.turn_clear_deg - sw.amount;
                return Ok(derived(
                    label,
                    false,
                    self.conf(margin, c.turn_clear_deg),
                    vec![Evidence {
                        signal: source.clone(),
                        t_s: t0,
                        value: sw.amount,
                        threshold: c.turn_clear_deg,
                        margin,
                        note: format!(
                            "the heading never turned more than {:.0}° to the {side} within {} s",
                            sw.amount, c.turn_window_s
                        ),
                    }],
                ));
            }
            Err(format!(
                "the heading turned {:.0}° to the {side} within {} s: between the clear level \
                 {}° and the turn level {}°",
                sw.amount, c.turn_window_s, c.turn_clear_deg, c.turn_heading_deg
            ))
        };
        (
            decide("turn_left", "left", rise),
            decide("turn_right", "right", fall),
        )
    }

    fn merge(&self, turned: (bool, bool)) -> Result<Derived, String> {
        let c = self.cfg;
        let yaw = self.yaw.as_ref().map_err(|e| format!("no yaw rate: {e}"))?;
        let v = self
            .speed
            .as_ref()
            .map_err(|e| format!("lateral motion needs the speed: {e}"))?;
        let yaw_v: Vec<Option<f64>> = yaw.v.iter().zip(&v.v).map(|(y, s)| s.and(*y)).collect();
        let (psi, segs) = self.heading(&yaw_v);
        let n = self.t.len();
        // Position in the frame of each stretch's first sample.
        let (mut x, mut y) = (vec![0.0; n], vec![0.0; n]);
        for &(s, e) in &segs {
            for k in s + 1..e {
                let dt = self.t[k] - self.t[k - 1];
                let (p0, p1) = (
                    psi[k - 1].unwrap_or(0.0).to_radians(),
                    psi[k].unwrap_or(0.0).to_radians(),
                );
                let (v0, v1) = (v.v[k - 1].unwrap_or(0.0), v.v[k].unwrap_or(0.0));
                x[k] = x[k - 1] + 0.5 * dt * (v0 * p0.cos() + v1 * p1.cos());
                y[k] = y[k - 1] + 0.5 * dt * (v0 * p0.sin() + v1 * p1.sin());
            }
        }
        let straight = |k: usize| yaw_v[k].is_some_and(|r| r.abs() <= c.merge_straight_dps);
        // Prefix counts of left / right signal samples, for "was it on in [a, b]".
        let (mut left_n, mut right_n) = (vec![0usize; n + 1], vec![0usize; n + 1]);
        for k in 0..n {
            let s = self.signal.and_then(|s| s[k]);
            left_n[k + 1] = left_n[k] + usize::from(s == Some(TurnSignal::Left));
            right_n[k + 1] = right_n[k] + usize::from(s == Some(TurnSignal::Right));
        }
        let signalled = |side_left: bool, t0: f64, t1: f64| {
            let a = self.t.partition_point(|&t| t < t0);
            let b = self.t.partition_point(|&t| t <= t1);
            let p = if side_left { &left_n } else { &right_n };
            p[b.max(a)] > p[a]
        };

        let mut windows = 0usize;
        let mut widest: Option<(f64, usize, usize, f64)> = None; // (lateral, i, j, net heading)
        let mut best_pos: Option<(f64, f64, usize, usize, f64, bool)> = None; // margin, lateral, i, j, net, signalled
        for &(s, e) in &segs {
            let mut end = s;
            for i in s..e {
                end = end.max(i);
                while end + 1 < e && self.t[end + 1] - self.t[i] <= c.merge_window_s {
                    end += 1;
                }
                if end == i || !straight(i) {
                    continue;
                }
                let Some(pi) = psi[i] else { continue };
                // Every window length up to merge_window_s (the shortest window around a
                // lane change is the least disturbed by heading noise), thinned to at most
                // WINDOW_ENDS ends per start so the work stays O(samples).
                let stride = (end - i).div_ceil(WINDOW_ENDS).max(1);
                let mut j = i;
                while j < end {
                    j = (j + stride).min(end);
                    if !straight(j) {
                        continue;
                    }
                    let Some(pj) = psi[j] else { continue };
                    let net = pj - pi;
                    if net.abs() >= c.merge_max_heading_deg {
                        continue;
                    }
                    windows += 1;
                    let lat = lateral(x[j] - x[i], y[j] - y[i], pi, pj);
                    if widest.is_none_or(|w| lat.abs() > w.0.abs()) {
                        widest = Some((lat, i, j, net));
                    }
                    if lat.abs() < c.merge_lateral_m {
                        continue;
                    }
                    let sig = signalled(lat > 0.0, self.t[i] - c.merge_signal_lead_s, self.t[j]);
                    let need = if sig {
                        c.merge_lateral_m
                    } else {
                        c.merge_lateral_unsignalled_m
                    };
                    let margin = lat.abs() - need;
                    if margin >= 0.0 && best_pos.is_none_or(|b| margin > b.0) {
                        best_pos = Some((margin, lat, i, j, net, sig));
                    }
                }
            }
        }
        let source = format!("lateral from {} and {}", yaw.source, v.source);
        let side = |lat: f64| if lat > 0.0 { "left" } else { "right" };
        if let Some((margin, lat, i, j, net, sig)) = best_pos {
            let need = if sig {
                c.merge_lateral_m
            } else {
                c.merge_lateral_unsignalled_m
            };
            return Ok(derived(
                "merge",
                true,
                self.conf(margin, need),
                vec![Evidence {
                    signal: source,
                    t_s: self.t[i],
                    value: lat,
                    threshold: need.copysign(lat),
                    margin,
                    note: format!(
                        "moved {:.1} m to the {} from {:.2} s to {:.2} s with a net heading change \
                         of {net:.0}°, {}",
                        lat.abs(),
                        side(lat),
                        self.t[i],
                        self.t[j],
                        if sig {
                            "with the turn signal on that side"
                        } else {
                            "without a matching turn signal"
                        }
                    ),
                }],
            ));
        }
        let Some((lat, i, j, _)) = widest else {
            return Err(format!(
                "no window of up to {} s starts and ends driving straight with a small net \
                 heading change",
                c.merge_window_s
            ));
        };
        // A turn signal the turn rules explain (a turn to that side) is not a lane change cue.
        let unexplained_signal = |side_left: bool, turned_that_way: bool| {
            let p = if side_left { &left_n } else { &right_n };
            p[n] > 0 && !turned_that_way
        };
        let signal_on = unexplained_signal(true, turned.0) || unexplained_signal(false, turned.1);
        if lat.abs() < c.merge_clear_m && !signal_on {
            let margin = c.merge_clear_m - lat.abs();
            return Ok(derived(
                "merge",
                false,
                self.conf(margin, c.merge_clear_m),
                vec![Evidence {
                    signal: source,
                    t_s: self.t[i],
                    value: lat,
                    threshold: c.merge_clear_m,
                    margin,
                    note: format!(
                        "at most {:.1} m of lateral motion over {windows} straight windows of up \
                         to {} s{}",
                        lat.abs(),
                        c.merge_window_s,
                        if self.signal.is_some() {
                            ", no unexplained turn signal"
                        } else {
                            " (no turn_signal column)"
                        }
                    ),
                }],
            ));
        }
        Err(if lat.abs() >= c.merge_lateral_m {
            format!(
                "moved {:.1} m to the {} from {:.2} s to {:.2} s without a matching turn \
                 signal: short of the {} m an unsignalled lane change needs",
                lat.abs(),
                side(lat),
                self.t[i],
                self.t[j],
                c.merge_lateral_unsignalled_m
            )
        } else if lat.abs() >= c.merge_clear_m {
            format!(
                "lateral motion of {:.1} m: between the clear level {} m and the lane-change \
                 level {} m",
                lat.abs(),
                c.merge_clear_m,
                c.merge_lateral_m
            )
        } else {
            "a turn signal was on that no turn explains, without lateral motion".to_string()
        })
    }
}

/// Ends tried per lane-change window start.
const WINDOW_ENDS: usize = 64;

/// The sideways offset (m, + left) of a displacement `(dx, dy)` between two points driven
/// through with headings `pi`, `pj` (°). Measured in both end frames; when they disagree in
/// sign the offset is taken as 0, else the smaller. Why not one frame: with headings a few
/// degrees apart, a long straight after a bend (or after the peak of a lane change) drifts
/// sideways in either end's frame by length × sin(difference), and that drift has opposite
/// signs in the two frames, whereas a lane change between parallel headings moves the same
/// way in both.
fn lateral(dx: f64, dy: f64, pi: f64, pj: f64) -> f64 {
    let side = |h: f64| {
        let h = h.to_radians();
        -dx * h.sin() + dy * h.cos()
    };
    let (a, b) = (side(pi), side(pj));
    if a * b <= 0.0 {
        0.0
    } else {
        a.signum() * a.abs().min(b.abs())
    }
}

fn derived(label: &str, value: bool, confidence: f64, evidence: Vec<Evidence>) -> Derived {
    Derived {
        label: label.to_string(),
        value,
        confidence,
        evidence,
    }
}

/// The largest change of the heading in direction `dir` (+1 rise = left, −1 fall = right)
/// within `window_s`, over samples `[s, e)`.
#[derive(Debug, Clone, Copy)]
struct Swing {
    amount: f64,
    start: usize,
    end: usize,
}

/// `max over j of dir·(ψ_j − ψ_i)` for `t_j − window_s ≤ t_i ≤ t_j`: a sliding-window
/// minimum of `dir·ψ` (monotonic queue), O(samples).
fn max_swing(
    t: &[f64],
    psi: &[Option<f64>],
    s: usize,
    e: usize,
    window_s: f64,
    dir: f64,
) -> Option<Swing> {
    let h = |k: usize| dir * psi[k].unwrap_or(0.0);
    let mut q: VecDeque<usize> = VecDeque::new();
    let mut best: Option<Swing> = None;
    for j in s..e {
        while q.back().is_some_and(|&b| h(b) >= h(j)) {
            q.pop_back();
        }
        q.push_back(j);
        while q.front().is_some_and(|&f| t[j] - t[f] > window_s) {
            q.pop_front();
        }
        if let Some(&i) = q.front() {
            let amount = h(j) - h(i);
            if best.is_none_or(|b| amount > b.amount) {
                best = Some(Swing {
                    amount,
                    start: i,
                    end: j,
                });
            }
        }
    }
    best
}
